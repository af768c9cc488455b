"""The recorder as a real process on loopback DDS, fed by a publisher process; the bags it leaves
are read by independent readers (rosbags' AnyReader, mcap_ros2's decoder, pymcap-cli)."""
from __future__ import annotations

from pathlib import Path
import shutil
import signal
import subprocess
import sys
import textwrap
import time
import warnings

from dds_harness import stop, subprocess_env  # this directory: on sys.path for pytest
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
import pytest
from rosbags.highlevel import AnyReader
import yaml

from rcbf_ros.bag import bag_info, BagError, read_bag_messages
from rcbf_ros.messages.typestore import jazzy_typestore

with warnings.catch_warnings():
    warnings.simplefilter('ignore', DeprecationWarning)  # the module warns on import
    from mcap_ros2.reader import read_ros2_messages

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


# Publishes /state = [i, 2i] for i = 0, 1, 2, ... (about 500 per second) until killed, from
# 1.5 s after the recorder's subscription matched: the recorder's side of the match can come
# later, and a volatile reader never receives what was sent before it matched.
_STREAMING_PUBLISHER = textwrap.dedent("""
    import sys, time
    from rcbf_ros.ros.runtime import get_message, HistoryPolicy, Node, QoSProfile, rclpy
    rclpy.init()
    node = Node('streaming_publisher')
    State = get_message('std_msgs/msg/Float64MultiArray')
    pub = node.create_publisher(State, '/state', QoSProfile(history=HistoryPolicy.KEEP_ALL,
                                                            depth=1000))
    deadline = time.monotonic() + 60
    while pub.get_subscription_count() < 1:
        if time.monotonic() > deadline:
            sys.exit('recorder never subscribed')
        rclpy.spin_once(node, timeout_sec=0.05)
    settle = time.monotonic() + 1.5
    while time.monotonic() < settle:
        rclpy.spin_once(node, timeout_sec=0.05)
    i = 0
    while rclpy.ok():
        state = State()
        state.data = [float(i), 2.0 * i]
        pub.publish(state)
        i += 1
        time.sleep(0.002)
""")


def _start_recorder(bag: Path, domain_id: int, topics: str, *extra: str) -> subprocess.Popen:
    args = [sys.executable, '-m', 'rcbf_ros.ros.recorder_node', '--ros-args',
            '-p', f'output:={bag}', '-p', 'flush_period_s:=0.2',
            '-p', 'discovery_period_s:=0.3', *extra]
    if topics:
        args += ['-p', f'topics:={topics}']
    return subprocess.Popen(args, env=subprocess_env(domain_id), stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)


def _start_publisher(domain_id: int) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, '-c', _PUBLISHER, str(N)],
                            env=subprocess_env(domain_id), stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)


def _wait_for_flushed(bag: Path, recorder: subprocess.Popen) -> None:
    """Poll the bag (read like a crashed one) until both topics have N messages on disk."""
    deadline = time.monotonic() + WAIT_S
    counts: dict[str, int] = {}
    while time.monotonic() < deadline:
        assert recorder.poll() is None, recorder.stdout.read()
        if any(bag.glob('*.mcap')):
            try:
                info = bag_info(bag)
            except BagError:  # the writer has created the file but not yet written its header
                time.sleep(0.2)
                continue
            counts = {name: t.message_count for name, t in info.topics.items()}
            if counts.get('/state') == N and counts.get('/cmd') == N:
                return
        time.sleep(0.2)
    pytest.fail(f'recorder did not flush {N} messages per topic within {WAIT_S} s: {counts}')


def _wait_for_whole_chunks(bag: Path, recorder: subprocess.Popen, publisher: subprocess.Popen,
                           *, at_least: int) -> int:
    """Poll the live bag until its whole chunks hold ``at_least`` messages; how many."""
    deadline = time.monotonic() + WAIT_S
    count = 0
    while time.monotonic() < deadline:
        assert recorder.poll() is None, recorder.stdout.read()
        assert publisher.poll() is None, publisher.stdout.read()
        if any(bag.glob('*.mcap')):
            try:
                count = bag_info(bag).message_count
            except BagError:  # the writer has created the file but not yet written its header
                time.sleep(0.1)
                continue
            if count >= at_least:
                return count
        time.sleep(0.1)
    pytest.fail(f'the recorder wrote {count} messages in whole chunks within {WAIT_S} s')


def _check_contents(state: list, cmd: list) -> None:
    assert [list(m.data) for m in state] == [[float(i), 2.0 * i] for i in range(N)]
    assert [(m.linear.x, m.angular.z) for m in cmd] == [(float(i), -float(i)) for i in range(N)]


def test_recorder_sigint_finalises_readable_bag(tmp_path: Path, ros_domain_id: int) -> None:
    bag = tmp_path / 'run_sigint'
    recorder = _start_recorder(bag, ros_domain_id, "['/state', '/cmd']")
    publisher = _start_publisher(ros_domain_id)
    try:
        _wait_for_flushed(bag, recorder)
        log = stop(recorder, signal.SIGINT)
    finally:
        stop(recorder, signal.SIGKILL)
        stop(publisher, signal.SIGTERM)
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


def test_recorder_sigkill_mid_recording_recovers_to_a_complete_bag(
        tmp_path: Path, ros_domain_id: int) -> None:
    """SIGKILL while messages still arrive; ``rcbf_ros bag recover`` then gives a bag that
    every reader accepts, holding a non-empty prefix of what was published."""
    bag = tmp_path / 'run_killed'
    recorder = _start_recorder(bag, ros_domain_id, "['/state']", '-p', 'chunk_size:=4096')
    publisher = subprocess.Popen([sys.executable, '-c', _STREAMING_PUBLISHER],
                                 env=subprocess_env(ros_domain_id), stdout=subprocess.PIPE,
                                 stderr=subprocess.STDOUT, text=True)
    try:
        on_disk = _wait_for_whole_chunks(bag, recorder, publisher, at_least=300)
        recorder.send_signal(signal.SIGKILL)
        recorder.wait(timeout=30)
        assert publisher.poll() is None, 'the publisher must still be publishing at the kill'
    finally:
        stop(recorder, signal.SIGKILL)
        stop(publisher, signal.SIGKILL)
    assert recorder.returncode == -signal.SIGKILL
    assert not (bag / 'metadata.yaml').exists()
    mcap_file = next(bag.glob('*.mcap'))
    with pytest.raises(BagError, match='cut short'):  # refused as it is
        list(read_bag_messages(bag))

    result = subprocess.run([sys.executable, '-m', 'rcbf_ros', 'bag', 'recover', str(bag)],
                            env=subprocess_env(ros_domain_id), capture_output=True, text=True,
                            timeout=120)
    assert result.returncode == 0, result.stdout + result.stderr
    assert f'{mcap_file}: recovered' in result.stdout

    def published(n: int) -> list[list[float]]:
        return [[float(i), 2.0 * i] for i in range(n)]

    with AnyReader([bag], default_typestore=jazzy_typestore()) as reader:
        counts = {c.topic: c.msgcount for c in reader.connections}
        states = [list(reader.deserialize(raw, c.msgtype).data)
                  for c, _, raw in reader.messages()]
    n = len(states)
    assert n >= on_disk > 0 and counts == {'/state': n}
    assert states == published(n), (result.stdout, states[:3])
    ros2 = [list(m.ros_msg.data) for m in read_ros2_messages(str(mcap_file))]
    assert ros2 == published(n)
    assert [list(m.data) for _, m in read_bag_messages(bag)] == published(n)
    doctor = subprocess.run([PYMCAP_CLI, 'doctor', str(mcap_file)], capture_output=True,
                            text=True, timeout=120)
    assert doctor.returncode == 0, doctor.stdout + doctor.stderr
    assert 'passed' in doctor.stdout
    meta = yaml.safe_load((bag / 'metadata.yaml').read_text())['rosbag2_bagfile_information']
    assert meta['message_count'] == n
