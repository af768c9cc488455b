"""A rate or a period out of its declared range stops a node at start: one line naming the key
on stderr, exit status 2, no traceback, before any timer (or bag) exists."""
from __future__ import annotations

from dds_harness import REPO, spawn, stop  # this directory: on sys.path for pytest
import pytest

LIDAR = str(REPO / 'config' / 'unicycle_lidar.yaml')
WAIT_S = 60.0

pytestmark = pytest.mark.integration


@pytest.fixture
def domain_id(ros_domain_id: int) -> int:
    """The test's own domain, never the runner's ROS_DOMAIN_ID (shared by parallel workers)."""
    return ros_domain_id


@pytest.mark.parametrize('module, args, line', [
    ('rcbf_ros.ros.scene_node', ['--params-file', LIDAR, '-p', 'rate_hz:=1e-300'],
     'scene_markers: invalid parameters: rate_hz: must be >= 0.001, got 1e-300'),
    ('rcbf_ros.ros.scene_node', ['--params-file', LIDAR, '-p', 'rate_hz:=2e9'],
     'scene_markers: invalid parameters: rate_hz: must be <= 100.0, got 2000000000.0'),
    ('sim_nodes.unicycle_lidar_node', ['-p', 'scan_rate_hz:=1e-300'],
     'unicycle_lidar: invalid parameters: scan_rate_hz: must be >= 0.001, got 1e-300'),
    ('sim_nodes.unicycle_lidar_node', ['-p', 'rate_hz:=1e308'],
     'unicycle_lidar: invalid parameters: rate_hz: must be <= 1000.0, got 1e+308'),
    ('rcbf_ros.ros.recorder_node', ['-p', 'flush_period_s:=1e308'], 'flush_period_s'),
])
def test_a_rate_or_period_out_of_range_exits_2_in_one_line_naming_it(domain_id, tmp_path,
                                                                     module, args, line):
    bag = tmp_path / 'bag'
    extra = ['-p', f'output:={bag}'] if module.endswith('recorder_node') else []
    process = spawn(domain_id, '-m', module, '--ros-args', *args, *extra)
    try:
        process.wait(timeout=WAIT_S)
    finally:
        output = stop(process, timeout=10)
    assert process.returncode == 2, output[-2000:]
    last = output.strip().splitlines()[-1]
    assert line in last and 'Traceback' not in output, output[-2000:]
    assert len(last) < 300
    assert not bag.exists()  # the recorder refused before it opened a bag
