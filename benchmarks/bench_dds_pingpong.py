"""Round-trip latency of a Float64MultiArray over loopback Cyclone DDS: raw vs our runtime.

``raw``: Cyclone's Python API directly (IdlStruct mirror from :mod:`rcbf_ros.ros.dds.messages`,
DataWriter.write / DataReader.take on a WaitSet): the transport's latency floor.
``runtime``: the same exchange through :mod:`rcbf_ros.ros.runtime` (Node, publish, spin_once,
rosbags CDR). An echo process returns every ping; the pinger stamps sends and receipts with its
own monotonic clock. Both modes run in one invocation so their ratio is comparable.

    python benchmarks/bench_dds_pingpong.py --rate 200 -n 1000
"""
from __future__ import annotations

# First: numpy's BLAS set up as in every rcbf_ros process (rcbf_ros/__init__.py).
import rcbf_ros  # noqa: F401  # isort: skip

import argparse
import os
from pathlib import Path
import subprocess
import sys
import time

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from rcbf_ros.ros.loopback import ensure_loopback  # noqa: E402

ensure_loopback()
TYPE = 'std_msgs/msg/Float64MultiArray'
PAYLOAD = 8  # doubles per message, a small state vector
DOMAIN = int(os.environ.get('ROS_DOMAIN_ID', '0')) or 97


def _raw_endpoints(participant, out_topic: str, in_topic: str):
    from cyclonedds.core import InstanceState, ReadCondition, SampleState, ViewState, WaitSet
    from cyclonedds.pub import DataWriter
    from cyclonedds.sub import DataReader
    from cyclonedds.topic import Topic

    from rcbf_ros.ros.dds.messages import idl_struct
    from rcbf_ros.ros.dds.qos import QoSProfile, to_cyclone_qos
    qos = to_cyclone_qos(QoSProfile(depth=10), b'')
    idl = idl_struct(TYPE)
    writer = DataWriter(participant, Topic(participant, 'rt' + out_topic, idl), qos=qos)
    reader = DataReader(participant, Topic(participant, 'rt' + in_topic, idl), qos=qos)
    waitset = WaitSet(participant)
    waitset.attach(ReadCondition(reader, SampleState.Any | ViewState.Any | InstanceState.Any))
    return idl, writer, reader, waitset


def echo(mode: str) -> None:
    """Return every message from /ping on /pong until /ping's writer leaves."""
    if mode == 'raw':
        from cyclonedds.domain import DomainParticipant
        from cyclonedds.util import duration
        participant = DomainParticipant(DOMAIN)
        idl, writer, reader, waitset = _raw_endpoints(participant, '/pong', '/ping')
        seen = False
        while True:
            waitset.wait(duration(milliseconds=100))
            for sample in reader.take(64):
                if isinstance(sample, idl):  # not the writer's unregistration
                    writer.write(sample)
                    seen = True
            matched = reader.get_subscription_matched_status().current_count
            if seen and matched == 0:
                return
    from rcbf_ros.ros.runtime import get_message, Node, rclpy
    rclpy.init(args=[], domain_id=DOMAIN)
    node = Node('echo')
    publisher = node.create_publisher(get_message(TYPE), '/pong', 10)
    subscription = node.create_subscription(get_message(TYPE), '/ping', publisher.publish, 10)
    seen = False
    while not seen or subscription.get_publisher_count() > 0:
        rclpy.spin_once(node, timeout_sec=0.1)
        seen = seen or publisher.get_subscription_count() > 0
    node.destroy_node()
    rclpy.try_shutdown()


def run_pingpong(rate_hz: float, n: int, mode: str = 'raw') -> np.ndarray:
    """Round-trip latencies (seconds, shape ``(n_received,)``) of ``n`` pings at ``rate_hz``."""
    env = dict(os.environ, PYTHONPATH=str(REPO), RCBF_ROS_RUNTIME='cyclone')
    echo_process = subprocess.Popen([sys.executable, __file__, '--echo', mode], env=env)
    sent: dict[int, int] = {}
    latencies: list[int] = []
    period_ns = int(1e9 / rate_hz)
    try:
        if mode == 'raw':
            from cyclonedds.domain import DomainParticipant
            from cyclonedds.util import duration
            participant = DomainParticipant(DOMAIN)
            idl, writer, reader, waitset = _raw_endpoints(participant, '/ping', '/pong')
            layout = idl_layout()
            while (writer.get_publication_matched_status().current_count == 0
                   or reader.get_subscription_matched_status().current_count == 0):
                time.sleep(0.01)
            time.sleep(0.2)
            for index in range(n):
                data = [float(index)] + [0.0] * (PAYLOAD - 1)
                sent[index] = time.monotonic_ns()
                writer.write(idl(layout=layout, data=data))
                deadline = sent[index] + period_ns
                while time.monotonic_ns() < deadline:
                    waitset.wait(duration(nanoseconds=max(deadline - time.monotonic_ns(), 1)))
                    for sample in reader.take(64):
                        if isinstance(sample, idl):
                                latencies.append(time.monotonic_ns() - sent[int(sample.data[0])])
            del writer
        else:
            from rcbf_ros.ros.runtime import get_message, Node, rclpy
            rclpy.init(args=[], domain_id=DOMAIN)
            node = Node('ping')
            message_class = get_message(TYPE)
            publisher = node.create_publisher(message_class, '/ping', 10)
            node.create_subscription(message_class, '/pong', lambda m: latencies.append(
                time.monotonic_ns() - sent[int(m.data[0])]), 10)
            while publisher.get_subscription_count() == 0 or node.count_publishers('/pong') == 0:
                rclpy.spin_once(node, timeout_sec=0.01)
            time.sleep(0.2)
            message = message_class()
            for index in range(n):
                message.data = [float(index)] + [0.0] * (PAYLOAD - 1)
                sent[index] = time.monotonic_ns()
                publisher.publish(message)
                deadline = sent[index] + period_ns
                while (remaining := deadline - time.monotonic_ns()) > 0:
                    rclpy.spin_once(node, timeout_sec=remaining / 1e9)
            node.destroy_node()
            rclpy.try_shutdown()
    finally:
        echo_process.wait(timeout=30)
    return np.array(latencies, dtype=np.float64) / 1e9


def idl_layout():
    from rcbf_ros.ros.dds.messages import idl_struct
    return idl_struct('std_msgs/msg/MultiArrayLayout')(dim=[], data_offset=0)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--rate', type=float, default=200.0)
    parser.add_argument('-n', type=int, default=1000)
    parser.add_argument('--echo', choices=('raw', 'runtime'))
    options = parser.parse_args()
    if options.echo:
        echo(options.echo)
        return
    medians = {}
    for mode in ('raw', 'runtime'):
        latencies = run_pingpong(options.rate, options.n, mode)
        medians[mode] = np.median(latencies)
        print(f'{mode:8s} received {len(latencies)}/{options.n}  round trip median '
              f'{1e6 * medians[mode]:.0f} us  p90 {1e6 * np.percentile(latencies, 90):.0f} us  '
              f'p99 {1e6 * np.percentile(latencies, 99):.0f} us')
    print(f'runtime / raw median ratio: {medians["runtime"] / medians["raw"]:.2f}')


if __name__ == '__main__':
    main()
