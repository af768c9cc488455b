"""pytest starts with a ROS 2 Jazzy sourced: its launch_testing plugin stays out.

Jazzy's launch_testing (3.4) registers the pytest11 entry point ``launch_testing`` whose hooks
take the ``path`` argument pytest 9 no longer passes, so loading it fails with a
``PluginValidationError`` before any test runs. A stand-in distribution with the same entry
point name and hook signature shows the failure, and that the project's config avoids it.
"""
from __future__ import annotations

from pathlib import Path
import subprocess
import sys

REPO = Path(__file__).resolve().parents[2]


def _fake_launch_testing(root: Path) -> Path:
    site = root / 'site'
    package = site / 'launch_testing' / 'pytest'
    package.mkdir(parents=True)
    (site / 'launch_testing' / '__init__.py').write_text('')
    (package / '__init__.py').write_text('')
    (package / 'hooks.py').write_text(
        'def pytest_pycollect_makemodule(path, parent):\n    return None\n')
    info = site / 'launch_testing-3.4.2.dist-info'
    info.mkdir()
    (info / 'METADATA').write_text('Metadata-Version: 2.1\nName: launch_testing\n'
                                   'Version: 3.4.2\n')
    (info / 'entry_points.txt').write_text(
        '[pytest11]\nlaunch_testing = launch_testing.pytest.hooks\n')
    return site


def _pytest(tmp_path: Path, site: Path, *config: str) -> subprocess.CompletedProcess:
    test = tmp_path / 'test_one.py'
    test.write_text('def test_one():\n    pass\n')
    return subprocess.run(
        [sys.executable, '-m', 'pytest', '-q', '-p', 'no:cacheprovider', *config, str(test)],
        cwd=tmp_path, capture_output=True, text=True, timeout=120,
        env={'PATH': '/usr/bin:/bin', 'PYTHONPATH': str(site)})


def test_pytest_starts_with_launch_testing_on_the_path(tmp_path):
    site = _fake_launch_testing(tmp_path)
    (tmp_path / 'pytest.ini').write_text('[pytest]\n')
    bare = _pytest(tmp_path, site, '-c', str(tmp_path / 'pytest.ini'))
    assert bare.returncode != 0 and 'PluginValidationError' in bare.stdout + bare.stderr
    ours = _pytest(tmp_path, site, '-c', str(REPO / 'pyproject.toml'),
                   '--rootdir', str(tmp_path))
    assert ours.returncode == 0, ours.stdout + ours.stderr
    assert '1 passed' in ours.stdout
