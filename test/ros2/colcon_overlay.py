"""The colcon overlay of the ``ros2`` tier: rcbf_ros built as README.md says, once per pytest run.

The workspace follows README.md "On a ROS 2 Jazzy machine": a virtual environment with the
system's site-packages, made before colcon runs; colcon run as ``python -m colcon`` from it, so
that every node script starts that environment's Python; ``source install/setup.bash``.
Here the "system" Python is the one of the Jazzy install (its ``ros2`` script's interpreter)
and two ``.pth`` files stand in for what a stock machine has without network access: the Jazzy
environment's site-packages (apt's colcon, numpy, PyYAML) and this checkout's virtual
environment's (what ``pip install`` puts into the new one: torch, osqp, ...).

Test modules make their ``overlay`` fixture with :func:`overlay_fixture` (on
:func:`shared_overlay`): the first one builds the workspace, the others reuse it. They take
``stop_group`` from here too.
"""
from __future__ import annotations

from pathlib import Path
import shutil
import sys
import sysconfig
import time
from typing import Callable

import pytest

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO / 'test'))
from conftest import Jazzy, stop_group  # noqa: E402

__all__ = ['Overlay', 'overlay_fixture', 'shared_overlay', 'stop_group', 'wait_for']

PACKAGE_FILES = ('setup.py', 'setup.cfg', 'package.xml', 'README.md', 'constraints.txt')
PACKAGE_DIRS = ('rcbf_ros', 'sim_nodes', 'config', 'launch', 'resource')
_BUILT: dict[Jazzy, Overlay] = {}


class Overlay:
    """A colcon workspace with rcbf_ros built in it."""

    def __init__(self, jazzy: Jazzy, workspace: Path) -> None:
        self.jazzy = jazzy
        self.workspace = workspace

    def script(self, command: str) -> str:
        return f'source {self.workspace}/install/setup.bash && {command}'

    def share(self) -> Path:
        return self.workspace / 'install' / 'rcbf_ros' / 'share' / 'rcbf_ros'

    def python(self, script: Path, *args: str) -> str:
        """A command running ``script`` on the overlay's Python (rclpy and rcbf_ros found)."""
        return self.script(f'{self.workspace}/venv/bin/python {script} {" ".join(args)}')


def build_overlay(jazzy: Jazzy, workspace: Path) -> Overlay:
    """Copy the package into ``workspace/src`` and build it with colcon from a venv."""
    source = workspace / 'src' / 'rcbf_ros'
    source.mkdir(parents=True)
    for name in PACKAGE_FILES:
        shutil.copy2(REPO / name, source / name)
    for name in PACKAGE_DIRS:
        shutil.copytree(REPO / name, source / name,
                        ignore=shutil.ignore_patterns('__pycache__', '*.egg-info'))
    site = 'venv/lib/python3.*/site-packages'
    done = jazzy.run(
        'PY=$(head -1 "$(command -v ros2)" | cut -c3-)\n'
        '"$PY" -m venv --system-site-packages --without-pip venv\n'
        'touch venv/COLCON_IGNORE\n'
        f'ROS_PY_SITE=$("$PY" -c "import sysconfig; print(sysconfig.get_path(\'purelib\'))")\n'
        f'echo "$ROS_PY_SITE" > $(echo {site})/system_packages.pth\n'
        f'echo {sysconfig.get_path("purelib")} > $(echo {site})/pip_installed.pth\n'
        'source venv/bin/activate\n'
        'python -m colcon build --packages-select rcbf_ros --event-handlers console_direct-\n',
        domain_id=0, cwd=workspace, timeout=300)
    assert done.returncode == 0, done.stdout[-4000:]
    built = Overlay(jazzy, workspace)
    script = workspace / 'install' / 'rcbf_ros' / 'lib' / 'rcbf_ros' / 'safety_filter'
    assert script.read_text().splitlines()[0] == f'#!{workspace}/venv/bin/python'
    return built


def shared_overlay(jazzy: Jazzy, tmp_path_factory: pytest.TempPathFactory) -> Overlay:
    """The overlay for ``jazzy`` of this pytest run, built on first use."""
    if jazzy not in _BUILT:
        _BUILT[jazzy] = build_overlay(jazzy, tmp_path_factory.mktemp('ws'))
    return _BUILT[jazzy]


def overlay_fixture() -> Callable[..., Overlay]:
    """A module-scoped ``overlay`` fixture: ``overlay = overlay_fixture()`` in a test module."""
    @pytest.fixture(scope='module', name='overlay')
    def overlay(jazzy: Jazzy, tmp_path_factory: pytest.TempPathFactory) -> Overlay:
        return shared_overlay(jazzy, tmp_path_factory)
    return overlay


def wait_for(check: Callable[[], str | None], timeout: float, what: str) -> str:
    """Poll ``check`` every second until it returns text."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        result = check()
        if result is not None:
            return result
        time.sleep(1.0)
    raise AssertionError(f'{what} did not happen in {timeout} s')
