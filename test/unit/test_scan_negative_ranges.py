"""LaserScan: a negative range is invalid (REP 117), whatever range_min says; it is never read
as a point mirrored through the sensor. The scans are encoded by rosbags' Jazzy type store."""
from __future__ import annotations

import math

from hypothesis import given, settings
from hypothesis import strategies as st
import numpy as np
from sensor_messages import scan_bytes

from rcbf_ros.messages import sensor


def test_a_negative_range_is_skipped_even_below_a_negative_range_min():
    out = sensor.scan_points(scan_bytes([-2.0, 1.0, 1.0], increment=0.5, range_min=-5.0))
    assert isinstance(out, sensor.SensorPoints)
    np.testing.assert_allclose(out.points, [[math.cos(0.5), math.sin(0.5)],
                                            [math.cos(1.0), math.sin(1.0)]], atol=1e-6)


@settings(max_examples=200, deadline=None)
@given(ranges=st.lists(st.floats(-20.0, 20.0, width=32), max_size=20),
       range_min=st.floats(-10.0, 1.0, width=32), range_max=st.floats(0.0, 30.0, width=32))
def test_the_points_of_a_scan_are_its_ranges_within_bounds_and_never_negative(
        ranges, range_min, range_max):
    out = sensor.scan_points(scan_bytes(ranges, angle_min=0.0, increment=0.25,
                                        range_min=range_min, range_max=range_max))
    if range_min > range_max:
        assert isinstance(out, sensor.Refused)
        return
    kept = [(i, r) for i, r in enumerate(ranges) if max(range_min, 0.0) <= r <= range_max]
    assert isinstance(out, sensor.SensorPoints)
    np.testing.assert_allclose(out.points.reshape(-1, 2),
                               np.array([(r * math.cos(0.25 * i), r * math.sin(0.25 * i))
                                         for i, r in kept]).reshape(-1, 2), atol=1e-5)
