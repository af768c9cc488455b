"""Recorder throughput at keep-all reliable QoS, nothing dropped, next to a counting subscriber.

For each payload size a publisher process sends N messages as fast as reliable keep-all
allows; in turn (same run, same publisher code) the receiver is

- ``count``: a process with one raw subscription that only counts (the transport's ceiling);
- ``recorder``: the recorder node writing the bag (zstd chunks, flush every 0.5 s).

Throughput is messages / (last receive time - first receive time); the recorder's is taken from
the bag's log times, and the bag must hold exactly N messages (nothing dropped). The ratio
recorder / count is the cost of recording.

Run: ``python benchmarks/bench_recorder.py [--messages 5000] [--sizes 1 100 10000] [--write]``.
"""
from __future__ import annotations

# First: numpy's BLAS set up as in every rcbf_ros process (rcbf_ros/__init__.py).
import rcbf_ros  # noqa: F401  # isort: skip

import argparse
import os
from pathlib import Path
import signal
import subprocess
import sys
import tempfile
import textwrap
import time

REPO_ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO_ROOT))

from rcbf_ros.bag import bag_info, read_bag  # noqa: E402
from rcbf_ros.ros.loopback import ensure_loopback  # noqa: E402

_PUBLISHER = textwrap.dedent("""
    import sys, time
    from rcbf_ros.ros.runtime import get_message, HistoryPolicy, Node, QoSProfile, rclpy
    n, size = int(sys.argv[1]), int(sys.argv[2])
    rclpy.init()
    node = Node('bench_publisher')
    State = get_message('std_msgs/msg/Float64MultiArray')
    pub = node.create_publisher(State, '/bench', QoSProfile(history=HistoryPolicy.KEEP_ALL,
                                                            depth=1000))
    while pub.get_subscription_count() < 1:
        rclpy.spin_once(node, timeout_sec=0.02)
    time.sleep(0.5)
    msg = State()
    msg.data = [0.5] * size
    for i in range(n):
        msg.layout.data_offset = i
        pub.publish(msg)
    print('published', flush=True)
    try:
        while rclpy.ok():
            rclpy.spin_once(node, timeout_sec=0.1)
    except BaseException:  # SIGTERM from the benchmark ends the publisher
        pass
""")

_COUNTER = textwrap.dedent("""
    import sys, time
    from rcbf_ros.ros.runtime import get_message, HistoryPolicy, Node, QoSProfile, rclpy
    n = int(sys.argv[1])
    rclpy.init()
    node = Node('bench_counter')
    times = []
    node.create_subscription(get_message('std_msgs/msg/Float64MultiArray'), '/bench',
                             lambda data: times.append(time.time_ns()),
                             QoSProfile(history=HistoryPolicy.KEEP_ALL, depth=1000), raw=True)
    deadline = time.monotonic() + 300
    while len(times) < n and time.monotonic() < deadline:
        rclpy.spin_once(node, timeout_sec=0.1)
    print(len(times), times[0] if times else 0, times[-1] if times else 0, flush=True)
""")


def _env(domain_id: int) -> dict[str, str]:
    env = dict(os.environ)
    ensure_loopback(env, force=True)
    env.update(ROS_DOMAIN_ID=str(domain_id), PYTHONPATH=str(REPO_ROOT),
               RCBF_ROS_RUNTIME='cyclone')
    return env


def _stop(proc: subprocess.Popen, sig: int) -> None:
    if proc.poll() is None:
        proc.send_signal(sig)
    try:
        proc.communicate(timeout=30)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.communicate()


def run_counter(n: int, size: int, domain_id: int) -> tuple[int, float]:
    """(received, messages/s) of the counting subscriber."""
    env = _env(domain_id)
    counter = subprocess.Popen([sys.executable, '-c', _COUNTER, str(n)], env=env,
                               stdout=subprocess.PIPE, text=True)
    publisher = subprocess.Popen([sys.executable, '-c', _PUBLISHER, str(n), str(size)],
                                 env=env, stdout=subprocess.PIPE, text=True)
    try:
        out, _ = counter.communicate(timeout=330)
    finally:
        _stop(counter, signal.SIGKILL)
        _stop(publisher, signal.SIGTERM)
    received, first, last = (int(x) for x in out.split())
    return received, (received - 1) / max(last - first, 1) * 1e9


def run_recorder(n: int, size: int, domain_id: int, workdir: Path) -> tuple[int, float, int]:
    """(messages in bag, messages/s, bag bytes) of the recorder."""
    env = _env(domain_id)
    bag = workdir / f'bench_{size}'
    recorder = subprocess.Popen(
        [sys.executable, '-m', 'rcbf_ros.ros.recorder_node', '--ros-args',
         '-p', f'output:={bag}', '-p', "topics:=['/bench']", '-p', 'discovery_period_s:=0.2'],
        env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    publisher = subprocess.Popen([sys.executable, '-c', _PUBLISHER, str(n), str(size)],
                                 env=env, stdout=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 300
        while time.monotonic() < deadline:
            if any(bag.glob('*.mcap')) and bag_info(bag).message_count >= n:
                break
            time.sleep(0.5)
        _stop(recorder, signal.SIGINT)
    finally:
        _stop(recorder, signal.SIGKILL)
        _stop(publisher, signal.SIGTERM)
    times = [m.log_time_ns for m in read_bag(bag)]
    size_bytes = sum(f.stat().st_size for f in bag.glob('*.mcap'))
    rate = (len(times) - 1) / max(times[-1] - times[0], 1) * 1e9 if times else 0.0
    return len(times), rate, size_bytes


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--messages', type=int, default=5000)
    parser.add_argument('--sizes', type=int, nargs='+', default=[1, 100, 10000],
                        help='doubles per Float64MultiArray')
    parser.add_argument('--domain-id', type=int, default=100 + os.getpid() % 100)
    parser.add_argument('--write', action='store_true', help='update benchmarks/RESULTS.md')
    args = parser.parse_args()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for size in args.sizes:
            counted, count_rate = run_counter(args.messages, size, args.domain_id)
            recorded, rec_rate, nbytes = run_recorder(args.messages, size, args.domain_id,
                                                      Path(tmp))
            rows.append((size, counted, count_rate, recorded, rec_rate, nbytes))
    print(f'\nN = {args.messages} messages per run, Float64MultiArray, keep-all reliable, '
          'loopback Cyclone DDS\n')
    print(f'{"doubles":>8} {"count rcv":>10} {"count msg/s":>12} {"bag msgs":>9} '
          f'{"recorder msg/s":>15} {"ratio":>6} {"dropped":>8} {"bag MB":>7}')
    for size, counted, count_rate, recorded, rec_rate, nbytes in rows:
        print(f'{size:>8} {counted:>10} {count_rate:>12.0f} {recorded:>9} {rec_rate:>15.0f} '
              f'{rec_rate / count_rate:>6.2f} {args.messages - recorded:>8} '
              f'{nbytes / 1e6:>7.2f}')
    if args.write:
        from benchmarks._results import machine_line, write_section
        table = ['| doubles per message | counting subscriber msg/s | recorder msg/s | '
                 'recorder / count | messages in bag | dropped | bag MB |',
                 '|---:|---:|---:|---:|---:|---:|---:|']
        table += [f'| {size} | {count_rate:.0f} | {rec_rate:.0f} | {rec_rate / count_rate:.2f} '
                  f'| {recorded} | {args.messages - recorded} | {nbytes / 1e6:.2f} |'
                  for size, counted, count_rate, recorded, rec_rate, nbytes in rows]
        write_section('Recorder throughput', (
            f'Command: `python benchmarks/bench_recorder.py --messages {args.messages} --sizes '
            f'{" ".join(map(str, args.sizes))} --write` (one run; {machine_line()}). '
            'Float64MultiArray, keep-all reliable QoS, loopback Cyclone DDS, the recorder node '
            'writing zstd-chunked MCAP; the bag must hold every published message.\n\n'
            + '\n'.join(table)))


if __name__ == '__main__':
    main()
