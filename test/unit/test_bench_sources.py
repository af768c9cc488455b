"""benchmarks/bench_sources.py: its worlds and messages (the timing itself is the
benchmark's, not a test's)."""
from __future__ import annotations

import math

from benchmark_modules import load_benchmark
import numpy as np
import pytest

from rcbf_ros.messages import sensor

bench = load_benchmark('bench_sources')


def test_the_scan_is_ray_cast_against_the_room_and_its_posts():
    ranges, angle_min = bench.ray_ranges(np.array([0.0, 0.0]), 0.0, 4)
    # beams at -pi, -pi/2, 0, pi/2: the walls at 4 m, the post (0, 2.5) r 0.3 at 2.2 m
    assert angle_min == -math.pi
    np.testing.assert_allclose(ranges, [4.0, 4.0, 4.0, 2.2], atol=1e-12)
    out = sensor.scan_points(bench.scan_message(np.array([0.0, 0.0]), 0.0, 4, 100))
    np.testing.assert_allclose(out.points, [[-4.0, 0.0], [0.0, -4.0], [4.0, 0.0], [0.0, 2.2]],
                               atol=1e-5)


def test_the_cloud_lies_on_the_walls_and_posts_and_a_quarter_is_in_the_band():
    data = bench.cloud_message(4000, 100, np.random.default_rng(0))
    everything = sensor.cloud_points(data)
    band = sensor.cloud_points(data, min_height=0.05, max_height=0.5)
    points = everything.points
    on_wall = np.isclose(np.abs(points).max(axis=1), bench.HALF, atol=1e-5)
    gaps = np.hypot(*(points[:, None, :] - bench.POSTS[None]).transpose(2, 0, 1))
    on_post = np.isclose(gaps, bench.POST_RADIUS, atol=1e-5).any(axis=1)
    assert len(points) == 4000 and np.all(on_wall | on_post)
    assert 0.2 < len(band.points) / 4000 < 0.33   # 0.45 of the 1.7 m of z


def test_the_hold_figures_are_read_and_the_memory_is_the_latest_message_only():
    figures = bench.hold(4, size=20_000, distinct=2)
    assert set(figures) == {'median', 'p99', 'max', 'first_mb', 'last_mb', 'peak_mb',
                            'rss_first', 'rss_last', 'message_mb'}
    assert 0.0 < figures['median'] <= figures['max']
    # the source keeps only its latest message's points: nothing piles up from one to the next
    assert figures['last_mb'] <= figures['first_mb'] * 1.5 + 0.05
    assert figures['peak_mb'] >= figures['last_mb'] > 0.0


def test_the_corridor_cloud_lies_on_its_two_walls_all_in_the_band():
    data = bench.corridor_message(3000, 100, np.random.default_rng(0))
    band = sensor.cloud_points(data, min_height=0.05, max_height=0.5)
    assert len(band.points) == 3000 and band.frame_id == 'odom'
    assert np.all(np.abs(band.points[:, 0]) <= 3.0)
    assert np.all((np.abs(band.points[:, 1]) >= 0.45 - 1e-6)
                  & (np.abs(band.points[:, 1]) <= 0.5 + 1e-6))


def test_the_side_by_side_run_decides_each_input_with_both_checkouts():
    # --against: another checkout imported beside this one (here this same tree again), its
    # modules its own, and both medians read
    other = bench.load_checkout(bench.ROOT)
    assert other['rcbf_ros.node_logic.sources'].ObservationSources is not bench.ObservationSources
    mine, theirs = bench.compare('scan', 16, 0.0, 3, other)
    assert mine > 0.0 and theirs > 0.0


@pytest.mark.parametrize('args', [['--against', '{tmp}'], ['--against', '{root}', '--only', 'x?']])
def test_the_side_by_side_run_refuses_a_tree_without_rcbf_ros_or_a_case_filter_matching_none(
        args, tmp_path, capsys):
    argv = [a.format(tmp=tmp_path, root=bench.ROOT) for a in args] + ['--calls', '3']
    with pytest.raises(SystemExit) as stop:
        bench.main(argv)
    assert stop.value.code == 2
    assert len(capsys.readouterr().err.strip().splitlines()[-1]) < 200
