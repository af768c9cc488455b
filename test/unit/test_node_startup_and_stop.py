"""How a node process starts: a bad params file is refused at init, in one line."""
from __future__ import annotations

from pathlib import Path

import pytest

from rcbf_ros.ros.dds.context import Context
from rcbf_ros.ros.node_main import run_node

REPO = Path(__file__).resolve().parents[2]


# --- params file -------------------------------------------------------------------------------

@pytest.mark.parametrize('content, expected', [
    (None, 'No such file or directory'),
    ('a: [1\n', 'not valid YAML at line 2, column 1'),
    ('- 1\n', 'top level must map node names'),
])
def test_a_node_refuses_a_bad_params_file_in_one_line_before_joining_dds(tmp_path, capsys,
                                                                        content, expected):
    path = tmp_path / 'params.yaml'
    if content is not None:
        path.write_text(content)
    built = []
    code = run_node('probe', lambda: built.append(1),
                    ['probe', '--ros-args', '--params-file', str(path)])
    assert code == 2 and not built
    lines = capsys.readouterr().err.splitlines()
    assert len(lines) == 1 and lines[0].startswith(f'probe: --params-file {str(path)!r}: ')
    assert expected in lines[0]


def test_params_files_are_read_when_the_context_is_initialized(tmp_path, ros_domain_id):
    context = Context()
    with pytest.raises(ValueError, match='missing.yaml'):
        context.init(['--ros-args', '--params-file', str(tmp_path / 'missing.yaml')],
                     domain_id=ros_domain_id)
    assert not context.ok() and context.participant is None
