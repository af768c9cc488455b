"""Replay a bag into a live recorder, both real processes on loopback DDS: the re-recorded bag
holds the same messages in the same order."""
from __future__ import annotations

from pathlib import Path
import signal
import subprocess
import sys

from dds_harness import stop, subprocess_env  # this directory: on sys.path for pytest
import pytest
from test_recorder import _start_recorder, _wait_for_flushed  # noqa: I001

from rcbf_ros.bag import BagWriter, read_bag

pytestmark = pytest.mark.integration

N = 200


def test_replay_into_recorder_reproduces_the_bag(tmp_path: Path, ros_domain_id: int) -> None:
    source = tmp_path / 'source'
    with BagWriter(source) as bag:
        bag.add_topic('/state', 'std_msgs/msg/Float64MultiArray')
        bag.add_topic('/cmd', 'geometry_msgs/msg/Twist')
        for i in range(N):
            t = 1_000_000_000 + i * 2_000_000
            bag.write_message('/state', {'data': [float(i), 2.0 * i]}, t)
            bag.write_message('/cmd', {'linear': {'x': float(i)}, 'angular': {'z': -float(i)}},
                              t + 1_000)
    copy = tmp_path / 'copy'
    recorder = _start_recorder(copy, ros_domain_id, "['/state', '/cmd']")
    replay = subprocess.Popen(
        [sys.executable, '-m', 'rcbf_ros.ros.replay_node', '--ros-args',
         '-p', f'bag:={source}', '-p', 'rate:=4.0', '-p', 'wait_for_subscribers_s:=30.0'],
        env=subprocess_env(ros_domain_id), stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
        text=True)
    try:
        _wait_for_flushed(copy, recorder)
        replay_log, _ = replay.communicate(timeout=60)
        stop(recorder, signal.SIGINT)
    finally:
        stop(recorder, signal.SIGKILL)
        stop(replay, signal.SIGKILL)
    assert replay.returncode == 0, replay_log
    assert f'{2 * N} messages published' in replay_log
    original = [(m.topic, m.data) for m in read_bag(source)]
    recorded = [(m.topic, m.data) for m in read_bag(copy)]
    # Same bytes per topic, in the same order (topics interleave by receive time).
    for topic in ('/state', '/cmd'):
        assert [d for t, d in recorded if t == topic] == [d for t, d in original if t == topic]
