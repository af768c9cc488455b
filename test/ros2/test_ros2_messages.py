"""Our runtime's messages start as rclpy's do: every type both know, default-constructed and
serialized, gives the same bytes (declared defaults such as Quaternion's w = 1 included)."""
from __future__ import annotations

import json
from pathlib import Path

import pytest

from rcbf_ros.messages.cdr import serialize_message
from rcbf_ros.messages.classes import get_message
from rcbf_ros.messages.typestore import jazzy_typestore as typestore

pytestmark = pytest.mark.ros2
HERE = Path(__file__).resolve().parent


def test_default_messages_serialize_as_rclpys(jazzy, tmp_path, ros_domain_id):
    names = sorted(name for name in typestore().fielddefs if '/msg/' in name)
    listing = tmp_path / 'types.txt'
    listing.write_text('\n'.join(names))
    done = jazzy.run(f'PY=$(head -1 "$(command -v ros2)" | cut -c3-); '
                     f'"$PY" {HERE / "rclpy_defaults.py"} {listing}',
                     domain_id=ros_domain_id, timeout=120)
    assert done.returncode == 0, done.stdout[-3000:]
    theirs = json.loads(done.stdout.strip().splitlines()[-1])
    assert len(theirs) > 100, sorted(theirs)  # std, geometry, nav, sensor, diagnostic, ...
    different = [name for name, data in theirs.items()
                 if serialize_message(get_message(name)()).hex() != data]
    assert not different, different


def test_rclpys_range_readings_read_as_their_arcs(jazzy, tmp_path, ros_domain_id):
    """sensor_msgs/Range as rclpy serializes it: our reader gives the bytes' arc (the bytes
    equal rosbags' encoding of the same message, which the unit tests' oracles check)."""
    import math

    import numpy as np

    from rcbf_ros.messages import sensor
    done = jazzy.run(f'PY=$(head -1 "$(command -v ros2)" | cut -c3-); '
                     f'"$PY" {HERE / "rclpy_ranges.py"}', domain_id=ros_domain_id, timeout=120)
    assert done.returncode == 0, done.stdout[-3000:]
    store = typestore()
    t = store.types
    for reading, field_of_view, data in json.loads(done.stdout.strip().splitlines()[-1]):
        theirs = bytes.fromhex(data)
        msg = t[sensor.RANGE](
            header=t['std_msgs/msg/Header'](
                stamp=t['builtin_interfaces/msg/Time'](sec=12, nanosec=345), frame_id='sonar'),
            radiation_type=0, field_of_view=field_of_view, min_range=0.02, max_range=4.0,
            range=float(reading), variance=0.0)
        assert bytes(store.serialize_cdr(msg, sensor.RANGE)) == theirs, reading
        out = sensor.range_points(theirs)
        assert not isinstance(out, sensor.Refused), (reading, out)
        assert (out.frame_id, out.stamp_ns) == ('sonar', 12 * 10**9 + 345)
        r = float(reading)
        if math.isnan(r) or r == math.inf:
            assert out.points.shape == (0, 2), reading
            continue
        half = float(np.float32(field_of_view)) / 2
        nearest = math.cos(half) if half <= math.pi / 2 else 0.0
        # the middle of the band a cone at r projects to; -inf: of the sector within min_range
        radius = 0.01 if r == -math.inf else float(np.float32(r)) * (1 + nearest) / 2
        np.testing.assert_allclose(np.hypot(*out.points.T), radius, rtol=1e-6)
