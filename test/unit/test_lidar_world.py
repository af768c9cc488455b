"""sim_nodes/lidar_world.py: ray casting against closed forms, the scan's REP 117 values, the
base's lag, slip and odometry, the blind controller and the seeded worlds."""
from __future__ import annotations

import math

from hypothesis import given, settings
from hypothesis import strategies as st
import numpy as np
import pytest

from sim_nodes import lidar_world as lw

NO_CIRCLES, NO_SEGMENTS = np.zeros((0, 3)), np.zeros((0, 4))


def world(circles=NO_CIRCLES, segments=NO_SEGMENTS, half_size=5.0, thickness=0.0) -> lw.World:
    return lw.World(half_size=half_size, circles=np.array(circles, dtype=float).reshape(-1, 3),
                    segments=np.array(segments, dtype=float).reshape(-1, 4),
                    start=np.zeros(3), goal=np.array([4.0, 0.0]), wall_thickness=thickness)


def test_a_ray_meets_a_circle_at_its_near_side_and_misses_beside_it():
    circle = np.array([[3.0, 0.0, 1.0]])
    # straight at it: 3 - 1; at angle a the near root of |t d - c|^2 = r^2
    a = 0.2
    near = 3 * math.cos(a) - math.sqrt(1 - (3 * math.sin(a)) ** 2)
    out = lw.cast_rays(np.zeros(2), np.array([0.0, a, math.asin(1 / 3) + 1e-6, math.pi]),
                       circle, NO_SEGMENTS)
    np.testing.assert_allclose(out[:2], [2.0, near], rtol=1e-12)
    assert out[2] == math.inf and out[3] == math.inf  # beside it, and away from it


def test_from_inside_a_circle_every_ray_meets_its_surface_on_the_way_out():
    angles = np.linspace(-math.pi, math.pi, 17)
    out = lw.cast_rays(np.zeros(2), angles, np.array([[0.0, 0.0, 1.5]]), NO_SEGMENTS)
    np.testing.assert_allclose(out, 1.5, rtol=1e-12)


def test_a_ray_meets_a_segment_at_x_over_cos_and_misses_past_its_ends_and_parallel():
    wall = np.array([[2.0, -1.0, 2.0, 1.0]])
    angles = np.array([0.0, 0.3, math.atan(0.5) + 1e-6, math.pi, math.pi / 2])
    out = lw.cast_rays(np.zeros(2), angles, NO_CIRCLES, wall)
    np.testing.assert_allclose(out[:2], [2.0, 2.0 / math.cos(0.3)], rtol=1e-12)
    assert np.isinf(out[2:]).all()
    # along the segment's own line: parallel, no hit
    assert lw.cast_rays(np.array([2.0, -3.0]), np.array([0.0]), NO_CIRCLES, wall)[0] == math.inf


def test_a_thick_wall_seen_end_on_returns_its_rounded_end():
    sides, ends = lw.wall_outline(np.array([[0.0, 1.0, 0.0, 2.0]]), 0.2)
    np.testing.assert_allclose(ends, [[0.0, 1.0, 0.1], [0.0, 2.0, 0.1]])
    out = lw.cast_rays(np.zeros(2), np.array([math.pi / 2, 0.0]), ends, sides)
    assert out[0] == pytest.approx(0.9) and out[1] == math.inf
    # from the side: the near face, half the thickness before the centre line
    side = lw.cast_rays(np.array([-1.0, 1.5]), np.array([0.0]), ends, sides)
    assert side[0] == pytest.approx(0.9)


def test_the_nearest_surface_wins():
    out = lw.cast_rays(np.zeros(2), np.array([0.0]), np.array([[5.0, 0.0, 1.0]]),
                       np.array([[3.0, -1.0, 3.0, 1.0]]))
    assert out[0] == pytest.approx(3.0)


@settings(max_examples=60, deadline=None)
@given(cx=st.floats(-4, 4), cy=st.floats(-4, 4), r=st.floats(0.05, 1.5),
       ox=st.floats(-4, 4), oy=st.floats(-4, 4), x0=st.floats(-4, 4), y0=st.floats(-4, 4),
       x1=st.floats(-4, 4), y1=st.floats(-4, 4), thickness=st.floats(0.01, 0.3))
def test_every_hit_lies_on_a_surface_and_no_ray_is_shorter_than_the_clearance(
        cx, cy, r, ox, oy, x0, y0, x1, y1, thickness):
    w = world([[cx, cy, r]], [[x0, y0, x1, y1]], thickness=thickness)
    origin = np.array([ox, oy])
    gap = lw.clearance(w, origin)[0]
    if gap <= 1e-6:  # inside or on a surface
        return
    angles = np.linspace(-math.pi, math.pi, 720, endpoint=False)
    sides, ends = lw.wall_outline(w.segments, thickness)
    circles = np.concatenate([w.circles, ends])
    out = lw.cast_rays(origin, angles, circles, sides)
    hit = np.isfinite(out)
    assert (out[hit] >= gap - 1e-9).all()
    points = origin + out[hit, None] * np.stack([np.cos(angles[hit]), np.sin(angles[hit])], 1)
    np.testing.assert_allclose(lw.clearance(w, points), 0.0, atol=1e-7)
    # a ray aimed at the nearest surface point (closed forms) meets it at the clearance
    centre = np.array([cx, cy])
    a, b = np.array([x0, y0]), np.array([x1, y1])
    s = np.clip((origin - a) @ (b - a) / max((b - a) @ (b - a), 1e-18), 0.0, 1.0)
    on_line = a + s * (b - a)
    candidates = [centre + r * (origin - centre) / np.linalg.norm(origin - centre),
                  on_line + thickness / 2 * (origin - on_line) / np.linalg.norm(origin - on_line)]
    nearest = min(candidates, key=lambda p: np.linalg.norm(p - origin))
    aim = math.atan2(*(nearest - origin)[::-1])
    ray = lw.cast_rays(origin, np.array([aim]), circles, sides)[0]
    assert ray == pytest.approx(gap, abs=1e-6)


def test_clearance_is_the_distance_to_the_nearest_surface_and_negative_in_a_post():
    w = world([[3.0, 0.0, 1.0]], [[0.0, 2.0, 4.0, 2.0]], thickness=0.2)
    np.testing.assert_allclose(lw.clearance(w, np.array([[0.0, 0.0], [3.0, 0.2], [-3.0, 2.0]])),
                               [1.9, -0.8, 2.9])


def test_a_scan_reports_rep_117_values_in_the_laser_frame():
    lidar = lw.Lidar(beams=4, range_max=3.0, range_min=0.5, dropout=0.0, mount=(0.1, 0.0, 0.0))
    # beams at -pi, -pi/2, 0, pi/2 from the laser at (0.1, 0): wall ahead at x = 2, a post
    # touching the laser on its left, nothing behind within 3 m, the floor's edge below at 4
    w = world([[0.1, 0.6, 0.2]], [[2.0, -5.0, 2.0, 5.0], [-5.0, -4.0, 5.0, -4.0]])
    out = lw.scan_ranges(w, np.zeros(3), lidar)
    assert out.dtype == np.float32
    assert out[0] == np.inf and out[1] == np.inf  # behind: no return; below: beyond 3 m
    assert out[2] == pytest.approx(1.9)
    assert out[3] == -np.inf  # 0.4 m: closer than range_min
    turned = lw.scan_ranges(w, np.array([0.0, 0.0, math.pi / 2]), lidar)
    # turned left: the laser at (0, 0.1), its beam at -pi/2 points along +x at the wall
    assert turned[1] == pytest.approx(2.0)
    fields = lw.scan_fields(out, lidar, stamp_ns=5)
    assert fields['frame_id'] == 'laser' and fields['angle_max'] == pytest.approx(math.pi / 2)


def test_a_scan_has_noise_and_dropped_beams_with_a_generator():
    lidar = lw.Lidar(dropout=0.1)
    w = world(segments=[[2.0, -50.0, 2.0, 50.0], [-2.0, -50.0, -2.0, 50.0]])
    out = lw.scan_ranges(w, np.zeros(3), lidar, np.random.default_rng(0))
    assert 10 < np.isnan(out).sum() < 70
    ahead = out[(np.abs(lidar.angles) < 0.5) & np.isfinite(out)]
    error = ahead - 2.0 / np.cos(lidar.angles[(np.abs(lidar.angles) < 0.5) & np.isfinite(out)])
    assert 0.003 < error.std() < 0.03


def test_the_wheels_lag_the_command_and_slip_leaves_odometry_ahead_of_the_truth():
    model = lw.BaseModel(tau_v=0.2, slip=0.1)
    state = lw.BaseState(pose=np.zeros(3), odom=np.zeros(3))
    for _ in range(20):  # 0.2 s: one time constant
        state = lw.step_base(state, np.array([0.4, 0.0]), 0.01, model)
    assert state.wheels[0] == pytest.approx(0.4 * (1 - math.exp(-1)), rel=1e-9)
    assert state.pose[0] == pytest.approx(0.9 * state.odom[0], rel=1e-9)
    assert state.pose[1] == 0.0 and state.odom[1] == 0.0


def test_commands_are_clipped_to_the_limits_and_noise_makes_odometry_drift():
    model = lw.BaseModel(tau_v=1e-6, tau_omega=1e-6)
    state = lw.BaseState(pose=np.zeros(3), odom=np.zeros(3))
    state = lw.step_base(state, np.array([9.0, -9.0]), 0.01, model)
    np.testing.assert_allclose(state.wheels, [model.v_max, -model.omega_max])
    rng = np.random.default_rng(1)
    for _ in range(500):
        state = lw.step_base(state, np.array([0.5, 0.5]), 0.01, model, rng)
    drift = np.hypot(*(state.pose[:2] - state.odom[:2]))
    assert 0.01 < drift < 1.0


def test_an_arc_is_integrated_exactly():
    pose = np.zeros(3)
    for _ in range(100):
        pose = lw._integrate(pose, 1.0, math.pi / 2, 0.01)  # a quarter turn of radius 2/pi
    np.testing.assert_allclose(pose, [2 / math.pi, 2 / math.pi, math.pi / 2], atol=1e-12)


def test_the_controller_drives_at_the_goal_and_turns_in_place_when_it_lies_behind():
    model = lw.BaseModel()
    np.testing.assert_allclose(lw.go_to_goal(np.zeros(3), np.array([3.0, 0.0]), model),
                               [model.v_max, 0.0])
    v, omega = lw.go_to_goal(np.zeros(3), np.array([-3.0, 0.1]), model)
    assert v == 0.0 and omega == pytest.approx(model.omega_max)


def test_worlds_are_seeded_reachable_and_start_clear():
    for seed in range(8):
        w = lw.random_world(seed)
        again = lw.random_world(seed)
        np.testing.assert_array_equal(w.circles, again.circles)
        np.testing.assert_array_equal(w.segments, again.segments)
        assert w.kind in lw.KINDS and w.seed == seed
        assert (lw.clearance(w, np.stack([w.start[:2], w.goal])) > 0.5).all()
        assert lw.reachable(w, 0.35)
        inside = np.abs(np.concatenate([w.circles[:, :2].ravel(), w.segments.ravel()]))
        assert (inside <= w.half_size + 1e-9).all()
    assert {lw.random_world(0, kind=k).kind for k in lw.KINDS} == set(lw.KINDS)


def test_a_wall_without_a_doorway_leaves_the_goal_unreachable():
    w = world(segments=[[0.0, -5.0, 0.0, 5.0], *lw._arena(5.0)])
    w = lw.World(**{**w.__dict__, 'start': np.array([-3.0, 0.0, 0.0])})
    assert not lw.reachable(w, 0.3)
    door = world(segments=[*lw._wall_with_doors(0.0, -5.0, 5.0, [(1.0, 1.0)]), *lw._arena(5.0)])
    door = lw.World(**{**door.__dict__, 'start': np.array([-3.0, 0.0, 0.0])})
    assert lw.reachable(door, 0.3)
    assert not lw.reachable(door, 0.55)  # the doorway is 1 m wide


def test_an_unknown_kind_is_refused_naming_it():
    with pytest.raises(ValueError, match="kind: 'maze'"):
        lw.random_world(0, kind='maze')
