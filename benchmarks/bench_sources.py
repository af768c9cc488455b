"""The safety filter's decision time from sensor messages to the command.

    python benchmarks/bench_sources.py [--calls 1000] [--no-write]
    python benchmarks/bench_sources.py --against DIR [--only LaserScan] [--calls 1000]

One decision = what the node does per proposal with an observation source: read the latest
message's bytes (:mod:`rcbf_ros.messages.sensor`), keep the state's pose at its stamp
(:meth:`ObservationSources.note_state`, which the node does per state), take the points into
the state's frame and into the filter (:meth:`ObservationSources.sense`), filter
(:meth:`SafetyFilter.filter`).
config/unicycle.yaml's filter with ``footprint.radius`` 0.2 m, the robot at random in a square
room of 8 m (its walls, plus 5 posts, what the sensor sees), proposals within the limits.
Messages are encoded by rosbags, once per world, before the timing:

- LaserScan in ``base_link``, 360 and 2,000 beams (ray cast against the room, max range 8 m);
- PointCloud2 in ``odom``, 24k points (x, y, z FLOAT32 and an intensity, z uniform in
  -0.2..1.5 m; the z band 0.05-0.5 m keeps about a quarter), without and with a 5 cm grid;
- PointCloud2 of 100k points (the cap is 200,000 per message: answered, not refused);
- PointCloud2 of 100k points all in the z band along the two walls of a corridor 0.9 m wide
  around the robot: tens of thousands of rows can bind at once (the exact solve on the rows
  that can bind, and the rows merged where it cannot finish), and of 200k such points: more
  than the 100,000 points all sources may give a decision, refused in one line.

Then what one 100k-point PointCloud2 costs the node's callback: the time the source's
callback holds the executor (decode + store, :meth:`ObservationSources.read`: the node takes
sensor messages as raw bytes, so this is all its callback does with a good one), which is how
long any other callback can wait behind it on the single-threaded executor; and the memory
over a stream of such messages (tracemalloc's current and peak, and the process's RSS).

Nav2 collision_monitor's figures from its README are printed beside ours as a reference, not
re-measured here (another machine, and a stop/slow-down check, not a QP).

``--against DIR`` compares instead: this checkout's rcbf_ros and the one in DIR (another
worktree, an older commit) are imported side by side in one process, and each input is decided
by both in turns, so that a shared or busy machine loads both alike; it prints each median and
their ratio per case (``--only`` picks cases by name) and leaves RESULTS.md alone.
"""
from __future__ import annotations

import argparse
import gc
import importlib
from pathlib import Path
import resource
import sys
import time
import tracemalloc

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from rcbf_ros.core.config import filter_config_from_params  # noqa: E402
from rcbf_ros.messages import sensor  # noqa: E402
from rcbf_ros.messages.typestore import jazzy_typestore  # noqa: E402
from rcbf_ros.node_logic.safety_filter import build_safety_filter, node_settings_from_params  # noqa: E402,E501
from rcbf_ros.node_logic.sources import ObservationSources  # noqa: E402
from rcbf_ros.parameters.rules import find_config, load_params  # noqa: E402

TITLE = 'Perception sources: decision time from scan or cloud to command'
HALF = 4.0
"""Half the room's side (m)."""
POSTS = np.array([[1.5, 1.5], [-1.5, 1.5], [-1.5, -1.5], [1.5, -1.5], [0.0, 2.5]])
POST_RADIUS = 0.3
CASES = (('LaserScan, 360 beams', 'scan', 360, 0.0, 150.0),
         ('LaserScan, 2,000 beams', 'scan', 2_000, 0.0, 300.0),
         ('PointCloud2, 24k points', 'pointcloud', 24_000, 0.0, 2_000.0),
         ('PointCloud2, 24k points, 5 cm grid', 'pointcloud', 24_000, 0.05, None),
         ('PointCloud2, 100k points', 'pointcloud', 100_000, 0.0, 20_000.0),
         ('PointCloud2, 100k points in a corridor', 'corridor', 100_000, 0.0, 20_000.0),
         ('PointCloud2, 200k points in a corridor (refused)', 'corridor', 200_000, 0.0,
          20_000.0))
"""(name, source type, beams or points, voxel_size, target median in us or None)."""
COLLISION_MONITOR = [
    '| Nav2 collision_monitor (its README, not re-measured here) | per frame |',
    '|---|---|',
    '| LaserScan, 360 points | 4.45-4.93 ms |',
    '| PointCloud2, 24k points | 4.1-20.7 ms |',
]


def params(kind: str, voxel: float) -> dict:
    """config/unicycle.yaml's safety_filter parameters with one source of ``kind``."""
    out = load_params(find_config('unicycle'), 'safety_filter')
    out.update({'observation_sources': ['sensor'], 'sensor.type': kind,
                'sensor.topic': 'sensor', 'sensor.timeout_s': 10.0, 'sensor.voxel_size': voxel,
                'footprint.radius': 0.2, 'obstacles.speed_input': 0,
                'obstacles.x': [40.0], 'obstacles.y': [40.0], 'obstacles.radius': [0.5]})
    return out


def ray_ranges(position: np.ndarray, heading: float, beams: int) -> tuple[np.ndarray, float]:
    """Ranges of ``beams`` beams over a full turn from ``position`` against the room's walls
    and posts (max range 8 m), and the first beam's angle in the robot's frame."""
    angle_min = -np.pi
    angles = angle_min + np.arange(beams) * (2 * np.pi / beams)
    world = angles + heading
    d = np.stack([np.cos(world), np.sin(world)], axis=1)
    with np.errstate(divide='ignore', invalid='ignore'):
        tx = np.where(d[:, 0] > 0, (HALF - position[0]) / d[:, 0],
                      (-HALF - position[0]) / d[:, 0])
        ty = np.where(d[:, 1] > 0, (HALF - position[1]) / d[:, 1],
                      (-HALF - position[1]) / d[:, 1])
    ranges = np.minimum(np.abs(tx), np.abs(ty))
    for post in POSTS:
        offset = position - post
        b = d @ offset
        c = offset @ offset - POST_RADIUS ** 2
        disc = b * b - c
        hit = (disc >= 0) & (-b - np.sqrt(np.maximum(disc, 0)) > 0)
        ranges = np.where(hit, np.minimum(ranges, -b - np.sqrt(np.maximum(disc, 0))), ranges)
    return np.where(ranges <= 8.0, ranges, np.inf), angle_min


def scan_message(position: np.ndarray, heading: float, beams: int, stamp_s: int) -> bytes:
    store = jazzy_typestore()
    t = store.types
    ranges, angle_min = ray_ranges(position, heading, beams)
    msg = t[sensor.LASER_SCAN](
        header=t['std_msgs/msg/Header'](stamp=t['builtin_interfaces/msg/Time'](
            sec=stamp_s, nanosec=0), frame_id='base_link'),
        angle_min=angle_min, angle_max=angle_min + 2 * np.pi * (beams - 1) / beams,
        angle_increment=2 * np.pi / beams, time_increment=0.0, scan_time=0.1,
        range_min=0.05, range_max=8.0, ranges=ranges.astype(np.float32),
        intensities=np.zeros(0, np.float32))
    return bytes(store.serialize_cdr(msg, sensor.LASER_SCAN))


def cloud_message(count: int, stamp_s: int, rng: np.random.Generator) -> bytes:
    """``count`` points on the room's walls and posts, z uniform in -0.2..1.5 m."""
    store = jazzy_typestore()
    t = store.types
    side = rng.integers(0, 5, count)
    along = rng.uniform(-HALF, HALF, count)
    xy = np.where(side[:, None] == 0, np.stack([np.full(count, HALF), along], 1),
                  np.where(side[:, None] == 1, np.stack([np.full(count, -HALF), along], 1),
                           np.where(side[:, None] == 2, np.stack([along, np.full(count, HALF)], 1),
                                    np.stack([along, np.full(count, -HALF)], 1))))
    posts = side == 4
    angle = rng.uniform(-np.pi, np.pi, posts.sum())
    which = POSTS[rng.integers(0, len(POSTS), posts.sum())]
    xy[posts] = which + POST_RADIUS * np.stack([np.cos(angle), np.sin(angle)], 1)
    record = np.dtype({'names': ['x', 'y', 'z', 'intensity'], 'formats': ['<f4'] * 4})
    table = np.zeros(count, record)
    table['x'], table['y'], table['z'] = xy[:, 0], xy[:, 1], rng.uniform(-0.2, 1.5, count)
    field = t['sensor_msgs/msg/PointField']
    msg = t[sensor.POINT_CLOUD2](
        header=t['std_msgs/msg/Header'](stamp=t['builtin_interfaces/msg/Time'](
            sec=stamp_s, nanosec=0), frame_id='odom'),
        height=1, width=count,
        fields=[field(name=n, offset=4 * k, datatype=sensor.FLOAT32, count=1)
                for k, n in enumerate(record.names)],
        is_bigendian=False, point_step=16, row_step=16 * count,
        data=table.view(np.uint8), is_dense=True)
    return bytes(store.serialize_cdr(msg, sensor.POINT_CLOUD2))


def corridor_message(count: int, stamp_s: int, rng: np.random.Generator) -> bytes:
    """``count`` points in ``odom`` on two walls along x (|x| <= 3 m) at |y| 0.45-0.5 m, every
    z within the band 0.05-0.5 m: each one a point of the filter."""
    store = jazzy_typestore()
    t = store.types
    record = np.dtype({'names': ['x', 'y', 'z'], 'formats': ['<f4'] * 3})
    table = np.zeros(count, record)
    table['x'] = rng.uniform(-3.0, 3.0, count)
    table['y'] = rng.choice([-1.0, 1.0], count) * rng.uniform(0.45, 0.5, count)
    table['z'] = rng.uniform(0.06, 0.49, count)
    field = t['sensor_msgs/msg/PointField']
    msg = t[sensor.POINT_CLOUD2](
        header=t['std_msgs/msg/Header'](stamp=t['builtin_interfaces/msg/Time'](
            sec=stamp_s, nanosec=0), frame_id='odom'),
        height=1, width=count,
        fields=[field(name=n, offset=4 * k, datatype=sensor.FLOAT32, count=1)
                for k, n in enumerate(record.names)],
        is_bigendian=False, point_step=12, row_step=12 * count,
        data=table.view(np.uint8), is_dense=True)
    return bytes(store.serialize_cdr(msg, sensor.POINT_CLOUD2))


def stack(kind: str, voxel: float, modules: dict | None = None) -> tuple:
    """(the safety filter, its ObservationSources) of one case; of another checkout's
    rcbf_ros with ``modules`` (:func:`load_checkout`)."""
    corridor = kind == 'corridor'
    if modules is None:
        config = filter_config_from_params(params('pointcloud' if corridor else kind, voxel))
        return (build_safety_filter(config=config, settings=node_settings_from_params({})),
                ObservationSources(config.sources))
    logic = modules['rcbf_ros.node_logic.safety_filter']
    config = modules['rcbf_ros.core.config'].filter_config_from_params(
        params('pointcloud' if corridor else kind, voxel))
    return (logic.build_safety_filter(config=config,
                                      settings=logic.node_settings_from_params({})),
            modules['rcbf_ros.node_logic.sources'].ObservationSources(config.sources))


def decisions(kind: str, size: int, number: int, seed: int = 0) -> list:
    """``number`` ((message bytes, state), proposal) of one case: 20 worlds (or fewer), in
    turn, and a proposal each."""
    corridor = kind == 'corridor'
    rng = np.random.default_rng(seed)
    worlds = []
    for _index in range(min(number, 20)):
        if corridor:  # the robot in the middle of the corridor, facing along it or nearly
            state = [float(rng.uniform(-1.0, 1.0)), float(rng.uniform(-0.05, 0.05)),
                     float(rng.uniform(-0.3, 0.3)) + float(rng.choice([0.0, np.pi]))]
            worlds.append((corridor_message(size, 100, rng), state))
            continue
        while True:
            position = rng.uniform(-HALF + 0.6, HALF - 0.6, 2)
            if np.all(np.hypot(*(POSTS - position).T) > POST_RADIUS + 0.6):
                break
        heading = float(rng.uniform(-np.pi, np.pi))
        data = (scan_message(position, heading, size, 100) if kind == 'scan'
                else cloud_message(size, 100, rng))
        worlds.append((data, [float(position[0]), float(position[1]), heading]))
    return [(worlds[i % len(worlds)], rng.uniform(-2.5, 2.5, 2).tolist())
            for i in range(number)]


STAMP_NS = 100 * 10 ** 9
"""Every message's and state's stamp, and the clock's time at each decision (ns)."""
BOX = ([-0.05, 0.0, 0.0], [0.025, 0.025, 0.0])
"""The disturbance box (mean, std) of every decision."""


def decide(safety_filter: object, sources: object, data: bytes, state: list,
           proposal: list) -> tuple[str, object]:
    """One decision: the message read, its points into the filter, the filter's answer
    ('' and the result, or the fail-safe's reason and None)."""
    reason = sources.read('sensor', data, received_ns=0)
    sources.note_state(np.array(state), stamp_ns=STAMP_NS)  # as the node: sense says why not
    reason = reason or sources.sense(safety_filter, np.array(state), now_ns=0,
                                     stamp_now_ns=STAMP_NS)
    return (reason, None) if reason else ('', safety_filter.filter(state, proposal, *BOX))


def measure(kind: str, size: int, voxel: float, number: int, seed: int = 0) -> dict:
    """Median and p99 (us) of one decision, the share of corrected answers and of fail-safes,
    the mean number of points in the filter, and one refusal if any."""
    safety_filter, sources = stack(kind, voxel)
    inputs = decisions(kind, size, number, seed)
    box = BOX
    times, active, fail, points, refusal = [], 0, 0, [], ''
    gc.collect()
    for timed, ((data, state), proposal) in zip([False] * 20 + [True] * number,
                                               inputs[:20] + inputs):
        start = time.perf_counter()
        reason = sources.read('sensor', data, received_ns=0)
        sources.note_state(np.array(state), stamp_ns=STAMP_NS)
        reason = reason or sources.sense(safety_filter, np.array(state), now_ns=0,
                                         stamp_now_ns=STAMP_NS)
        if reason:
            u = safety_filter.fail_safe_action
        else:
            result = safety_filter.filter(state, proposal, *box)
            u = result.u_safe
        elapsed = time.perf_counter() - start
        if not timed:
            continue
        times.append(elapsed)
        if reason:
            fail += 1
            refusal = refusal or reason
        else:
            active += bool(result.active)
            fail += bool(result.fail_safe)
            points.append(safety_filter.point_count)
        del u
    times_us = np.array(times) * 1e6
    return {'median': float(np.median(times_us)), 'p99': float(np.percentile(times_us, 99)),
            'active': active / number, 'fail': fail / number,
            'points': float(np.mean(points)) if points else 0.0, 'refusal': refusal}


def load_checkout(root: Path) -> dict:
    """The modules of another checkout's rcbf_ros that a decision uses, imported from ``root``
    beside this checkout's (which are put back in ``sys.modules`` after): its functions keep
    their own modules' globals. Raises ValueError (one line) where ``root`` holds none."""
    def ours() -> dict:
        return {name: module for name, module in sys.modules.items()
                if name == 'rcbf_ros' or name.startswith('rcbf_ros.')}
    mine = ours()
    for name in mine:
        del sys.modules[name]
    sys.path.insert(0, str(root))
    try:
        modules = {name: importlib.import_module(name) for name in (
            'rcbf_ros.core.config', 'rcbf_ros.node_logic.safety_filter',
            'rcbf_ros.node_logic.sources')}
    except ImportError as exc:
        raise ValueError(f'--against: no rcbf_ros to import in {root} '
                         f'({" ".join(str(exc).split())[:160]})') from None
    finally:
        sys.path.remove(str(root))
        for name in ours():
            del sys.modules[name]
        sys.modules.update(mine)
    where = Path(modules['rcbf_ros.node_logic.sources'].__file__).resolve()
    if Path(root).resolve() not in where.parents:
        raise ValueError(f'--against: rcbf_ros came from {where}, not from {root}')
    return modules


def compare(kind: str, size: int, voxel: float, number: int, other: dict,
            seed: int = 0) -> tuple[float, float]:
    """Median (us) of one decision of this checkout and of ``other``'s
    (:func:`load_checkout`), on the same inputs, in one loop: each input decided by both, in
    turns (which goes first alternates), so that the machine's load falls on both alike."""
    stacks = (stack(kind, voxel), stack(kind, voxel, other))
    inputs = decisions(kind, size, number, seed)
    times: tuple[list[float], list[float]] = ([], [])
    gc.collect()
    warm = inputs[:20]  # unmeasured
    for index, ((data, state), proposal) in enumerate(warm + inputs):
        for which in ((0, 1) if index % 2 else (1, 0)):
            start = time.perf_counter()
            decide(*stacks[which], data, state, proposal)
            if index >= len(warm):
                times[which].append(time.perf_counter() - start)
    return float(np.median(times[0])) * 1e6, float(np.median(times[1])) * 1e6


def compare_table(number: int, root: Path, only: str) -> list[str]:
    """This checkout against the one at ``root``, for the cases whose name holds ``only``."""
    other = load_checkout(root)
    lines = [f'| source | this checkout, median (us) | {root}, median (us) | ratio |',
             '|---|---:|---:|---:|']
    print(lines[0], flush=True)
    for name, kind, size, voxel, _goal in CASES:
        if only.lower() not in name.lower():
            continue
        mine, theirs = compare(kind, size, voxel, number, other)
        lines.append(f'| {name} | {mine:,.0f} | {theirs:,.0f} | {mine / theirs:.3f} |')
        print(lines[-1], flush=True)
    return lines


def rss_mb() -> float:
    """The process's resident set size (MB), from /proc (0 where there is none)."""
    try:
        with open('/proc/self/statm') as statm:
            return int(statm.read().split()[1]) * resource.getpagesize() / 2**20
    except OSError:
        return 0.0


def hold(messages: int, size: int = 100_000, distinct: int = 5, seed: int = 1) -> dict:
    """One source's callback on ``messages`` PointCloud2 of ``size`` points (``distinct``
    different ones, in turn): the time each holds the callback (decode + store, ms), then,
    over the same stream again with tracemalloc on, the memory held after the first message
    and after the last (MB) and the peak; RSS after the first and the last of the timed
    pass."""
    config = filter_config_from_params(params('pointcloud', 0.0))
    sources = ObservationSources(config.sources)
    rng = np.random.default_rng(seed)
    stream = [cloud_message(size, 100, rng) for _ in range(distinct)]
    gc.collect()
    times, rss = [], []
    for index in range(messages):
        data = bytes(stream[index % distinct])  # a fresh buffer, as the runtime hands over
        start = time.perf_counter()
        reason = sources.read('sensor', data, received_ns=0)
        times.append(time.perf_counter() - start)
        assert not reason, reason
        del data
        if index in (0, messages - 1):
            rss.append(rss_mb())
    gc.collect()
    tracemalloc.start()
    held = []
    try:
        for index in range(messages):
            data = bytes(stream[index % distinct])
            sources.read('sensor', data, received_ns=0)
            del data
            if index in (0, messages - 1):
                held.append(tracemalloc.get_traced_memory()[0] / 2**20)
        peak = tracemalloc.get_traced_memory()[1] / 2**20
    finally:
        tracemalloc.stop()
    times_ms = np.array(times) * 1e3
    return {'median': float(np.median(times_ms)), 'p99': float(np.percentile(times_ms, 99)),
            'max': float(times_ms.max()), 'first_mb': held[0], 'last_mb': held[-1],
            'peak_mb': peak, 'rss_first': rss[0], 'rss_last': rss[-1],
            'message_mb': len(stream[0]) / 2**20}


def hold_table(messages: int) -> list[str]:
    """The callback's hold time and the memory over ``messages`` 100k-point clouds."""
    f = hold(messages)
    lines = ['| 100k-point PointCloud2 (%.1f MB), %d messages | value |' % (f['message_mb'],
                                                                          messages),
             '|---|---:|',
             f'| callback hold (decode + store), median | {f["median"]:.1f} ms |',
             f'| callback hold, p99 / max | {f["p99"]:.1f} / {f["max"]:.1f} ms |',
             f'| memory held after message 1 / {messages} (tracemalloc) | '
             f'{f["first_mb"]:.2f} / {f["last_mb"]:.2f} MB |',
             f'| peak while reading (tracemalloc) | {f["peak_mb"]:.2f} MB |',
             f'| RSS after message 1 / {messages} | {f["rss_first"]:.0f} / '
             f'{f["rss_last"]:.0f} MB |']
    for line in lines:
        print(line, flush=True)
    return lines


def run(number: int) -> list[str]:
    lines = ['| source | points in the filter (mean) | median (us) | p99 (us) | corrected | '
             'fail-safe | target (median) |',
             '|---|---:|---:|---:|---:|---:|---|']
    for name, kind, size, voxel, goal in CASES:
        figures = measure(kind, size, voxel, number)
        verdict = ('-' if goal is None else
                   f'<= {goal:,.0f} us: {"met" if figures["median"] <= goal else "not met"}')
        lines.append(f'| {name} | {figures["points"]:,.0f} | {figures["median"]:,.0f} | '
                     f'{figures["p99"]:,.0f} | {figures["active"]:.0%} | {figures["fail"]:.0%} '
                     f'| {verdict} |')
        print(lines[-1], flush=True)
        if figures['refusal']:
            print(f'  refused: {figures["refusal"]}', flush=True)
    return lines


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--calls', type=int, default=1000,
                        help='decisions timed per source (default 1000)')
    parser.add_argument('--hold-messages', type=int, default=100,
                        help='100k-point clouds read for the callback hold and memory '
                             '(default 100)')
    parser.add_argument('--no-write', dest='write', action='store_false',
                        help='print the section only; leave benchmarks/RESULTS.md alone')
    parser.add_argument('--against', metavar='DIR', type=Path, default=None,
                        help='instead: time this checkout and the rcbf_ros checkout in DIR '
                             'side by side, their decisions interleaved in one process on '
                             'the same inputs; print both medians and their ratio (RESULTS.md '
                             'is left alone)')
    parser.add_argument('--only', default='', metavar='TEXT',
                        help="with --against: only the cases whose name holds TEXT (e.g. "
                             "'LaserScan')")
    args = parser.parse_args(argv)
    if args.calls < 1:
        parser.error('--calls must be >= 1')
    if args.hold_messages < 2:
        parser.error('--hold-messages must be >= 2')
    if args.against is not None:
        if not (args.against / 'rcbf_ros' / '__init__.py').is_file():
            parser.error(f'--against: {args.against} holds no rcbf_ros package')
        if not any(args.only.lower() in name.lower() for name, *_ in CASES):
            parser.error(f"--only: no case's name holds {args.only!r}")
        try:
            compare_table(args.calls, args.against, args.only)
        except ValueError as exc:
            parser.error(str(exc))
        return 0
    table = run(args.calls)
    holding = hold_table(args.hold_messages)
    from benchmarks._results import load_averages, publish_section
    publish_section(
        TITLE, script='bench_sources.py'
        + (f' --calls {args.calls}' if args.calls != 1000 else '')
        + (f' --hold-messages {args.hold_messages}' if args.hold_messages != 100 else ''),
        conditions=f'; {load_averages()}',
        write=args.write, blocks=[
            'One decision from sources to command: the latest message read from its CDR '
            "bytes, the state's pose kept at its stamp (what the node does per state), the "
            "message's points taken into the state's frame (a scan in `base_link` through "
            "that pose) and into the filter, and one "
            '`SafetyFilter.filter` call (config/unicycle.yaml, `footprint.radius` 0.2 m; the '
            'robot at random in a square room of 8 m with 5 posts; proposals within the '
            'limits and a small disturbance box; `--calls` decisions per source after 20 '
            'unmeasured). LaserScan in `base_link` over a full turn (max range 8 m); '
            'PointCloud2 in `odom`, x/y/z/intensity FLOAT32, z in -0.2..1.5 m cut to the band '
            '0.05-0.5 m. "corrected": the answers that changed the proposal.',
            table, COLLISION_MONITOR,
            'What one 100k-point PointCloud2 (x/y/z/intensity FLOAT32, the band keeping about '
            'a quarter) costs the node: the time its source callback holds the executor '
            '(`ObservationSources.read`, decode + store: the node takes sensor messages as raw '
            'bytes, so this is the whole callback for a good message; another callback waits '
            'at most this long behind it), over a stream of such messages; and the memory: '
            "tracemalloc's current after the first and the last message (only the latest "
            "message's points are kept, so it stays flat) and its peak (one message's decode "
            'in flight), and the RSS.',
            holding,
            'Caveats: the machine (2 cores) was shared with other jobs, which moves the p99 '
            'most; the decode is timed per decision (the node reads a message once, when it '
            'arrives, so a decision between two messages costs less); no publishing; '
            "collision_monitor's figures come from its README, another machine and a "
            'different check (stop / slow-down zones, no QP), printed as a reference only. '
            "The callback hold leaves out the runtime's taking of the sample from DDS (a copy "
            'of its bytes) before the callback runs.'])
    return 0


if __name__ == '__main__':
    sys.exit(main())
