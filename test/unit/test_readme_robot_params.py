"""The README's params file for a TurtleBot-sized robot builds the filter it describes.

The block is read from README.md as a user would copy it, and parsed as a ROS 2 params file
for the safety_filter node (``/**`` then ``/safety_filter``).
"""
from __future__ import annotations

from pathlib import Path
import re

import numpy as np

from rcbf_ros.bag.refilter import build_filter, resolve_params

README = Path(__file__).resolve().parents[2] / 'README.md'


def robot_yaml() -> str:
    section = README.read_text().split('### On your robot', 1)[1]
    return re.search(r'```yaml\n(.*?)```', section, re.S).group(1)


def test_the_readme_robot_params_build_a_lidar_only_filter(tmp_path: Path) -> None:
    path = tmp_path / 'robot.yaml'
    path.write_text(robot_yaml())
    flat = resolve_params(path)
    config, settings, safety_filter = build_filter(flat)
    assert settings.state_frame_id == 'odom'
    assert flat['footprint.radius'] == 0.18 and flat['scan.topic'] == '/scan'
    assert config.sources is not None and [name for name, _ in config.sources.sources] == ['scan']
    # the lidar's points are its rows: a point 0.5 m ahead brakes a robot driving at it
    state, u = np.array([0.0, 0.0, 0.0]), np.array([0.3, 0.0])
    safety_filter.set_points(np.zeros((0, 2)))
    assert np.allclose(safety_filter.filter(state, u).u_safe, u)
    safety_filter.set_points(np.array([[0.45, 0.0]]))
    result = safety_filter.filter(state, u)
    assert not result.fail_safe and result.u_safe[0] < 0.3 - 1e-3
