"""Setup for every test: loopback-only DDS and single-threaded torch, before anything else;
and the ``ros2`` tier's access to a real ROS 2 Jazzy (skipped, with the reason, without one)."""
from __future__ import annotations

import contextlib
import dataclasses
from dataclasses import dataclass
import functools
import itertools
import os
from pathlib import Path
import shlex
import shutil
import signal
import subprocess
import sysconfig
from typing import Mapping

from hypothesis import settings
import pytest

from rcbf_ros.ros.loopback import ensure_loopback

# CI runs the property tests on Hypothesis's fixed, per-test example sequence, so that a run
# is repeatable; a local run keeps searching new examples (where it finds a failure, add it
# to the test with @example).
settings.register_profile('ci', derandomize=True, database=None)
if os.environ.get('CI') == 'true':
    settings.load_profile('ci')

# Before any DDS participant can exist: no traffic may leave the machine.
ensure_loopback(force=True)
# The suite tests our Cyclone runtime, also where a sourced ROS 2 would make runtime.py pick
# rclpy; the ros2 tier reaches real rclpy through its own commands (Jazzy.environment).
os.environ.setdefault('RCBF_ROS_RUNTIME', 'cyclone')

_domain_counter = itertools.count()


@pytest.fixture
def ros_domain_id() -> int:
    """A ROS_DOMAIN_ID of this test's own, so parallel runs and tests never cross.

    Derived from the pid so that two pytest processes on one machine pick different ids;
    kept in 1..200 (valid DDS domain ids that leave room for the port arithmetic).
    """
    return 1 + (os.getpid() * 7 + next(_domain_counter)) % 200


def pytest_configure(config):
    try:
        import torch
        torch.set_num_threads(1)
    except ImportError:
        pass


# --- the ros2 tier: real Jazzy (rclpy, ros2cli, launch_ros, rosbag2) as the oracle -------------
JAZZY_SETUP = Path(os.environ.get('RCBF_JAZZY_SETUP', '/opt/rcbf_jazzy/install/setup.bash'))
"""The Jazzy install the ``ros2`` tests source when none is sourced already."""
JAZZY_PACKAGES = ('rclpy', 'rmw_cyclonedds_cpp', 'ros2cli', 'ros2launch', 'launch_ros',
                  'ros2bag', 'rosbag2_storage_mcap', 'ros2param', 'std_msgs')
"""What the tier needs of that install."""


@dataclass(frozen=True)
class Jazzy:
    """A ROS 2 Jazzy to run commands in: ``bash -c 'source <setup> && <command>'``.

    Commands get the loopback ``CYCLONEDDS_URI``, ``RMW_IMPLEMENTATION=rmw_cyclonedds_cpp``,
    the test's ``ROS_DOMAIN_ID``, and none of this test environment's Python settings that
    would leak into ROS's Python (the Cyclone runtime choice).
    """

    setup: Path | None
    """setup.bash to source; None: Jazzy is sourced in this environment already."""
    log_dir: Path | None = None
    """ROS_LOG_DIR of the commands (None: ROS's default, ~/.ros/log)."""

    def environment(self, domain_id: int, extra: Mapping[str, str] | None = None
                    ) -> dict[str, str]:
        _JAZZY_DOMAINS.add(domain_id)
        env = {k: v for k, v in os.environ.items() if k != 'RCBF_ROS_RUNTIME'}
        ensure_loopback(env, force=True)
        env.update(RMW_IMPLEMENTATION='rmw_cyclonedds_cpp', ROS_DOMAIN_ID=str(domain_id),
                   PYTHONUNBUFFERED='1', OMP_NUM_THREADS='1')
        if self.log_dir is not None:
            env['ROS_LOG_DIR'] = str(self.log_dir)
        env.update(extra or {})
        return env

    def command(self, script: str) -> list[str]:
        """``bash -c`` with the install sourced first (``set -e``)."""
        source = f'source {shlex.quote(str(self.setup))} && ' if self.setup else ''
        return ['bash', '-c', f'set -e; {source}{script}']

    @staticmethod
    def python_module(module: str, arguments: str = '') -> str:
        """The script that runs ``python -m module arguments`` with the install's interpreter
        (the one ros2cli runs on) and this repository importable, on rclpy
        (``RCBF_ROS_RUNTIME=rclpy``)."""
        repo = Path(__file__).resolve().parents[1]
        path = f'{repo}:{sysconfig.get_path("purelib")}'
        return ('PY=$(head -1 "$(command -v ros2)" | cut -c3-); '
                f'PYTHONPATH="$PYTHONPATH:{path}" RCBF_ROS_RUNTIME=rclpy exec "$PY" -m '
                f'{module} {arguments}').rstrip()

    def run(self, script: str, *, domain_id: int, timeout: float = 120.0,
            cwd: Path | None = None, env: Mapping[str, str] | None = None
            ) -> subprocess.CompletedProcess:
        """Run ``script`` to its end; its output as text (stdout and stderr together)."""
        return subprocess.run(self.command(script), cwd=cwd, timeout=timeout, text=True,
                              stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                              env=self.environment(domain_id, env))

    def start(self, script: str, *, domain_id: int, log: Path, cwd: Path | None = None,
              env: Mapping[str, str] | None = None) -> subprocess.Popen:
        """Start ``script`` in its own process group, output to ``log``; stop it with
        :func:`stop_group`."""
        return subprocess.Popen(self.command(script), cwd=cwd, start_new_session=True,
                                stdout=log.open('w'), stderr=subprocess.STDOUT,
                                env=self.environment(domain_id, env))


_JAZZY_DOMAINS: set[int] = set()
"""The domains Jazzy commands ran on since the last :func:`stop_ros2_daemons`."""


def stop_ros2_daemons(jazzy: Jazzy, domains: set[int]) -> None:
    """``ros2 daemon stop`` on each of ``domains``.

    A ros2cli command without ``--no-daemon`` leaves a daemon behind, a participant of its
    domain that outlives the test and the run: a later test that draws the same domain id
    (another pytest process, such as the integration suite the tier runs on rclpy) would see
    its node in the graph."""
    if not domains:
        return
    loop = ' '.join(str(domain) for domain in sorted(domains))
    jazzy.run(f'for d in {loop}; do ROS_DOMAIN_ID=$d ros2 daemon stop || true; done',
              domain_id=0, timeout=60 + 10 * len(domains))


@pytest.fixture(autouse=True)
def _no_ros2_daemon_outlives_its_test():
    _JAZZY_DOMAINS.clear()
    yield
    domains = set(_JAZZY_DOMAINS)
    _JAZZY_DOMAINS.clear()
    if domains:
        found, _ = find_jazzy()
        if found is not None:
            stop_ros2_daemons(found, domains)


def stop_group(process: subprocess.Popen, *, timeout: float = 20.0) -> int:
    """SIGINT to the process group we started, then SIGKILL if it does not end in time."""
    if process.poll() is None:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(process.pid, signal.SIGINT)
        try:
            process.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(process.pid, signal.SIGKILL)
            process.wait()
    return process.returncode


@functools.cache
def find_jazzy() -> tuple[Jazzy | None, str]:
    """The Jazzy to test against and where it is, or None and why there is none."""
    if os.environ.get('ROS_DISTRO') == 'jazzy' and shutil.which('ros2'):
        jazzy, where = Jazzy(None), 'the sourced ROS 2 Jazzy'
    elif JAZZY_SETUP.is_file():
        jazzy, where = Jazzy(JAZZY_SETUP), str(JAZZY_SETUP)
    else:
        return None, (f'no ROS 2 Jazzy: none sourced (ROS_DISTRO) and no {JAZZY_SETUP} '
                      '(RCBF_JAZZY_SETUP names another)')
    try:
        probe = jazzy.run('echo "distro=$ROS_DISTRO"; ros2 pkg list', domain_id=0, timeout=60)
    except (OSError, subprocess.TimeoutExpired) as exc:
        return None, f'{where}: ros2 pkg list failed ({exc})'
    lines = probe.stdout.split()
    missing = [name for name in JAZZY_PACKAGES if name not in lines]
    if probe.returncode != 0 or 'distro=jazzy' not in lines or missing:
        return None, (f'{where} is not a usable Jazzy (exit {probe.returncode}, '
                      f'missing {missing or "nothing"})')
    return jazzy, where


@pytest.fixture(scope='session')
def jazzy(tmp_path_factory) -> Jazzy:
    """The Jazzy of the ``ros2`` tier (the tests are skipped without one); ROS logs go to a
    temporary directory."""
    found, reason = find_jazzy()
    if found is None:
        pytest.skip(reason)
    return dataclasses.replace(found, log_dir=tmp_path_factory.mktemp('ros_log'))


def pytest_collection_modifyitems(config, items):
    tier = [item for item in items if item.get_closest_marker('ros2')]
    config.stash[_ROS2_TIER] = len(tier)
    if not tier:
        return
    found, reason = find_jazzy()
    if found is None:
        for item in tier:
            item.add_marker(pytest.mark.skip(reason=reason))


def pytest_terminal_summary(terminalreporter, exitstatus, config):
    """One line: whether the ros2 tier ran, against which Jazzy, or why not."""
    count = config.stash.get(_ROS2_TIER, 0)
    if not count:
        line = 'ros2 tier: not selected'
    else:
        found, reason = find_jazzy()
        outcomes = {key: 0 for key in ('passed', 'failed', 'skipped', 'error')}
        for key in outcomes:
            outcomes[key] = sum(1 for r in terminalreporter.stats.get(key, [])
                                if getattr(r, 'when', 'call') in ('call', 'setup')
                                and 'ros2' in getattr(r, 'keywords', {}))
        if found is None:
            line = f'ros2 tier: skipped ({count} tests): {reason}'
        else:
            done = ', '.join(f'{n} {key}' for key, n in outcomes.items() if n)
            line = f'ros2 tier: ran against {reason}: {done or "nothing run"}'
    terminalreporter.write_line(line)
    report = os.environ.get('RCBF_ROS2_TIER_REPORT')
    if report:
        Path(report).write_text(line + '\n')


_ROS2_TIER = pytest.StashKey[int]()
