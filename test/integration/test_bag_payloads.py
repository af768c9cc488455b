"""A bag the recorder takes over DDS holds each message as exactly its serialized CDR, and the
events a transient-local publisher sent before the recorder existed.

One publisher process (this runtime's publishers, as every node uses them) offers
``/diagnostic`` DiagnosticArrays and ``/episode`` Strings of every length modulo 4, the events
topic transient local as the simulator offers it. It sends the first events before the recorder
starts, the rest once the recorder has matched. The bag is then read back: every payload must
equal rosbags' serialisation of the message it decodes to (no padding, no stray bytes), the
early events must be there, and the offered QoS must be in the bag's metadata as rosbag2 writes
it. Foxglove's own reader checks the same bag when npm is available.
"""
from __future__ import annotations

import json
import os
from pathlib import Path
import shutil
import signal
import subprocess
import sys
import textwrap
import time

from dds_harness import node_runtime, stop, subprocess_env  # this directory: on sys.path
import pytest
import yaml

from rcbf_ros.bag import bag_info, RecordedQos
from rcbf_ros.messages.typestore import jazzy_typestore

pytestmark = pytest.mark.integration

REPO_ROOT = Path(__file__).resolve().parents[2]
FOXGLOVE_TOOL = REPO_ROOT / 'test' / 'tools' / 'foxglove'
WAIT_S = 60.0
EARLY_EVENTS = 3
EVENTS = 8
DIAGNOSTICS = 40

# Early events, then (once the recorder matched both topics) DiagnosticArrays whose strings
# grow one character at a time, and more events: payload lengths of every residue modulo 4.
_PUBLISHER = textwrap.dedent("""
    import json, sys, time
    from rcbf_ros.ros.runtime import (
        DurabilityPolicy, get_message, HistoryPolicy, Node, QoSProfile, rclpy)
    early, events, diagnostics = (int(a) for a in sys.argv[1:4])
    rclpy.init()
    node = Node('payload_publisher')
    String = get_message('std_msgs/msg/String')
    Array = get_message('diagnostic_msgs/msg/DiagnosticArray')
    Status = get_message('diagnostic_msgs/msg/DiagnosticStatus')
    KeyValue = get_message('diagnostic_msgs/msg/KeyValue')
    events_pub = node.create_publisher(String, '/episode', QoSProfile(
        depth=10, durability=DurabilityPolicy.TRANSIENT_LOCAL))
    diag_pub = node.create_publisher(Array, '/diagnostics', QoSProfile(
        history=HistoryPolicy.KEEP_ALL, depth=1000))
    def event(i):
        return String(data=json.dumps({'event': 'start', 'episode': i}) + ' ' * (i % 4))
    for i in range(early):
        events_pub.publish(event(i))
    print('early events published', flush=True)
    deadline = time.monotonic() + 60
    while (events_pub.get_subscription_count() < 1
           or diag_pub.get_subscription_count() < 1):
        if time.monotonic() > deadline:
            sys.exit('the recorder never subscribed')
        rclpy.spin_once(node, timeout_sec=0.05)
    for i in range(diagnostics):
        status = Status(level=bytes([i % 3]), name='safety_filter', message='m' * i,
                        hardware_id='qp' * (i % 3),
                        values=[KeyValue(key='h_0', value=str(0.5 * i) + '0' * (i % 5))])
        diag = Array(status=[status])
        diag.header.frame_id = 'f' * (i % 4)
        diag_pub.publish(diag)
    for i in range(early, events):
        events_pub.publish(event(i))
    print('published', flush=True)
    while rclpy.ok():
        rclpy.spin_once(node, timeout_sec=0.1)
""")


@pytest.fixture(scope='module')
def bag(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The recorded bag directory (the recorder closed it with Ctrl-C)."""
    domain_id = 1 + (os.getpid() * 7 + 113) % 200
    bag = tmp_path_factory.mktemp('payloads') / 'bag'
    publisher = subprocess.Popen(
        [sys.executable, '-c', _PUBLISHER, str(EARLY_EVENTS), str(EVENTS), str(DIAGNOSTICS)],
        env=subprocess_env(domain_id), stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    recorder = None
    try:
        assert publisher.stdout.readline().strip() == 'early events published'
        recorder = subprocess.Popen(
            [sys.executable, '-m', 'rcbf_ros.ros.recorder_node', '--ros-args',
             '-p', f'output:={bag}', '-p', 'flush_period_s:=0.2',
             '-p', "topics:=['/episode', '/diagnostics']"],
            env=subprocess_env(domain_id), stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
            text=True)
        # Everything sent after the match; the early events (the recorder's transient-local
        # history) came before those, and the tests check for them.
        wanted = {'/episode': EVENTS - EARLY_EVENTS, '/diagnostics': DIAGNOSTICS}
        deadline = time.monotonic() + WAIT_S
        counts: dict[str, int] = {}
        while (any(counts.get(t, 0) < n for t, n in wanted.items())
               and time.monotonic() < deadline):
            assert recorder.poll() is None, recorder.stdout.read()
            if any(bag.glob('*.mcap')):
                counts = {n: t.message_count for n, t in bag_info(bag).topics.items()}
            time.sleep(0.2)
        log = stop(recorder, signal.SIGINT)
        assert recorder.returncode == 0, log
    finally:
        if recorder is not None:
            stop(recorder, signal.SIGKILL)
        stop(publisher, signal.SIGKILL)
    assert all(counts.get(t, 0) >= n for t, n in wanted.items()), log
    return bag


def _unstated_padding() -> bool:
    """Whether the payloads keep DDS's padding: under rclpy, rmw_cyclonedds hands over each
    sample zero-padded to a multiple of 4 bytes without stating the padding in the
    encapsulation options, and the recorder stores it as it came (as rosbag2 does); our
    runtime's writer states it, and the recorder removes it."""
    return node_runtime() == 'rclpy'


def _serialized_again(bag: Path) -> list[tuple[str, bytes, bytes]]:
    """(topic, payload, the payload's message serialized again by rosbags) for every message."""
    from mcap.reader import make_reader
    store = jazzy_typestore()
    with open(next(bag.glob('*.mcap')), 'rb') as stream:
        return [(channel.topic, message.data,
                 bytes(store.serialize_cdr(store.deserialize_cdr(message.data, schema.name),
                                           schema.name)))
                for schema, channel, message in make_reader(stream).iter_messages()]


def test_every_payload_is_exactly_the_serialized_message(bag: Path) -> None:
    lengths = set()
    for topic, payload, again in _serialized_again(bag):
        expected = again + bytes(-len(again) % 4) if _unstated_padding() else again
        assert payload == expected, (topic, payload[-8:].hex(), len(payload), len(again))
        lengths.add(len(again) % 4)
    assert lengths == {0, 1, 2, 3}  # every padding case was exercised


def test_events_sent_before_the_recorder_existed_are_recorded(bag: Path) -> None:
    from rcbf_ros.bag import read_bag_messages
    episodes = [json.loads(message.data)['episode']
                for _, message in read_bag_messages(bag, topics=['/episode'])]
    assert episodes == list(range(EVENTS))


def test_the_offered_qos_is_requested_and_recorded(bag: Path) -> None:
    topics = bag_info(bag).topics
    assert topics['/episode'].offered_qos == (
        RecordedQos(depth=10, durability='transient_local'),)
    assert topics['/diagnostics'].offered_qos == (RecordedQos(history='keep_all', depth=0),)
    meta = yaml.safe_load((bag / 'metadata.yaml').read_text())['rosbag2_bagfile_information']
    offered = {t['topic_metadata']['name']: t['topic_metadata']['offered_qos_profiles']
               for t in meta['topics_with_message_count']}
    # rosbag2 Jazzy (version 9) writes the profiles as a YAML sequence
    assert [profile['durability'] for profile in offered['/episode']] == ['transient_local']
    assert [profile['durability'] for profile in offered['/diagnostics']] == ['volatile']


def test_foxglove_reads_every_message_without_trailing_bytes(
        bag: Path, request: pytest.FixtureRequest,
        tmp_path_factory: pytest.TempPathFactory) -> None:
    """Foxglove's MCAP reader and ROS 2 decoder (npm packages, installed on first use into
    pytest's cache directory, outside the sources)."""
    npm, node = shutil.which('npm'), shutil.which('node')
    if npm is None or node is None:
        pytest.skip("npm and node are needed to run Foxglove's reader (not installed)")
    cache = getattr(request.config, 'cache', None)  # None under -p no:cacheprovider
    tool = Path(cache.mkdir('foxglove_bag_check') if cache is not None
                else tmp_path_factory.mktemp('foxglove_bag_check'))
    package = (FOXGLOVE_TOOL / 'package.json').read_text()
    if (tool / 'package.json').exists() and (tool / 'package.json').read_text() != package:
        shutil.rmtree(tool / 'node_modules', ignore_errors=True)
    (tool / 'package.json').write_text(package)
    shutil.copy(FOXGLOVE_TOOL / 'check_bag.cjs', tool / 'check_bag.cjs')
    if not (tool / 'node_modules').is_dir():
        install = subprocess.run([npm, 'install', '--no-audit', '--no-fund', '--ignore-scripts'],
                                 cwd=tool, capture_output=True, text=True, timeout=300)
        if install.returncode != 0:
            shutil.rmtree(tool / 'node_modules', ignore_errors=True)
            reason = (install.stderr.strip().splitlines() or ['no output'])[-1]
            pytest.skip(f"npm could not install Foxglove's reader: {reason}")
    check = subprocess.run([node, 'check_bag.cjs', str(next(bag.glob('*.mcap')))], cwd=tool,
                           capture_output=True, text=True, timeout=120)
    assert check.returncode == 0, check.stdout + check.stderr
    report = json.loads(check.stdout)
    assert report['complete']
    padded = {'/episode': 0, '/diagnostics': 0}
    for topic, _, again in _serialized_again(bag):
        padded[topic] += int(_unstated_padding() and len(again) % 4 != 0)
    assert report['topics'] == {
        '/episode': {'messages': EVENTS, 'trailing': padded['/episode'], 'errors': []},
        '/diagnostics': {'messages': DIAGNOSTICS, 'trailing': padded['/diagnostics'],
                         'errors': []}}
