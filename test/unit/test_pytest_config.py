"""pytest starts with a ROS 2 Jazzy sourced: its launch_testing plugin stays out.

Jazzy's launch_testing (3.4) registers the pytest11 entry point ``launch_testing`` whose hooks
take the ``path`` argument pytest 9 no longer passes, so loading it fails with a
``PluginValidationError`` before any test runs. launch_testing_ros (0.26, in ros_core, so on
every Jazzy install) registers ``launch_ros``, which implements a hook that only
launch_testing's own hook specification declares: with launch_testing left out, pytest rejects
it as an unknown hook. Stand-in distributions with the same entry point names and hooks show
each failure, and that the project's config avoids them.
"""
from __future__ import annotations

from pathlib import Path
import subprocess
import sys

import pytest

REPO = Path(__file__).resolve().parents[2]


PLUGINS = {
    # distribution: (version, entry point name, module, its hook)
    'launch_testing': ('3.4.2', 'launch_testing', 'launch_testing.pytest.hooks',
                       'def pytest_pycollect_makemodule(path, parent):\n    return None\n'),
    'launch_testing_ros': ('0.26.5', 'launch_ros', 'launch_testing_ros_pytest_entrypoint',
                           'def pytest_launch_collect_makemodule(path, parent, entrypoint):\n'
                           '    return None\n'),
}


def _fake_site(root: Path, distributions: tuple[str, ...]) -> Path:
    """A site directory with stand-ins of these Jazzy distributions' pytest plugins."""
    site = root / 'site'
    for name in distributions:
        version, entry, module, hook = PLUGINS[name]
        path = site.joinpath(*module.split('.')).with_suffix('.py')
        path.parent.mkdir(parents=True, exist_ok=True)
        for package in list(path.relative_to(site).parents)[:-1]:
            (site / package / '__init__.py').touch()
        path.write_text(hook)
        info = site / f'{name}-{version}.dist-info'
        info.mkdir()
        (info / 'METADATA').write_text(f'Metadata-Version: 2.1\nName: {name}\n'
                                       f'Version: {version}\n')
        (info / 'entry_points.txt').write_text(f'[pytest11]\n{entry} = {module}\n')
    return site


def _pytest(tmp_path: Path, site: Path, *config: str) -> subprocess.CompletedProcess:
    test = tmp_path / 'test_one.py'
    test.write_text('def test_one():\n    pass\n')
    return subprocess.run(
        [sys.executable, '-m', 'pytest', '-q', '-p', 'no:cacheprovider', *config, str(test)],
        cwd=tmp_path, capture_output=True, text=True, timeout=120,
        env={'PATH': '/usr/bin:/bin', 'PYTHONPATH': str(site)})


@pytest.mark.parametrize('distributions', [('launch_testing',), ('launch_testing_ros',),
                                           ('launch_testing', 'launch_testing_ros')])
def test_pytest_starts_with_jazzys_launch_testing_plugins_on_the_path(tmp_path, distributions):
    site = _fake_site(tmp_path, distributions)
    (tmp_path / 'pytest.ini').write_text('[pytest]\n')
    bare = _pytest(tmp_path, site, '-c', str(tmp_path / 'pytest.ini'))
    assert bare.returncode != 0 and 'PluginValidationError' in bare.stdout + bare.stderr
    ours = _pytest(tmp_path, site, '-c', str(REPO / 'pyproject.toml'),
                   '--rootdir', str(tmp_path))
    assert ours.returncode == 0, ours.stdout + ours.stderr
    assert '1 passed' in ours.stdout
