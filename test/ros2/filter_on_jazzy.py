"""The safety filter run on a real Jazzy's rclpy for a test, and ``ros2`` commands beside it."""
from __future__ import annotations

from collections.abc import Callable, Iterator
import contextlib
from pathlib import Path
import sys
from typing import Any, NamedTuple

from colcon_overlay import wait_for

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO / 'test'))
from conftest import stop_group  # noqa: E402

WAIT_S = 90.0
"""How long the node may take to start, and a ``ros2`` command's effect to show."""


class FilterRun(NamedTuple):
    """A running filter: its log file, a ``ros2 ...`` command runner on its domain (the
    command's stdout), and its process."""

    log: Path
    ros2: Callable[[str], str]
    node: Any


@contextlib.contextmanager
def filter_on_jazzy(jazzy: Any, tmp_path: Path, domain_id: int, arguments: str = ''
                    ) -> Iterator[FilterRun]:
    """The safety_filter node on the Jazzy's rclpy with config/unicycle.yaml and
    ``arguments`` (more ``--ros-args``), once it said it started. On leaving the block it must
    still run; it is then stopped, and must exit 0 without a traceback in its log."""
    log = tmp_path / 'safety_filter.log'
    node = jazzy.start(jazzy.python_module(
        'rcbf_ros.ros.safety_filter_node',
        f'--ros-args --params-file {REPO / "config" / "unicycle.yaml"} {arguments}'.rstrip()),
        domain_id=domain_id, log=log)

    def ros2(command: str) -> str:
        return jazzy.run(command, domain_id=domain_id, timeout=60).stdout

    try:
        wait_for(lambda: '' if 'barriers on unicycle' in log.read_text() else None,
                 WAIT_S, 'the safety_filter started')
        yield FilterRun(log, ros2, node)
        assert node.poll() is None, log.read_text()[-3000:]
    finally:
        code = stop_group(node)
    output = log.read_text()
    assert code == 0 and 'Traceback' not in output, output[-3000:]
