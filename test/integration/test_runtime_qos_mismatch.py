"""QoS that keeps a publisher and a subscription apart is said, once per pair, as rclpy says it.

The safety_filter node runs as its own process over loopback DDS; the test's node offers it
what it cannot take: a best-effort publisher on ``cmd_proposed`` (the filter subscribes
reliable) and a volatile one on ``obstacles`` (the filter subscribes transient-local). Each
side warns once per remote endpoint, in rclpy's words (its default incompatible-QoS event
callbacks), naming the topic as the node asked for it and the last incompatible policy:

- the filter (subscription): ``New publisher discovered on topic 'cmd_proposed', offering
  incompatible QoS. No messages will be received from it. Last incompatible policy:
  RELIABILITY``;
- the test's node (publisher): ``New subscription discovered on topic '/obstacles', requesting
  incompatible QoS. No messages will be sent to it. Last incompatible policy: DURABILITY``.

Samples sent on the mismatched pairs never reach the filter and never repeat the warning; a
second incompatible publisher is a new pair and gets a warning of its own.
"""
from __future__ import annotations

from pathlib import Path
import signal
import subprocess
import sys
import time

from dds_harness import end_process, subprocess_env  # this directory: on sys.path for pytest
import pytest
from test_safety_filter_node import Probe, UNICYCLE, WAIT_S

pytestmark = pytest.mark.integration

REPO = Path(__file__).resolve().parents[2]
SUBSCRIPTION_WARNING = ("[safety_filter]: New publisher discovered on topic '{topic}', offering "
                        'incompatible QoS. No messages will be received from it. Last '
                        'incompatible policy: {policy}')
PUBLISHER_WARNING = ("[probe]: New subscription discovered on topic '{topic}', requesting "
                     'incompatible QoS. No messages will be sent to it. Last incompatible '
                     'policy: {policy}')


def _wait_until(condition, what: str, process: subprocess.Popen, log: Path) -> None:
    deadline = time.monotonic() + WAIT_S
    while not condition():
        assert process.poll() is None, f'the filter ended:\n{log.read_text()[-3000:]}'
        assert time.monotonic() < deadline, f'never saw {what}:\n{log.read_text()[-3000:]}'
        time.sleep(0.05)


def test_each_incompatible_pair_is_warned_once_on_both_sides(ros_domain_id, tmp_path, capfd):
    from rcbf_ros.ros.runtime import get_message, QoSProfile, ReliabilityPolicy

    log = tmp_path / 'filter.log'
    with open(log, 'w') as out:
        process = subprocess.Popen(
            [sys.executable, '-m', 'rcbf_ros.ros.safety_filter_node', '--ros-args',
             '--params-file', UNICYCLE], env=subprocess_env(ros_domain_id), cwd=REPO,
            stdout=out, stderr=subprocess.STDOUT)
    probe = Probe(ros_domain_id)
    try:
        array = get_message('std_msgs/msg/Float64MultiArray')
        best_effort = QoSProfile(depth=10, reliability=ReliabilityPolicy.BEST_EFFORT)
        proposals = probe.node.create_publisher(array, '/cmd_proposed', best_effort)
        obstacles = probe.node.create_publisher(array, '/obstacles', QoSProfile(depth=1))
        probe.subscribe('std_msgs/msg/Float64MultiArray', '/filter_info')
        probe.start()
        reliability = SUBSCRIPTION_WARNING.format(topic='cmd_proposed', policy='RELIABILITY')
        durability = SUBSCRIPTION_WARNING.format(topic='obstacles', policy='DURABILITY')
        _wait_until(lambda: reliability in log.read_text() and durability in log.read_text(),
                    'both warnings of the filter', process, log)
        for _ in range(50):   # samples on refused pairs: nothing arrives, nothing is said again
            proposals.publish(array(data=[1.0, 0.0, 0.0, 0.0, 0.0]))
            obstacles.publish(array(data=[0.0, 0.0, 0.5]))
            time.sleep(0.01)
        second = probe.node.create_publisher(array, '/cmd_proposed', best_effort)
        _wait_until(lambda: log.read_text().count(reliability) == 2,
                    "the second pair's warning", process, log)
        for _ in range(20):
            second.publish(array(data=[1.0, 0.0, 0.0, 0.0, 0.0]))
            time.sleep(0.01)
        time.sleep(1.0)   # room for a repeat to show
        assert probe.count('/filter_info') == 0   # the filter never heard a proposal
        assert proposals.get_subscription_count() == obstacles.get_subscription_count() == 0
    finally:
        probe.close()
        code = end_process(process, sig=signal.SIGINT)
    ours = capfd.readouterr().err
    output = log.read_text()
    lines = output.splitlines()
    assert sum(reliability in line for line in lines) == 2, output[-3000:]
    assert sum(durability in line for line in lines) == 1, output[-3000:]
    assert all(line.startswith('[WARN] ') for line in lines
               if 'incompatible QoS' in line), output[-3000:]
    assert sum('incompatible QoS' in line for line in lines) == 3, output[-3000:]
    assert code == 0 and 'Traceback' not in output, output[-3000:]
    # The test's own node, as publisher: the filter's reliable subscription refuses each
    # best-effort publisher, its transient-local one the volatile publisher.
    ours_lines = [line for line in ours.splitlines() if 'incompatible QoS' in line]
    assert sorted(line.split('] ', 2)[2] for line in ours_lines) == sorted([
        PUBLISHER_WARNING.format(topic='/cmd_proposed', policy='RELIABILITY'),
        PUBLISHER_WARNING.format(topic='/cmd_proposed', policy='RELIABILITY'),
        PUBLISHER_WARNING.format(topic='/obstacles', policy='DURABILITY')]), ours
    assert all(line.startswith('[WARN] ') for line in ours_lines), ours
