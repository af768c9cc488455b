"""No ros2cli daemon outlives the test that started it (conftest.stop_ros2_daemons): one left
running joins its domain's graph, where a later test drawing the same domain id would see it."""
from __future__ import annotations

from pathlib import Path
import sys

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from conftest import stop_ros2_daemons  # noqa: E402

pytestmark = pytest.mark.ros2


def test_the_daemon_a_ros2_command_leaves_is_stopped(jazzy, ros_domain_id):
    started = jazzy.run('ros2 topic list > /dev/null; ros2 daemon status',
                        domain_id=ros_domain_id, timeout=60)
    assert 'The daemon is running' in started.stdout, started.stdout
    stop_ros2_daemons(jazzy, {ros_domain_id})
    status = jazzy.run('ros2 daemon status || true', domain_id=ros_domain_id, timeout=60)
    assert 'The daemon is not running' in status.stdout, status.stdout
