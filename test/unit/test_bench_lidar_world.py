"""benchmarks/bench_lidar_world.py: its map by hand, its stop zone, its scans and transforms
through the node's path (placed through tf at the scan's stamp), and short drives of a handful
of seeded worlds (outcomes, not speed)."""
from __future__ import annotations

import math

from benchmark_modules import load_benchmark
import numpy as np
import pytest

from rcbf_ros.core.config import filter_config_from_params
from rcbf_ros.messages import sensor
from sim_nodes import lidar_world as lw

bench = load_benchmark('bench_lidar_world')


def post_ahead() -> lw.World:
    """A post of radius 0.4 m straight between the start and the goal."""
    h = 5.0
    return lw.World(half_size=h, circles=np.array([[2.0, 0.0, 0.4]]),
                    segments=np.array(lw._arena(h), dtype=float), start=np.zeros(3),
                    goal=np.array([4.0, 0.0]), kind='posts', seed=7)


def test_the_map_by_hand_covers_every_point_within_the_body_of_a_wall():
    world = lw.random_world(1, kind='wall')
    circles = bench.world_circles(world)
    rng = np.random.default_rng(0)
    segment = world.segments[4]  # the first inner wall
    s = rng.uniform(0, 1, 2000)
    along = segment[:2] + s[:, None] * (segment[2:] - segment[:2])
    normal = np.array([-(segment[3] - segment[1]), segment[2] - segment[0]])
    normal /= np.linalg.norm(normal)
    reach = bench.BASE.radius + world.wall_thickness / 2
    points = along + rng.uniform(-reach, reach, 2000)[:, None] * normal
    inside = (np.linalg.norm(points[:, None, :] - circles[None, :, :2], axis=2)
              <= circles[None, :, 2]).any(axis=1)
    assert inside.all()
    # posts keep their centres, widened by the body's radius
    np.testing.assert_allclose(circles[:len(world.circles)],
                               world.circles + [0.0, 0.0, bench.BASE.radius])


def test_both_filters_parameters_are_accepted():
    world = lw.random_world(2)
    assert filter_config_from_params(bench.filter_params(None)).sources.sources
    config = filter_config_from_params(bench.filter_params(world))
    assert config.problem.n_barriers == len(bench.world_circles(world))


def test_the_stop_zone_counts_the_points_in_its_box():
    points = np.array([[0.1, 0.0], [0.39, 0.29], [0.41, 0.0], [-0.1, 0.0], [0.2, -0.31],
                       [0.0, -0.3]])
    assert bench.in_stop_zone(points) == 3
    assert bench.in_stop_zone(np.zeros((0, 2))) == 0


def test_a_scan_goes_through_the_node_s_reader_in_the_laser_frame():
    world = post_ahead()
    ranges = lw.scan_ranges(world, world.start, bench.LIDAR)
    out = sensor.scan_points(bench.ScanEncoder()(ranges, 1_500_000_000))
    assert out.frame_id == 'laser' and out.stamp_ns == 1_500_000_000
    assert out.received == bench.LIDAR.beams
    # the beam straight ahead (index 180 of 360 from -pi) meets the post 1.6 m from base_link,
    # 1.5 m from the laser mounted 0.1 m ahead; the stop zone sees it in base_link again
    ahead = out.points[np.argmin(np.abs(np.arctan2(out.points[:, 1], out.points[:, 0])))]
    np.testing.assert_allclose(ahead, [1.5, 0.0], atol=1e-5)
    np.testing.assert_allclose(bench.laser_to_base(ahead[None]), [[1.6, 0.0]], atol=1e-5)
    assert len(out.points) == np.isfinite(ranges).sum()


def test_the_scan_is_placed_through_tf_at_its_stamp():
    """The laser's points land on the post in odom with the odometry's pose at the scan's
    stamp, not the latest one: the robot turned and moved since."""
    world = post_ahead()
    config = filter_config_from_params(bench.filter_params(None))
    sources = bench.ObservationSources(config.sources)
    tf = bench.TfEncoder()
    assert sources.read_tf(tf.static(), static=True) == ''
    seen_at = np.array([0.3, -0.2, 0.25])  # odom == the true pose here
    assert sources.read_tf(tf.odometry(seen_at, 1_000_000_000), static=False) == ''
    ranges = lw.scan_ranges(world, seen_at, bench.LIDAR)
    assert sources.read('scan', bench.ScanEncoder()(ranges, 1_000_000_000),
                        received_ns=1_000_000_000) == ''
    later = np.array([0.6, -0.1, -0.5])
    assert sources.read_tf(tf.odometry(later, 1_100_000_000), static=False) == ''
    out = sources.points(later, now_ns=1_100_000_000, stamp_now_ns=1_100_000_000)
    assert not isinstance(out, str), out
    points, spread = out
    assert len(points) == np.isfinite(ranges).sum() and spread == 0.0
    # every point lies on a surface of the world (the lidar's noise is 1 cm)
    assert np.abs(lw.clearance(world, points)).max() < 0.05
    assert sources.tf_counts == {'messages': 3, 'refused': 0, 'transforms_refused': 0}


def test_a_drive_feeds_tf_as_a_base_does_at_every_scan_s_stamp(monkeypatch):
    """Each scan finds in tf, at its own stamp and without tolerance, base_link on odom at
    the odometry's pose of that instant (the state of the decision taken then) and the laser
    on base_link at its mount."""
    checked: list[tuple[float, float]] = []

    class Checked(bench.ObservationSources):
        scan_stamp = -1

        def read(self, name, data, *, received_ns):
            self.scan_stamp = sensor.scan_points(data).stamp_ns
            return super().read(name, data, received_ns=received_ns)

        def points(self, state, *, now_ns, stamp_now_ns):
            if self.scan_stamp == now_ns:  # the decision at the scan's instant
                base = self.tf.lookup_transform('odom', 'base_link', now_ns, tolerance_ns=0)
                laser = self.tf.lookup_transform('base_link', 'laser', now_ns, tolerance_ns=0)
                x, y, _ = base.translation
                yaw = 2 * math.atan2(base.rotation[2], base.rotation[3])
                pose_error = max(abs(x - state[0]), abs(y - state[1]),
                                 abs(lw.wrap(yaw - state[2])))
                mount_error = max(abs(a - b) for a, b in zip(laser.translation[:2],
                                                             bench.LIDAR.mount[:2]))
                checked.append((pose_error, mount_error))
            return super().points(state, now_ns=now_ns, stamp_now_ns=stamp_now_ns)

    monkeypatch.setattr(bench, 'ObservationSources', Checked)
    run = bench.drive(post_ahead(), 'filter, scan', duration=3.0)
    assert run.outcome == 'timeout' and run.fail_safe == 0
    assert len(checked) == 30   # 10 Hz for 3 s
    assert max(max(errors) for errors in checked) < 1e-9, checked


def test_blind_it_hits_the_post_and_the_stop_zone_and_filter_do_not():
    world = post_ahead()
    blind = bench.drive(world, 'no filter', duration=8.0)
    assert blind.outcome == 'collision' and blind.closest < 0.0
    stop = bench.drive(world, 'stop zone', duration=8.0)
    assert stop.outcome != 'collision' and stop.closest > 0.0 and stop.corrected > 0
    # the filter steers round the post (the deadlock of a post dead ahead is broken by the
    # start's small offsets: slip and noise)
    for setup in ('filter, true circles', 'filter, scan'):
        run = bench.drive(world, setup, duration=8.0)
        assert run.outcome != 'collision' and run.closest > 0.0 and run.corrected > 0, setup
        assert run.fail_safe == 0, setup  # the scan's frame was placed through tf throughout


@pytest.mark.parametrize('seed', [0, 3, 8, 11])
def test_the_filter_on_the_scan_keeps_a_seeded_world_s_robot_off_every_surface(seed):
    world = lw.random_world(seed)
    run = bench.drive(world, 'filter, scan', seed=seed, duration=12.0)
    assert run.outcome != 'collision' and run.closest > 0.0
    assert run.path.shape[1] == 2 and len(run.path) > 10


def test_the_tables_count_outcomes_per_set_up_and_kind():
    path = np.zeros((5, 2))
    runs = [bench.Run('no filter', 0, 'posts', 'collision', 3.0, path, -0.01),
            bench.Run('filter, scan', 0, 'posts', 'goal', 20.0, path, 0.1, corrected=2),
            bench.Run('filter, scan', 1, 'wall', 'stuck', 12.0, path, 0.2)]
    table = bench.summary(runs)
    assert table[2].startswith('| no filter | 1 | 1 | 0 | 0 | nan | - | -0.010 |')
    assert table[3].startswith('| filter, scan | 2 | 0 | 1 | 1 | 20.0 | 20.0 (1) | 0.100 | 20% |')
    # a set-up without a collision that missed world 0 leaves no world every one reached
    stopped = bench.summary([*runs, bench.Run('stop zone', 0, 'posts', 'stuck', 15.0, path, 0.2)])
    assert stopped[3].startswith('| stop zone | 1 | 0 | 0 | 1 | nan | - |')
    assert stopped[4].startswith('| filter, scan | 2 | 0 | 1 | 1 | 20.0 | - |')
    kinds = bench.by_kind(runs)
    assert kinds[2].startswith('| posts | 1 | 0 goals, 1 hits | 0 goals, 0 hits |')
    assert kinds[3].endswith('| 0 goals, 0 hits |')


def test_bad_options_stop_with_status_2_and_one_line(tmp_path, capsys):
    for argv in (['--worlds', '0'], ['--worlds', 'many'], ['--out', str(tmp_path / 'f')]):
        (tmp_path / 'f').write_text('')
        with pytest.raises(SystemExit) as stop:
            bench.main([*argv, '--no-write'])
        assert stop.value.code == 2
        err = capsys.readouterr().err.strip().splitlines()[-1]
        assert err.split('error: ', 1)[1].startswith(('argument', '--worlds', '--out')), err


def test_one_world_draws_a_picture_per_set_up(tmp_path, capsys):
    pytest.importorskip('matplotlib')
    assert bench.main(['--worlds', '1', '--out', str(tmp_path / 'runs'), '--no-write']) == 0
    names = sorted(p.name for p in (tmp_path / 'runs').iterdir())
    assert names == ['filter_scan.png', 'filter_true_circles.png', 'no_filter.png',
                     'stop_zone.png']
    out = capsys.readouterr().out
    assert '| filter, scan | 1 |' in out and math.isfinite(len(out))


FAST_BASE = lw.BaseModel(v_max=1.0)
"""The base of the between-samples runs: twice the speed of the others' (a fast approach)."""


def test_between_samples_the_margin_keeps_the_scan_robot_clear_where_the_plain_filter_hits():
    # commands held 50 ms, data 50 ms late, alpha 20: worlds 4 and 5 are hit within 5 s by the
    # filter whose rows hold at the samples only, and missed with the sampled-data margin
    plain, tightened = ([bench.drive_held(lw.random_world(seed), tightened=tight, period=0.05,
                                          latency=0.05, alpha=20.0, base=FAST_BASE, seed=seed,
                                          duration=5.0) for seed in (4, 5)]
                        for tight in (False, True))
    assert [run.outcome for run in plain].count('collision') >= 1, [r.outcome for r in plain]
    assert not any(run.outcome == 'collision' for run in tightened)
    assert min(run.closest for run in tightened) > 0.0
    assert {run.setup for run in tightened} == {'filter, scan, margin'}


def test_between_samples_the_filter_sees_the_state_at_most_the_latency_old(monkeypatch):
    ages = []
    sense = bench.ObservationSources.sense

    def recording(self, safety_filter, state, *, now_ns, stamp_now_ns):
        stamps = [s for s in recorded if np.array_equal(s[0], state)]
        ages.append((now_ns - stamps[-1][1]) * 1e-9)
        return sense(self, safety_filter, state, now_ns=now_ns, stamp_now_ns=stamp_now_ns)

    recorded = []
    odometry = bench.TfEncoder.odometry

    def keep(self, odom, stamp_ns):
        recorded.append((np.array(odom), stamp_ns))
        return odometry(self, odom, stamp_ns)

    monkeypatch.setattr(bench.ObservationSources, 'sense', recording)
    monkeypatch.setattr(bench.TfEncoder, 'odometry', keep)
    bench.drive_held(lw.random_world(0), tightened=True, period=0.05, latency=0.033,
                     base=FAST_BASE, duration=0.6)
    assert len(ages) >= 10
    assert max(ages) <= 0.033 + 1e-9
    assert min(ages) >= 0.033 - bench.ODOMETRY_DT - 1e-9


def test_between_samples_refuses_a_latency_below_the_odometry_period():
    with pytest.raises(ValueError, match='latency'):
        bench.drive_held(lw.random_world(0), tightened=False, period=0.05, latency=0.001)
