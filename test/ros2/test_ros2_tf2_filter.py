"""On real rclpy the safety filter places its sources' points through tf2_ros's own Buffer.

rclpy_tf2_filter.py runs the filter node on a Jazzy's rclpy, this checkout first on the path,
with a scan source in ``laser``; a robot node in the same process publishes /tf_static
base_link -> laser, /tf odom -> base_link (two samples, 2 s apart) and the scans. Checked here:

- tf2_ros's Buffer answers (the lookup's ``backend``; the log line saying so), and /tf and
  /tf_static have one subscription each (tf2_ros's listener's, not ours besides);
- points land where the closed form puts them: a scan between the two odom samples at the
  interpolated pose, one 0.05 s after the newest at the newest pose (``transform_tolerance``
  0.1 s);
- a scan 0.2 s after the newest or before the oldest, or in a frame tf does not know: the
  fail-safe's reason, naming both frames;
- a NaN transform: refused, counted in ``tf.transforms_refused`` and said in one WARN line, as
  on our runtime.
"""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from test_ros2_integration import rclpy_python

pytestmark = pytest.mark.ros2
HERE = Path(__file__).resolve().parent
REPO = HERE.parents[1]
MOUNT = (0.3, -0.1), 0.4
"""As rclpy_tf2_filter.py: the laser's (x, y) on base_link and its yaw."""
BEAMS = (-0.2, 0.1, [1.0, 2.0, 0.5])
"""As rclpy_tf2_filter.py: angle_min, increment, ranges."""


def closed_form(pose: tuple[float, float, float]) -> np.ndarray:
    """The scan's beams in odom, for base_link at ``pose`` (x, y, yaw)."""
    (mx, my), mount_yaw = MOUNT
    x, y, yaw = pose
    angle_min, increment, ranges = BEAMS
    out = []
    for k, r in enumerate(ranges):
        a = mount_yaw + angle_min + k * increment
        bx, by = mx + r * math.cos(a), my + r * math.sin(a)
        out.append((x + bx * math.cos(yaw) - by * math.sin(yaw),
                    y + bx * math.sin(yaw) + by * math.cos(yaw)))
    return np.array(out)


def test_the_filter_on_rclpy_places_points_through_tf2_ros(jazzy, tmp_path, ros_domain_id):
    python = rclpy_python(jazzy, tmp_path)
    done = jazzy.run(f'export PYTHONPATH="{REPO}:$PYTHONPATH"; '
                     f'{python} {HERE / "rclpy_tf2_filter.py"} {REPO / "config/unicycle.yaml"}',
                     domain_id=ros_domain_id, cwd=REPO, timeout=240,
                     env={'RCBF_ROS_RUNTIME': 'rclpy'})
    if "No module named 'tf2_ros'" in done.stdout:
        pytest.skip('this Jazzy has no tf2_ros (ros2/geometry2: tf2_ros_py)')
    assert done.returncode == 0, done.stdout[-4000:]
    out = json.loads(done.stdout.strip().splitlines()[-1])
    log = done.stdout
    assert out['backend'] == 'tf2_ros', out
    assert 'tf: tf2_ros Buffer and TransformListener (cache 10 s) on /tf and /tf_static' in log
    assert out['tf_subscriptions'] == ['/tf', '/tf_static'], out
    # odom -> base_link at 9 s (1, 2, yaw 0.2) and 11 s (3, 0, yaw 0.6): at 10 s, halfway
    np.testing.assert_allclose(out['interpolated'], closed_form((2.0, 1.0, 0.4)), atol=1e-9)
    np.testing.assert_allclose(out['held'], closed_form((3.0, 0.0, 0.6)), atol=1e-9)
    t0 = out['t0_s']  # the stamps: seconds after t0
    assert out['too_old'].startswith(
        f"source front: no transform from 'laser' to 'odom' at {t0 + 11}.200 s: too old: the "
        f'newest is at {t0 + 11}.000 s, 0.200 s before (transform_tolerance 0.100 s)'), out
    assert out['too_new'].startswith(
        f"source front: no transform from 'laser' to 'odom' at {t0 + 8}.800 s: too new: a "
        f'link starts at {t0 + 9}.000 s, 0.200 s after (transform_tolerance 0.100 s)'), out
    assert out['missing'].startswith(
        "source front: frame 'laser2' is placed neither in the state's 'odom' nor in the "
        "robot's 'base_link' by tf"), out
    np.testing.assert_allclose(out['after_nan'], out['held'])
    assert out['counts'] == {'messages': 4, 'refused': 0, 'transforms_refused': 1}, out
    assert ("/tf refused: transforms[0] 'odom' -> 'base_link': translation (nan, 0, 0) is not "
            'finite') in log
    assert 'Traceback' not in log and 'Exception ignored' not in log, log[-4000:]
