"""The layout is the architecture: every module sits in a layer or concern folder, and imports
point down only (ARCHITECTURE.md's layers, plus the concern folders around them).

Read from the sources with ``ast`` (every import, also those inside functions), so a lazy
import that climbs a layer fails here as surely as one at the top of a file.
"""
from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]

LAYERS: tuple[frozenset[str], ...] = (
    frozenset({'parameters', 'messages'}),  # leaves: ROS conventions without middleware
    frozenset({'core'}),                    # pure math
    frozenset({'learning'}),                # GP, SAC, buffers
    frozenset({'envs'}),                    # the systems as Gymnasium envs
    frozenset({'node_logic'}),              # what the nodes decide, without middleware
    frozenset({'bag'}),                     # MCAP writing, reading, recovery, re-filtering
    frozenset({'reports'}),                 # plots and run summaries
    frozenset({'training'}),                # in-process training runs
    frozenset({'experiments'}),             # the paper's experiments
    frozenset({'ros', 'sim_nodes'}),        # the nodes and the runtime
    frozenset({'launch'}),                  # launch setups and the local launcher
    frozenset({'cli'}),                     # the rcbf_ros command
)
"""Bottom first: a folder may import its own layer and the layers before it."""

RANK = {folder: rank for rank, layer in enumerate(LAYERS) for folder in layer}


def _folder(module: str) -> str | None:
    parts = module.split('.')
    if parts[0] == 'sim_nodes':
        return 'sim_nodes'
    if parts[0] == 'rcbf_ros' and len(parts) > 1:
        return parts[1]
    return None


def _sources() -> list[Path]:
    return sorted([*ROOT.glob('rcbf_ros/**/*.py'), *ROOT.glob('sim_nodes/*.py')])


def _imports(path: Path) -> list[tuple[int, str]]:
    found = []
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            found.append((node.lineno, node.module))
        elif isinstance(node, ast.Import):
            found.extend((node.lineno, alias.name) for alias in node.names)
    return found


def test_no_module_is_loose_at_the_package_top() -> None:
    loose = sorted(p.name for p in (ROOT / 'rcbf_ros').glob('*.py')
                   if p.name not in ('__init__.py', '__main__.py'))
    assert loose == [], f'modules outside any layer or concern folder: {loose}'


def test_every_folder_has_a_layer() -> None:
    folders = {p.parent.name for p in (ROOT / 'rcbf_ros').glob('*/__init__.py')}
    folders.discard('config')
    assert folders - set(RANK) == set(), 'a package folder missing from LAYERS'


@pytest.mark.parametrize('path', _sources(), ids=lambda p: str(p.relative_to(ROOT)))
def test_imports_point_down(path: Path) -> None:
    module = '.'.join(path.relative_to(ROOT).with_suffix('').parts)
    here = _folder(module)
    if here not in RANK:  # rcbf_ros/__init__.py, __main__.py
        return
    upward = [f'line {line}: {name} ({_folder(name)})' for line, name in _imports(path)
              if _folder(name) in RANK and RANK[_folder(name)] > RANK[here]]
    assert upward == [], f'{here} imports a higher layer: {upward}'
