"""The Cyclone runtime's ROS graph: ``ros_discovery_info``, ``/rosout`` and ``use_sim_time``.

Checked without ROS: the graph sample is read by a bare Cyclone participant and decoded with
rosbags' own CDR decoder (not the runtime's message classes), and its GIDs are compared with
the endpoints' GUIDs as Cyclone's built-in discovery topics show them. Two contexts in one
process are two participants, as two processes would be. ``test/ros2/test_ros2_graph.py``
checks the same against the real ros2cli and rclpy.
"""
from __future__ import annotations

import inspect
import io
import os
import signal
import subprocess
import sys
import time
from typing import Any, Callable

from cyclonedds._clayer import ddspy_take
from cyclonedds.builtin import (
    BuiltinDataReader,
    BuiltinTopicDcpsPublication,
    BuiltinTopicDcpsSubscription,
)
from cyclonedds.core import InstanceState, Policy, Qos, ReadCondition, SampleState, ViewState
from cyclonedds.domain import DomainParticipant
from cyclonedds.sub import DataReader
from cyclonedds.topic import Topic
from dds_harness import REPO, subprocess_env  # this directory: on sys.path for pytest
import pytest
from rosbags.typesys import get_typestore, Stores

from rcbf_ros.ros.dds import graph, messages
from rcbf_ros.ros.dds.context import Context, ExternalShutdownException, spin_once
from rcbf_ros.ros.dds.node import Node as RuntimeNode
from rcbf_ros.ros.dds.node import Parameter, ParameterException
from rcbf_ros.ros.dds.qos import QoSProfile, ReliabilityPolicy

pytestmark = pytest.mark.integration


def Node(*args: Any, **kwargs: Any) -> RuntimeNode:  # noqa: N802 (stands in for the class)
    """A runtime node without the parameter services: their twelve endpoints would be in every
    graph entry checked here (test_runtime_services.py covers them in the graph's place)."""
    return RuntimeNode(*args, start_parameter_services=False, **kwargs)

_ANY = SampleState.Any | ViewState.Any | InstanceState.Any
_ALIVE = SampleState.Any | ViewState.Any | InstanceState.Alive
_STRING = messages.get_message('std_msgs/msg/String')


def _wait_for(check: Callable[[], Any], what: str, timeout: float = 10.0) -> Any:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        result = check()
        if result:
            return result
        time.sleep(0.05)
    raise AssertionError(f'timed out waiting for {what}')


@pytest.fixture
def contexts(ros_domain_id: int):
    """A factory of initialized contexts (participants) on the test's domain; all shut down
    at the end."""
    made: list[Context] = []

    def make() -> Context:
        context = Context()
        context.init(args=[], domain_id=ros_domain_id)
        made.append(context)
        return context
    yield make
    for context in made:
        context.try_shutdown()


class BareGraphReader:
    """A plain Cyclone participant reading ``ros_discovery_info`` as rmw does (TL, keep-all),
    decoding with rosbags."""

    def __init__(self, domain_id: int) -> None:
        self.participant = DomainParticipant(domain_id)
        topic = Topic(self.participant, graph.DISCOVERY_TOPIC,
                      messages.idl_struct(graph.PARTICIPANT_INFO_TYPE))
        self.reader = DataReader(self.participant, topic, qos=Qos(
            Policy.Reliability.Reliable(max_blocking_time=10**9), Policy.Durability.TransientLocal,
            Policy.History.KeepAll))
        self.builtin = {}
        for kind in (BuiltinTopicDcpsPublication, BuiltinTopicDcpsSubscription):
            reader = BuiltinDataReader(self.participant, kind)
            self.builtin[kind] = (reader, ReadCondition(reader, _ALIVE))
        self.store = get_typestore(Stores.ROS2_JAZZY)
        self.latest: dict[bytes, Any] = {}

    def take(self) -> dict[bytes, Any]:
        """Latest decoded sample per participant GID."""
        for data, info in ddspy_take(self.reader._ref, _ANY, 256):
            if info.valid_data:
                message = self.store.deserialize_cdr(bytes(data), graph.PARTICIPANT_INFO_TYPE)
                self.latest[bytes(message.gid.data)] = message
        return self.latest

    def nodes_of(self, participant_gid: bytes) -> list[tuple[str, str, set, set]]:
        message = self.take().get(participant_gid)
        if message is None:
            return []
        return [(n.node_namespace, n.node_name, {bytes(g.data) for g in n.reader_gid_seq},
                 {bytes(g.data) for g in n.writer_gid_seq})
                for n in message.node_entities_info_seq]

    def endpoints(self, kind: Any, participant_gid: bytes) -> dict[str, set]:
        """DDS topic name -> GUIDs of ``participant_gid``'s endpoints (built-in topics)."""
        found: dict[str, set] = {}
        reader, alive = self.builtin[kind]
        for sample in reader.read(N=1000, condition=alive):
            if sample.participant_key.bytes == participant_gid:
                found.setdefault(sample.topic_name, set()).add(sample.key.bytes)
        return found

    def close(self) -> None:
        self.participant.__del__()


@pytest.fixture
def bare(ros_domain_id: int):
    reader = BareGraphReader(ros_domain_id)
    yield reader
    reader.close()


def test_graph_sample_decodes_with_rosbags_and_lists_the_endpoint_guids(contexts, bare):
    context = contexts()
    node = Node('safety_filter', namespace='/robot', context=context)
    publisher = node.create_publisher(_STRING, 'cmd_safe', 10)
    subscription = node.create_subscription(_STRING, 'state', lambda _: None, 10)
    gid = context.participant.guid.bytes
    assert graph.gid_of(context.participant) == gid and len(gid) == graph.GID_SIZE

    def complete() -> Any:
        nodes = bare.nodes_of(gid)
        return nodes if nodes and len(nodes[0][2]) == 1 and len(nodes[0][3]) == 3 else None
    [(namespace, name, readers, writers)] = _wait_for(complete, 'the node with 4 endpoints')
    assert (namespace, name) == ('/robot', 'safety_filter')
    writers_seen = _wait_for(lambda: bare.endpoints(BuiltinTopicDcpsPublication, gid).get(
        'rt/robot/cmd_safe') and bare.endpoints(BuiltinTopicDcpsPublication, gid).get(
        'rt/parameter_events') and bare.endpoints(BuiltinTopicDcpsPublication, gid),
        'the writers in discovery')
    readers_seen = _wait_for(lambda: bare.endpoints(BuiltinTopicDcpsSubscription, gid).get(
        'rt/robot/state') and bare.endpoints(BuiltinTopicDcpsSubscription, gid),
        'the reader in discovery')
    # as rclpy's: every node publishes /rosout and /parameter_events
    assert writers == (writers_seen['rt/robot/cmd_safe'] | writers_seen['rt/rosout']
                       | writers_seen['rt/parameter_events'])
    assert readers == readers_seen['rt/robot/state']
    assert publisher._writer.guid.bytes in writers
    assert subscription._reader.guid.bytes in readers
    # the graph writer itself: rmw's topic, type, user data and QoS
    reader, alive = bare.builtin[BuiltinTopicDcpsPublication]
    [info_writer] = [e for e in reader.read(N=1000, condition=alive)
                     if e.participant_key.bytes == gid and e.topic_name == 'ros_discovery_info']
    assert info_writer.type_name == 'rmw_dds_common::msg::dds_::ParticipantEntitiesInfo_'
    assert info_writer.qos[Policy.Durability] == Policy.Durability.TransientLocal
    assert info_writer.qos[Policy.History] == Policy.History.KeepLast(1)
    assert isinstance(info_writer.qos[Policy.Reliability], Policy.Reliability.Reliable)
    assert info_writer.qos[Policy.Userdata].data == (
        f'typehash={messages.type_hash(graph.PARTICIPANT_INFO_TYPE)};'.encode())


def test_graph_sample_follows_endpoint_and_node_changes_and_reaches_late_joiners(
        contexts, bare, ros_domain_id):
    context = contexts()
    gid = context.participant.guid.bytes
    node = Node('simulator', context=context)
    publisher = node.create_publisher(_STRING, 'state', 10)
    subscription = node.create_subscription(_STRING, 'cmd_safe', lambda _: None, 10)
    own = {node._rosout.writer.guid.bytes,
           node._parameter_event_publisher._writer.guid.bytes}  # every node's, as rclpy's
    both = ('/', 'simulator', {subscription._reader.guid.bytes},
            own | {publisher._writer.guid.bytes})
    _wait_for(lambda: bare.nodes_of(gid) == [both], 'the node with its endpoints')
    node.destroy_publisher(publisher)
    node.destroy_subscription(subscription)
    _wait_for(lambda: bare.nodes_of(gid) == [('/', 'simulator', set(), own)],
              'the destroyed endpoints leaving the sample')
    other = Node('recorder', context=context)
    late = BareGraphReader(ros_domain_id)  # joins after every change: gets the current one
    try:
        nodes = _wait_for(lambda: late.nodes_of(gid), 'the current sample')
        assert nodes[0] == ('/', 'simulator', set(), own)
        assert [entry[:2] for entry in nodes] == [('/', 'simulator'), ('/', 'recorder')]
        node.destroy_node()
        _wait_for(lambda: [e[1] for e in late.nodes_of(gid)] == ['recorder'],
                  'the destroyed node leaving the sample')
        other.destroy_node()
        _wait_for(lambda: gid in late.take() and late.nodes_of(gid) == [],
                  'an empty node list')
    finally:
        late.close()


def test_node_names_and_endpoint_owners_across_participants(contexts):
    ours, theirs = contexts(), contexts()
    observer = Node('observer', context=ours)
    talker = Node('simulator', namespace='/sim', context=theirs)
    talker.create_publisher(_STRING, 'state', 10)
    expected = {('observer', '/'), ('simulator', '/sim')}
    _wait_for(lambda: set(observer.get_node_names_and_namespaces()) == expected,
              'both nodes in the graph')
    assert sorted(observer.get_node_names()) == ['observer', 'simulator']
    [info] = _wait_for(lambda: observer.get_publishers_info_by_topic('/sim/state'),
                       'the publisher in discovery')
    _wait_for(lambda: observer.get_publishers_info_by_topic('/sim/state')[0].node_name
              == 'simulator', 'the publisher named')
    [info] = observer.get_publishers_info_by_topic('/sim/state')
    assert (info.node_name, info.node_namespace) == ('simulator', '/sim')
    owners = {(i.node_name, i.node_namespace)
              for i in observer.get_publishers_info_by_topic('/rosout')}
    assert owners == expected
    theirs.shutdown()
    _wait_for(lambda: observer.get_node_names() == ['observer'],
              'the shut-down context leaving the graph')


def test_endpoint_owner_rules_are_rmws():
    participant, endpoint = b'p' * 16, b'e' * 16
    node = graph.NodeEntities(namespace='/', name='n', readers=[endpoint])
    assert graph.node_of_endpoint(participants={participant: [node]},
                                  participant_gid=participant, endpoint_gid=endpoint,
                                  is_reader=True) == ('n', '/')
    assert graph.node_of_endpoint(participants={participant: [node]},
                                  participant_gid=participant, endpoint_gid=endpoint,
                                  is_reader=False) == graph.NODE_NAME_UNKNOWN
    assert graph.node_of_endpoint(participants={}, participant_gid=participant,
                                  endpoint_gid=endpoint, is_reader=True) == graph.BARE_DDS_APP


# ----------------------------------------------------------------------------- /rosout
def test_log_lines_reach_rosout_with_rcls_fields(contexts, capsys):
    context, listener_context = contexts(), contexts()
    received: list[Any] = []
    listener = Node('listener', context=listener_context, enable_rosout=False)
    listener.create_subscription(messages.get_message('rcl_interfaces/msg/Log'), '/rosout',
                                 received.append, 10)
    node = Node('safety_filter', namespace='/robot', context=context)
    _wait_for(lambda: node._rosout.writer.get_publication_matched_status().current_count,
              'the /rosout subscription matched')
    node.get_logger().debug('below the level: not sent')
    node.get_logger().get_child('qp').warning('solver slow')
    log_line = inspect.currentframe().f_lineno + 1
    node.get_logger().info('filter ready')
    _wait_for(lambda: spin_once(listener, timeout_sec=0.05) or len(received) >= 2,
              'two Log messages')
    first, second = received[:2]
    assert (first.level, first.name, first.msg) == (30, 'robot.safety_filter.qp', 'solver slow')
    assert (second.level, second.name, second.msg) == (20, 'robot.safety_filter', 'filter ready')
    assert second.file == __file__
    assert second.function == 'test_log_lines_reach_rosout_with_rcls_fields'
    assert second.line == log_line
    assert abs(second.stamp.sec + second.stamp.nanosec * 1e-9 - time.time()) < 60
    err = capsys.readouterr().err
    assert '] [robot.safety_filter]: filter ready\n' in err  # the console line is unchanged
    assert 'below the level' not in err
    assert len(received) == 2
    # rcl's rosout QoS: reliable, transient local, keep-last 1000, lifespan 10 s
    qos = node._rosout.writer.get_qos()
    assert qos[Policy.History] == Policy.History.KeepLast(1000)
    assert qos[Policy.Durability] == Policy.Durability.TransientLocal
    assert qos[Policy.Lifespan] == Policy.Lifespan(10 * 10**9)


def test_quiet_logger_sends_nothing(contexts, monkeypatch):
    node = Node('quiet', context=contexts())
    writes: list[dict] = []
    monkeypatch.setattr(node._rosout, 'write', lambda **kw: writes.append(kw))
    node.get_logger().debug('not at this level')
    node.get_logger().info('once', once=True)
    node.get_logger().info('once', once=True)
    assert [w['msg'] for w in writes] == ['once']
    node.destroy_node()
    node.get_logger().info('after destroy: console only')
    assert node._rosout.writer is None


def test_disable_rosout_logs_leaves_nodes_without_rosout(ros_domain_id):
    context = Context()
    context.init(args=['prog', '--ros-args', '--enable-rosout-logs', '--disable-rosout-logs'],
                 domain_id=ros_domain_id)
    try:
        node = Node('silent', context=context)
        assert node._rosout is None
        assert node.get_logger().info('console only')
        [entry] = context.graph.participants()[context.graph.gid]
        # only /parameter_events, which every node publishes (as rclpy's)
        assert entry.writers == [graph.gid_of(node._parameter_event_publisher._writer)]
    finally:
        context.shutdown()


# ----------------------------------------------------------------------------- use_sim_time
def test_use_sim_time_declared_false_by_default(contexts):
    node = Node('plain', context=contexts())
    assert node.get_parameter('use_sim_time').value is False
    assert abs(node.get_clock().now().nanoseconds * 1e-9 - time.time()) < 60
    assert not node.get_clock().ros_time_is_active


def test_use_sim_time_follows_clock_and_switches_back(contexts):
    clock_type = messages.get_message('rosgraph_msgs/msg/Clock')
    time_type = messages.get_message('builtin_interfaces/msg/Time')
    context = contexts()
    node = Node('simulated', context=context,
                parameter_overrides=[Parameter('use_sim_time', value=True)])
    assert node.get_clock().ros_time_is_active
    assert node.get_clock().now().nanoseconds == 0  # no /clock yet
    clock_node = Node('clock', context=contexts())
    clock_pub = clock_node.create_publisher(
        clock_type, '/clock', QoSProfile(depth=1, reliability=ReliabilityPolicy.BEST_EFFORT))
    _wait_for(lambda: clock_pub.get_subscription_count(), '/clock matched')
    clock_pub.publish(clock_type(clock=time_type(sec=12, nanosec=5)))
    _wait_for(lambda: spin_once(node, timeout_sec=0.05)
              or node.get_clock().now().nanoseconds == 12 * 10**9 + 5, 'the /clock time')
    [result] = node.set_parameters([Parameter('use_sim_time', value=False)])
    assert result.successful
    assert not node.get_clock().ros_time_is_active
    assert abs(node.get_clock().now().nanoseconds * 1e-9 - time.time()) < 60
    [result] = node.set_parameters([Parameter('use_sim_time', value='yes')])
    assert not result.successful  # statically typed bool, as rclpy declares it


def test_timers_follow_clock_under_use_sim_time(contexts):
    clock_type = messages.get_message('rosgraph_msgs/msg/Clock')
    time_type = messages.get_message('builtin_interfaces/msg/Time')
    node = Node('simulated', context=contexts(),
                parameter_overrides=[Parameter('use_sim_time', value=True)])
    calls: list[int] = []
    node.create_timer(0.2, lambda: calls.append(node.get_clock().now().nanoseconds))
    clock_node = Node('clock', context=contexts())
    clock_pub = clock_node.create_publisher(
        clock_type, '/clock', QoSProfile(depth=1, reliability=ReliabilityPolicy.BEST_EFFORT))
    _wait_for(lambda: clock_pub.get_subscription_count(), '/clock matched')

    def spin_for(seconds: float) -> None:
        deadline = time.monotonic() + seconds
        while time.monotonic() < deadline:
            spin_once(node, timeout_sec=0.02)

    def set_sim_time(nanoseconds: int) -> None:
        sec, nanosec = divmod(nanoseconds, 10**9)

        def arrived() -> bool:
            clock_pub.publish(clock_type(clock=time_type(sec=sec, nanosec=nanosec)))
            spin_for(0.05)
            return node.get_clock().now().nanoseconds == nanoseconds
        _wait_for(arrived, f'simulated time {nanoseconds} ns')
        spin_for(0.1)

    spin_for(0.5)  # wall time passes, simulated time does not (zero: no /clock yet)
    assert calls == []
    set_sim_time(100_000_000)
    assert calls == []
    set_sim_time(250_000_000)
    assert calls == [250_000_000]
    set_sim_time(1_000_000_000)  # missed periods are skipped, not queued
    assert calls == [250_000_000, 1_000_000_000]
    set_sim_time(50_000_000)  # back beyond the last call: one period from there
    set_sim_time(200_000_000)
    assert calls == [250_000_000, 1_000_000_000]
    set_sim_time(260_000_000)
    assert calls == [250_000_000, 1_000_000_000, 260_000_000]


def test_a_use_sim_time_override_of_another_type_leaves_no_node(contexts):
    context = contexts()
    with pytest.raises(ParameterException, match="'use_sim_time'.*expecting type 'BOOL'"):
        Node('refused', context=context, parameter_overrides=[Parameter('use_sim_time', value=1)])
    assert context.graph.node_names_and_namespaces() == []
    assert context._nodes == []


def test_a_node_script_refuses_a_bad_use_sim_time_in_one_line(ros_domain_id):
    done = subprocess.run(
        [sys.executable, '-m', 'rcbf_ros.ros.recorder_node', '--ros-args', '-p',
         'use_sim_time:=1'], env=subprocess_env(ros_domain_id), cwd=REPO, timeout=120,
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    assert done.returncode == 2, done.stderr
    assert done.stderr.strip().splitlines() == [
        "recorder: cannot record: Trying to set parameter 'use_sim_time' to '1' of type "
        "'INTEGER', expecting type 'BOOL': use_sim_time"]


@pytest.mark.parametrize('signum, expected', [(signal.SIGINT, KeyboardInterrupt),
                                              (signal.SIGTERM, ExternalShutdownException)])
def test_a_signal_during_a_graph_query_raises_the_signals_exception(
        ros_domain_id, monkeypatch, signum, expected):
    # Cyclone builds discovery samples through Python callbacks; a signal handled inside one
    # used to come out of the query as a bare "Sampleinfo errored" Exception.
    context = Context()
    context.init(args=[], domain_id=ros_domain_id)  # installs the SIGINT/SIGTERM handlers
    try:
        node = Node('queried', context=context)
        node.create_publisher(_STRING, 'state', 10)
        _wait_for(lambda: node.count_publishers('state'), 'the publisher in discovery')
        node._endpoint_cache.clear()
        for reader, _, _ in node._builtin_readers:
            build = reader._constructor

            def build_with_signal(*args, build=build):
                os.kill(os.getpid(), signum)
                return build(*args)
            monkeypatch.setattr(reader, '_constructor', build_with_signal)
        with pytest.raises(expected):
            node.get_topic_names_and_types()
    finally:
        context.try_shutdown()


def test_use_sim_time_refuses_a_value_that_is_not_a_bool_as_rclpys_time_source(contexts):
    # Declared from an integer override before the time source looks: rclpy logs an error and
    # its time source refuses every later value that is not a bool.
    node = Node('auto', context=contexts(),
                parameter_overrides=[Parameter('use_sim_time', value=1)],
                automatically_declare_parameters_from_overrides=True)
    assert not node.get_clock().ros_time_is_active
    [result] = node.set_parameters([Parameter('use_sim_time', value=3)])
    assert not result.successful
    assert result.reason == 'use_sim_time parameter set to something besides a bool'
    assert node.get_parameter('use_sim_time').value == 1


def _discovery_writer(participant: DomainParticipant):
    """A writer of ``participant`` on the ROS 2 graph's discovery topic, with rmw's QoS."""
    from cyclonedds.pub import DataWriter
    topic = Topic(participant, graph.DISCOVERY_TOPIC,
                  messages.idl_struct(graph.PARTICIPANT_INFO_TYPE))
    return DataWriter(participant, topic, qos=Qos(
        Policy.Reliability.Reliable(max_blocking_time=10**9),
        Policy.Durability.TransientLocal, Policy.History.KeepLast(1)))


def test_an_undecodable_graph_sample_is_dropped_and_counted(contexts, ros_domain_id):
    from cyclonedds._clayer import ddspy_write
    context = contexts()
    observer = Node('observer', context=context)
    stranger = DomainParticipant(ros_domain_id)
    try:
        writer = _discovery_writer(stranger)
        # well-formed for DDS, but a node name that is not UTF-8
        valid = messages.serialize_message(graph.participant_info_message(
            participant_gid=stranger.guid.bytes,
            nodes=[graph.NodeEntities(namespace='/', name='AB')]))
        ddspy_write(writer._ref, messages.dds_payload(valid.replace(b'AB\x00', b'\xff\xfe\x00')))
        _wait_for(lambda: context.graph.participants() is not None
                  and context.graph.undecodable_count == 1, 'the sample counted')
        assert observer.get_node_names() == ['observer']
    finally:
        stranger.__del__()


def test_a_log_line_rosout_cannot_carry_goes_to_the_console_with_one_more_line(
        contexts, monkeypatch):
    node = Node('talker', context=contexts())
    console = io.StringIO()
    monkeypatch.setattr(sys, 'stderr', console)
    assert node.get_logger().info('bad \udcff text')
    err = console.getvalue()
    assert err.count('\n') == 2 and 'Failed to publish log message to rosout: ' in err


def test_a_spinning_node_takes_the_graph_samples_of_others_as_they_arrive(contexts,
                                                                          ros_domain_id):
    """The graph reader keeps every sample until taken: a node that never queries the graph
    (a filter answering ``ros2 param get``, which creates and destroys a client per call)
    must not hold every change another participant announced."""
    from cyclonedds._clayer import ddspy_read, ddspy_write
    context = contexts()
    node = Node('quiet', context=context)
    stranger = DomainParticipant(ros_domain_id)
    try:
        writer = _discovery_writer(stranger)
        _wait_for(lambda: writer.get_matched_subscriptions(), 'the graph reader matched')
        for index in range(40):
            sample = messages.serialize_message(graph.participant_info_message(
                participant_gid=stranger.guid.bytes,
                nodes=[graph.NodeEntities(namespace='/', name=f'n{index}')]))
            ddspy_write(writer._ref, messages.dds_payload(sample))

        def held() -> int:
            return len(ddspy_read(context.graph._reader._ref, _ANY, 1000))
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline:
            spin_once(node, timeout_sec=0.05)
            if held() == 0 and context.graph._remote:
                break
        assert held() == 0
        assert [n.name for n in context.graph._remote[stranger.guid.bytes]] == ['n39']
    finally:
        stranger.__del__()
