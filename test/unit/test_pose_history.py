"""The robot's pose by stamp (rcbf_ros.node_logic.pose_history): tf's lookup rules on a planar
pose, against closed forms; any input one line or a pose, never a raise."""
from __future__ import annotations

import math

from hypothesis import given, settings
from hypothesis import strategies as st
import pytest

from rcbf_ros.node_logic.pose_history import PoseHistory

S = 1_000_000_000


def test_a_stamp_between_two_states_is_interpolated_the_heading_along_the_shorter_arc():
    poses = PoseHistory()
    assert poses.add(10 * S, 0.0, 1.0, 3.0) == ''
    assert poses.add(11 * S, 2.0, -1.0, -3.0) == ''  # 0.28 rad on across +-pi, not 6 back
    x, y, heading = poses.at(10 * S + S // 4, tolerance_ns=0)
    assert (x, y) == pytest.approx((0.5, 0.5))
    assert math.remainder(heading - (3.0 + 0.25 * (2 * math.pi - 6.0)), math.tau) == \
        pytest.approx(0.0, abs=1e-12)


def test_outside_the_states_a_pose_is_held_within_the_tolerance_else_refused():
    poses = PoseHistory()
    poses.add(10 * S, 1.0, 2.0, 0.5)
    poses.add(11 * S, 3.0, 2.0, 0.5)
    assert poses.at(11 * S + 100, tolerance_ns=100) == (3.0, 2.0, 0.5)
    assert poses.at(10 * S - 100, tolerance_ns=100) == (1.0, 2.0, 0.5)
    assert poses.at(11 * S + 101, tolerance_ns=100) == (
        'the newest state is 0.000 s older than the message (tolerance 0.000 s)')
    assert poses.at(9 * S, tolerance_ns=S // 10) == (
        'the oldest state kept is 1.000 s newer than the message (tolerance 0.100 s)')
    assert PoseHistory().at(0, tolerance_ns=S) == 'no state yet'


def test_a_clock_that_goes_back_clears_the_history_and_old_poses_expire():
    poses = PoseHistory(cache_s=1.0, max_poses=3)
    poses.add(10 * S, 1.0, 0.0, 0.0)
    poses.add(10 * S, 2.0, 0.0, 0.0)  # the same stamp: replaced
    assert len(poses) == 1 and poses.at(10 * S, tolerance_ns=0) == (2.0, 0.0, 0.0)
    poses.add(5 * S, 0.0, 0.0, 0.0)  # a simulation restarted
    assert len(poses) == 1 and poses.clears == 1
    for k in range(1, 4):
        poses.add(5 * S + k * S // 4, float(k), 0.0, 0.0)
    assert len(poses) == 3  # at most max_poses
    poses.add(7 * S, 9.0, 0.0, 0.0)  # the others more than cache_s older
    assert len(poses) == 1


@pytest.mark.parametrize('values', [(math.nan, 0.0, 0.0), (0.0, math.inf, 0.0),
                                    (0.0, 0.0, -math.inf)])
def test_a_pose_that_is_not_finite_is_not_kept(values):
    poses = PoseHistory()
    assert poses.add(S, *values) == "the state's pose is not finite"
    assert poses.add(1.5, 0.0, 0.0, 0.0) == 'pose stamp 1.5 is not an integer'
    assert len(poses) == 0


_FINITE = st.floats(-1e6, 1e6, allow_nan=False)


@settings(max_examples=300, deadline=None)
@given(entries=st.lists(st.tuples(st.integers(-2**62, 2**62), _FINITE, _FINITE,
                                  st.floats(-1e3, 1e3, allow_nan=False)), max_size=20),
       stamp=st.integers(-2**63, 2**63 - 1), tolerance=st.integers(-2**63, 2**63 - 1))
def test_any_states_and_stamp_give_a_pose_between_its_neighbours_or_one_line(
        entries, stamp, tolerance):
    poses = PoseHistory()
    for entry in entries:
        poses.add(*entry)
    out = poses.at(stamp, tolerance_ns=tolerance)
    if isinstance(out, str):
        assert '\n' not in out and out
        return
    xs = [x for _, x, _, _ in entries]
    ys = [y for _, _, y, _ in entries]
    assert min(xs) - 1e-6 <= out[0] <= max(xs) + 1e-6
    assert min(ys) - 1e-6 <= out[1] <= max(ys) + 1e-6
    assert all(math.isfinite(v) for v in out)


def test_states_out_of_order_go_in_their_place_and_only_the_clock_going_back_clears():
    """Odometry stamps that jitter by a few ms keep every pose; a receiver's clock that goes
    back (a simulation restarted) clears them."""
    poses = PoseHistory()
    for k, (stamp, x) in enumerate(((10, 1.0), (30, 3.0), (20, 2.0), (40, 4.0), (25, 2.5))):
        assert poses.add(stamp * 1_000_000, x, 0.0, 0.0, now_ns=50_000_000 + k) == ''
    assert len(poses) == 5 and poses.clears == 0
    assert poses.at(15_000_000, tolerance_ns=0) == pytest.approx((1.5, 0.0, 0.0))
    assert poses.at(27_500_000, tolerance_ns=0) == pytest.approx((2.75, 0.0, 0.0))
    poses.add(45_000_000, 5.0, 0.0, 0.0, now_ns=50_000_000)  # the clock went back
    assert len(poses) == 1 and poses.clears == 1


def test_a_full_history_makes_room_with_its_oldest_pose():
    poses = PoseHistory(max_poses=3)
    for stamp in (10, 20, 30):
        poses.add(stamp, float(stamp), 0.0, 0.0)
    poses.add(15, 15.0, 0.0, 0.0)  # between: the oldest (10) leaves
    assert poses.at(15, tolerance_ns=0) == (15.0, 0.0, 0.0)
    assert poses.at(10, tolerance_ns=0) == 'the oldest state kept is 0.000 s newer than the ' \
        'message (tolerance 0.000 s)'
    poses.add(5, 5.0, 0.0, 0.0)  # older than every pose of a full history: not kept
    assert len(poses) == 3 and poses.at(15, tolerance_ns=0) == (15.0, 0.0, 0.0)
