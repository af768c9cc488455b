"""The recorder as a real process on loopback DDS, fed by a publisher process; the bags it leaves
are read by independent readers (rosbags' AnyReader, mcap_ros2's decoder, pymcap-cli)."""
from __future__ import annotations

import os
from pathlib import Path
import shutil
import signal
import subprocess
import sys
import textwrap
import time

from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
import pytest
from rosbags.highlevel import AnyReader

from rcbf_ros.bag import bag_info, read_bag_messages, reindex_bag
from rcbf_ros.bag.messages import jazzy_typestore

pytestmark = pytest.mark.integration

REPO_ROOT = Path(__file__).resolve().parents[2]
PYMCAP_CLI = shutil.which('pymcap-cli') or str(Path(sys.executable).parent / 'pymcap-cli')
N = 200
WAIT_S = 60.0

# Publishes N Float64MultiArray on /state and N Twist on /cmd once the recorder has matched
# both, then stays alive (so reliable retransmissions can complete) until terminated.
_PUBLISHER = textwrap.dedent("""
    import sys, time
    from rcbf_ros.ros.runtime import (
        get_message, HistoryPolicy, Node, QoSProfile, rclpy)
    n = int(sys.argv[1])
    rclpy.init()
    node = Node('test_publisher')
    qos = QoSProfile(history=HistoryPolicy.KEEP_ALL, depth=1000)
    State = get_message('std_msgs/msg/Float64MultiArray')
    Twist = get_message('geometry_msgs/msg/Twist')
    pub_state = node.create_publisher(State, '/state', qos)
    pub_cmd = node.create_publisher(Twist, '/cmd', qos)
    deadline = time.monotonic() + 60
    while (pub_state.get_subscription_count() < 1 or pub_cmd.get_subscription_count() < 1):
        if time.monotonic() > deadline:
            sys.exit('recorder never subscribed')
        rclpy.spin_once(node, timeout_sec=0.05)
    for i in range(n):
        state = State()
        state.data = [float(i), 2.0 * i]
        pub_state.publish(state)
        cmd = Twist()
        cmd.linear.x = float(i)
        cmd.angular.z = -float(i)
        pub_cmd.publish(cmd)
    print('published', flush=True)
    while rclpy.ok():
        rclpy.spin_once(node, timeout_sec=0.1)
""")


def _env(domain_id: int) -> dict[str, str]:
    env = dict(os.environ)
    env.update(ROS_DOMAIN_ID=str(domain_id), PYTHONPATH=str(REPO_ROOT),
               RCBF_ROS_RUNTIME='cyclone', PYTHONUNBUFFERED='1')
    assert env.get('CYCLONEDDS_URI'), 'conftest pins Cyclone to loopback'
    return env


def _start_recorder(bag: Path, domain_id: int, topics: str) -> subprocess.Popen:
    args = [sys.executable, '-m', 'rcbf_ros.ros.recorder_node', '--ros-args',
            '-p', f'output:={bag}', '-p', 'flush_period_s:=0.2',
            '-p', 'discovery_period_s:=0.3']
    if topics:
        args += ['-p', f'topics:={topics}']
    return subprocess.Popen(args, env=_env(domain_id), stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)


def _start_publisher(domain_id: int) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, '-c', _PUBLISHER, str(N)], env=_env(domain_id),
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)


def _wait_for_flushed(bag: Path, recorder: subprocess.Popen) -> None:
    """Poll the bag (read like a crashed one) until both topics have N messages on disk."""
    deadline = time.monotonic() + WAIT_S
    counts: dict[str, int] = {}
    while time.monotonic() < deadline:
        assert recorder.poll() is None, recorder.stdout.read()
        if any(bag.glob('*.mcap')):
            info = bag_info(bag)
            counts = {name: t.message_count for name, t in info.topics.items()}
            if counts.get('/state') == N and counts.get('/cmd') == N:
                return
        time.sleep(0.2)
    pytest.fail(f'recorder did not flush {N} messages per topic within {WAIT_S} s: {counts}')


def _stop(proc: subprocess.Popen, sig: int) -> str:
    if proc.poll() is None:
        proc.send_signal(sig)
    try:
        out, _ = proc.communicate(timeout=30)
    except subprocess.TimeoutExpired:
        proc.kill()
        out, _ = proc.communicate()
    return out or ''


def _check_contents(state: list, cmd: list) -> None:
    assert [list(m.data) for m in state] == [[float(i), 2.0 * i] for i in range(N)]
    assert [(m.linear.x, m.angular.z) for m in cmd] == [(float(i), -float(i)) for i in range(N)]


def test_recorder_sigint_finalises_readable_bag(tmp_path: Path, ros_domain_id: int) -> None:
    bag = tmp_path / 'run_sigint'
    recorder = _start_recorder(bag, ros_domain_id, "['/state', '/cmd']")
    publisher = _start_publisher(ros_domain_id)
    try:
        _wait_for_flushed(bag, recorder)
        log = _stop(recorder, signal.SIGINT)
    finally:
        _stop(recorder, signal.SIGKILL)
        _stop(publisher, signal.SIGTERM)
    assert recorder.returncode == 0, log
    assert f'{2 * N} messages' in log, log
    assert (bag / 'metadata.yaml').is_file()

    with AnyReader([bag], default_typestore=jazzy_typestore()) as reader:
        assert {c.topic: c.msgcount for c in reader.connections} == {'/state': N, '/cmd': N}
        decoded: dict[str, list] = {'/state': [], '/cmd': []}
        for connection, _, raw in reader.messages():
            decoded[connection.topic].append(reader.deserialize(raw, connection.msgtype))
    _check_contents(decoded['/state'], decoded['/cmd'])

    mcap_file = next(bag.glob('*.mcap'))
    by_topic: dict[str, list] = {'/state': [], '/cmd': []}
    with open(mcap_file, 'rb') as stream:
        for _, channel, _, msg in make_reader(
                stream, decoder_factories=[DecoderFactory()]).iter_decoded_messages():
            by_topic[channel.topic].append(msg)
    _check_contents(by_topic['/state'], by_topic['/cmd'])
    doctor = subprocess.run([PYMCAP_CLI, 'doctor', str(mcap_file)], capture_output=True,
                            text=True, timeout=120)
    assert doctor.returncode == 0, doctor.stdout + doctor.stderr


def test_recorder_sigkill_leaves_flushed_data(tmp_path: Path, ros_domain_id: int) -> None:
    """All topics (discovery mode); SIGKILL once everything is on disk; nothing is lost."""
    bag = tmp_path / 'run_sigkill'
    recorder = _start_recorder(bag, ros_domain_id, '')
    publisher = _start_publisher(ros_domain_id)
    try:
        _wait_for_flushed(bag, recorder)
        _stop(recorder, signal.SIGKILL)
    finally:
        _stop(recorder, signal.SIGKILL)
        _stop(publisher, signal.SIGTERM)
    assert recorder.returncode == -signal.SIGKILL
    assert not (bag / 'metadata.yaml').exists()
    mcap_file = next(bag.glob('*.mcap'))

    recovered = tmp_path / 'recovered.mcap'
    result = subprocess.run([PYMCAP_CLI, 'recover', str(mcap_file), '-o', str(recovered),
                             '--force'], capture_output=True, text=True, timeout=120)
    assert result.returncode in (0, 3), result.stdout + result.stderr
    by_topic: dict[str, list] = {'/state': [], '/cmd': []}
    with open(recovered, 'rb') as stream:
        for _, channel, _, msg in make_reader(
                stream, decoder_factories=[DecoderFactory()]).iter_decoded_messages():
            by_topic.setdefault(channel.topic, []).append(msg)
    _check_contents(by_topic['/state'], by_topic['/cmd'])

    ours = {'/state': [], '/cmd': []}
    for item, msg in read_bag_messages(bag):
        ours.setdefault(item.topic, []).append(msg)
    _check_contents(ours['/state'], ours['/cmd'])
    reindex_bag(bag)
    assert (bag / 'metadata.yaml').is_file()
