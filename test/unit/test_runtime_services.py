"""Services of the Cyclone runtime without ROS: rmw_cyclonedds's wire format, our client
against our service, and the parameter services every node offers."""
from __future__ import annotations

import struct
import time

from cyclonedds._clayer import ddspy_write
from cyclonedds.core import Policy, Qos
from cyclonedds.pub import DataWriter
from cyclonedds.sub import DataReader
from cyclonedds.topic import Topic
import pytest

from rcbf_ros.ros.dds import messages, services
from rcbf_ros.ros.dds import rclpy_compat as rclpy
from rcbf_ros.ros.dds.node import Node, Parameter, ParameterNotDeclaredException
from rcbf_ros.ros.dds.parameter_service import (
    parameter_from_msg,
    parameter_msg,
    PARAMETER_SERVICES,
)

GetParameters = services.get_service('rcl_interfaces/srv/GetParameters')
SetParameters = services.get_service('rcl_interfaces/srv/SetParameters')
SetAtomically = services.get_service('rcl_interfaces/srv/SetParametersAtomically')
ListParameters = services.get_service('rcl_interfaces/srv/ListParameters')
Describe = services.get_service('rcl_interfaces/srv/DescribeParameters')
GetTypes = services.get_service('rcl_interfaces/srv/GetParameterTypes')
ParameterEvent = messages.get_message('rcl_interfaces/msg/ParameterEvent')


def _hand_built_get_parameters_request() -> bytes:
    """What rmw_cyclonedds writes for GetParameters {names: [gain, a.b]}, client handle
    0x0102030405060708, sequence number 42: laid out byte by byte."""
    return (b'\x00\x01\x00\x00'                      # plain CDR, little endian
            + struct.pack('<Qq', 0x0102030405060708, 42)  # request header
            + struct.pack('<I', 2)                   # names: 2 strings
            + struct.pack('<I', 5) + b'gain\x00' + b'\x00' * 3  # length with NUL, pad to 4
            + struct.pack('<I', 4) + b'a.b\x00')


# ----------------------------------------------------------------------------- wire format
def test_a_request_laid_out_as_rmw_does_decodes():
    header, cdr = services.decode_sample(_hand_built_get_parameters_request())
    assert header == (0x0102030405060708, 42)
    assert messages.deserialize_message(cdr, GetParameters.Request).names == ['gain', 'a.b']


def test_encoding_gives_rmws_layout_and_cyclones_own_serializer_agrees():
    header = services.RequestHeader(0x0102030405060708, 42)
    ours = services.encode_sample(header=header, cdr=messages.serialize_message(
        GetParameters.Request(names=['gain', 'a.b'])))
    assert ours == _hand_built_get_parameters_request()
    mirror = services.sample_idl_struct('rcl_interfaces/srv/GetParameters_Request')
    assert mirror.__idl_typename__ == 'rcl_interfaces::srv::dds_::GetParameters_Request_'
    assert mirror(rmw_client_guid_=header.client_guid, rmw_sequence_number_=42,
                  names=['gain', 'a.b']).serialize() == ours


def test_a_big_endian_header_is_read_in_the_streams_order():
    data = b'\x00\x00\x00\x00' + struct.pack('>Qq', 7, 9) + struct.pack('>I', 0)
    header, cdr = services.decode_sample(data)
    assert header == (7, 9)
    assert messages.deserialize_message(cdr, GetParameters.Request).names == []


@pytest.mark.parametrize('data', [b'', b'\x00\x01\x00\x00' + bytes(15), b'\x12\x34' + bytes(30)])
def test_samples_without_a_header_are_refused_in_one_line(data):
    with pytest.raises(messages.DeserializationError, match='not a ROS 2 service sample'):
        services.decode_sample(data)


def test_endpoint_ids_are_written_as_rmw_writes_them():
    guid = bytes([0x01, 0x0f, 0xa0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 0xee, 0xee, 0xee, 0xee])
    expected = '01.f.a0.0.1.2.3.4.5.6.7.8.0.0.1.2'
    assert services.endpoint_id(participant_guid=guid, counter=0x0102) == expected


def test_user_data_values_are_found_by_key():
    qos = Qos(Policy.Userdata(b'clientid=01.2.3;typehash=RIHS01_ab;'))
    assert services.user_data_value(qos, 'clientid') == '01.2.3'
    assert services.user_data_value(qos, 'serviceid') is None
    assert services.user_data_value(None, 'clientid') is None


def test_service_types_register_once_and_refuse_a_different_definition():
    again = services.register_service_type('rcl_interfaces/srv/GetParameters',
                                           request='string[] names',
                                           response='ParameterValue[] values')
    assert again is GetParameters
    with pytest.raises(ValueError, match='GetParameters'):
        services.register_service_type('rcl_interfaces/srv/GetParameters',
                                       request='int32 names', response='bool ok')
    with pytest.raises(ValueError, match='unknown service type'):
        services.get_service('rcl_interfaces/srv/NoSuchService')


@pytest.mark.parametrize('parameter', [
    Parameter('b', value=True), Parameter('i', value=-3), Parameter('d', value=0.5),
    Parameter('s', value='x'), Parameter('by', value=[b'\x00', b'\xff']),
    Parameter('ba', value=[True, False]), Parameter('ia', value=[1, 2]),
    Parameter('da', value=[1.5]), Parameter('sa', value=['a', 'b']),
    Parameter('n', Parameter.Type.NOT_SET)])
def test_parameters_survive_the_message_and_the_wire(parameter):
    msg = messages.deserialize_message(messages.serialize_message(parameter_msg(parameter)),
                                       'rcl_interfaces/msg/Parameter')
    back = parameter_from_msg(msg)
    assert (back.name, back.type_, back.value) == (parameter.name, parameter.type_,
                                                   parameter.value)


# ----------------------------------------------------------------------------- over DDS
@pytest.fixture
def nodes(ros_domain_id):
    rclpy.init(args=[], domain_id=ros_domain_id)
    server = Node('safety_filter', namespace='/robot')
    server.declare_parameter('gain', 1.5)
    server.declare_parameter('limits.speed', 2.0)
    server.declare_parameter('limits.deep.x', 1)
    server.declare_parameter('mode', 'safe')
    probe = Node('probe', start_parameter_services=False)
    yield server, probe
    rclpy.try_shutdown()


def _matched_writer(node: Node, topic: str, type_name: str, *, qos: Qos | None = None
                    ) -> DataWriter:
    """A plain DDS writer of ``type_name`` on ``topic`` (a service's request or reply topic,
    past the runtime) in ``node``'s participant, once a reader matched it (or after 10 s)."""
    participant = node.context.participant
    writer = DataWriter(participant,
                        Topic(participant, topic, services.sample_idl_struct(type_name)), qos=qos)
    deadline = time.monotonic() + 10
    while not writer.get_matched_subscriptions() and time.monotonic() < deadline:
        time.sleep(0.01)
    return writer


def _call(server: Node, probe: Node, srv_type, name: str, request, timeout: float = 10.0):
    client = probe.create_client(srv_type, name)
    assert client.wait_for_service(timeout_sec=timeout), f'{name} never became available'
    future = client.call_async(request)
    deadline = time.monotonic() + timeout
    while not future.done() and time.monotonic() < deadline:
        rclpy.spin_once(server, timeout_sec=0.01)
        rclpy.spin_once(probe, timeout_sec=0.01)
    assert future.done(), f'no reply from {name}'
    probe.destroy_client(client)
    return future.result()


def test_every_node_serves_the_parameter_services_under_its_name(nodes):
    server, probe = nodes
    names = sorted(s.srv_name for s in server._service_endpoints)
    assert names == sorted(f'/robot/safety_filter/{name}' for name in PARAMETER_SERVICES)
    assert probe._service_endpoints == []


def test_get_parameters_answers_values_and_nothing_for_an_undeclared_name(nodes):
    server, probe = nodes
    reply = _call(server, probe, GetParameters, '/robot/safety_filter/get_parameters',
                  GetParameters.Request(names=['gain', 'mode']))
    assert [(v.type, v.double_value, v.string_value) for v in reply.values] == [
        (3, 1.5, ''), (4, 0.0, 'safe')]
    reply = _call(server, probe, GetParameters, '/robot/safety_filter/get_parameters',
                  GetParameters.Request(names=['gain', 'nope']))
    assert reply.values == []


def test_set_parameters_sets_each_and_says_why_one_fails(nodes):
    server, probe = nodes
    request = SetParameters.Request(parameters=[
        parameter_msg(Parameter('gain', value=2.5)), parameter_msg(Parameter('mode', value=1)),
        parameter_msg(Parameter('nope', value=1))])
    reply = _call(server, probe, SetParameters, '/robot/safety_filter/set_parameters', request)
    assert [r.successful for r in reply.results] == [True, False, False]
    assert reply.results[1].reason.startswith('Wrong parameter type')
    # rclpy 7.1.1's words: its list holds the undeclared names after the first, none here
    assert reply.results[2].reason == 'Invalid access to undeclared parameter(s): []'
    assert server.get_parameter('gain').value == 2.5
    assert server.get_parameter('mode').value == 'safe'


def test_set_parameters_atomically_sets_all_or_none(nodes):
    server, probe = nodes
    name = '/robot/safety_filter/set_parameters_atomically'
    bad = SetAtomically.Request(parameters=[parameter_msg(Parameter('gain', value=9.0)),
                                            parameter_msg(Parameter('mode', value=3))])
    assert not _call(server, probe, SetAtomically, name, bad).result.successful
    assert server.get_parameter('gain').value == 1.5
    good = SetAtomically.Request(parameters=[parameter_msg(Parameter('gain', value=9.0)),
                                             parameter_msg(Parameter('mode', value='x'))])
    assert _call(server, probe, SetAtomically, name, good).result.successful
    assert (server.get_parameter('gain').value, server.get_parameter('mode').value) == (9.0, 'x')


def test_list_describe_and_types_answer_as_rclpy(nodes):
    server, probe = nodes
    listed = _call(server, probe, ListParameters, '/robot/safety_filter/list_parameters',
                   ListParameters.Request(prefixes=['limits'], depth=1)).result
    assert (listed.names, listed.prefixes) == (['limits.speed'], ['limits'])
    described = _call(server, probe, Describe, '/robot/safety_filter/describe_parameters',
                      Describe.Request(names=['gain', 'mode'])).descriptors
    assert [(d.name, d.type) for d in described] == [('gain', 3), ('mode', 4)]
    types = _call(server, probe, GetTypes, '/robot/safety_filter/get_parameter_types',
                  GetTypes.Request(names=['limits.deep.x', 'mode'])).types
    assert list(types) == [2, 4]
    assert list(_call(server, probe, GetTypes, '/robot/safety_filter/get_parameter_types',
                      GetTypes.Request(names=['mode', 'nope'])).types) == []


def test_a_set_through_the_service_is_announced_on_parameter_events(nodes):
    server, probe = nodes
    events = []
    probe.create_subscription(ParameterEvent, '/parameter_events', events.append, 1000)
    deadline = time.monotonic() + 10
    while probe._subscriptions[0].get_publisher_count() == 0 and time.monotonic() < deadline:
        time.sleep(0.01)
    request = SetParameters.Request(parameters=[parameter_msg(Parameter('gain', value=3.0))])
    _call(server, probe, SetParameters, '/robot/safety_filter/set_parameters', request)
    while not events and time.monotonic() < deadline:
        rclpy.spin_once(probe, timeout_sec=0.05)
    (event,) = events
    assert event.node == '/robot/safety_filter'
    assert [p.name for p in event.changed_parameters] == ['gain']
    assert event.changed_parameters[0].value.double_value == 3.0
    assert event.new_parameters == [] and event.deleted_parameters == []


def test_a_user_service_replies_and_a_wrong_response_type_raises(nodes):
    server, probe = nodes
    seen = []

    def echo(request, response):
        seen.append(list(request.names))
        response.types = [len(name) for name in request.names]
        return response
    server.create_service(GetTypes, 'name_lengths', echo)
    reply = _call(server, probe, GetTypes, '/robot/name_lengths',
                  GetTypes.Request(names=['ab', 'abc']))
    assert list(reply.types) == [2, 3] and seen == [['ab', 'abc']]

    server.create_service(GetTypes, 'broken', lambda request, response: None)
    client = probe.create_client(GetTypes, '/robot/broken')
    assert client.wait_for_service(timeout_sec=10)
    client.call_async(GetTypes.Request())
    with pytest.raises(TypeError, match="service '/robot/broken': the callback returned "
                                        'NoneType'):
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline:
            rclpy.spin_once(server, timeout_sec=0.05)


def test_an_undecodable_request_is_dropped_and_the_service_goes_on(nodes, capfd):
    server, probe = nodes
    service = next(s for s in server._service_endpoints if s.srv_name.endswith('/get_parameters'))
    writer = _matched_writer(probe, 'rq/robot/safety_filter/get_parametersRequest',
                             'rcl_interfaces/srv/GetParameters_Request')
    deadline = time.monotonic() + 10
    # DDS checks a sample's structure; a name that is not UTF-8 gets past it.
    ddspy_write(writer._ref, b'\x00\x01\x00\x00' + struct.pack('<QqII', 1, 1, 1, 3)
                + b'\xff\xfe\x00\x00')
    while service.undecodable_count == 0 and time.monotonic() < deadline:
        rclpy.spin_once(server, timeout_sec=0.05)
    assert service.undecodable_count == 1
    assert 'get_parameters: dropped 1 undecodable sample(s)' in capfd.readouterr().err
    reply = _call(server, probe, GetParameters, '/robot/safety_filter/get_parameters',
                  GetParameters.Request(names=['gain']))
    assert [v.double_value for v in reply.values] == [1.5]


def test_a_reply_whose_client_never_reads_is_dropped_with_a_warning(nodes, capfd, monkeypatch):
    server, probe = nodes
    monkeypatch.setattr(services, 'REPLY_READER_WAIT_S', 0.2)
    # A client's request writer whose reply reader never appears.
    writer = _matched_writer(probe, 'rq/robot/safety_filter/get_parametersRequest',
                             'rcl_interfaces/srv/GetParameters_Request',
                             qos=Qos(Policy.Userdata(b'clientid=01.2.3.4;')))
    deadline = time.monotonic() + 10
    ddspy_write(writer._ref, _hand_built_get_parameters_request())
    service = next(s for s in server._service_endpoints if s.srv_name.endswith('/get_parameters'))
    while 'reply to request 42 dropped' not in capfd.readouterr().err:
        assert time.monotonic() < deadline, 'the pending reply was never given up'
        rclpy.spin_once(server, timeout_sec=0.05)
    assert service._pending == []


def test_client_call_spins_the_node_itself_and_times_out(nodes):
    server, probe = nodes
    client = probe.create_client(GetParameters, '/robot/safety_filter/get_parameters')
    assert client.wait_for_service(timeout_sec=10)
    assert client.call(GetParameters.Request(names=['gain']), timeout_sec=0.2) is None  # unserved
    assert client._futures == {}
    nobody = probe.create_client(GetParameters, '/nobody/get_parameters')
    assert not nobody.wait_for_service(timeout_sec=0.1)
    with pytest.raises(TypeError, match='expects rcl_interfaces/srv/GetParameters_Request'):
        client.call_async(SetParameters.Request())


# ----------------------------------------------------------------------------- Parameter API
def test_list_parameters_follows_rclpys_prefix_and_depth_rules(nodes):
    server, _ = nodes
    everything = server.list_parameters([], 0)
    assert everything.names == ['use_sim_time', 'gain', 'limits.speed', 'limits.deep.x', 'mode']
    assert everything.prefixes == ['limits', 'limits.deep']
    assert server.list_parameters([], 1).names == ['use_sim_time', 'gain', 'mode']
    assert server.list_parameters(['limits'], 0).names == ['limits.speed', 'limits.deep.x']
    assert server.list_parameters(['limits'], 1).names == ['limits.speed']
    assert server.list_parameters(['gain'], 1).names == ['gain']
    with pytest.raises(ValueError):
        server.list_parameters([], -1)
    with pytest.raises(TypeError):
        server.list_parameters('limits', 0)


def test_set_parameters_atomically_refuses_undeclared_names_before_setting_any(nodes):
    server, _ = nodes
    with pytest.raises(ParameterNotDeclaredException):
        server.set_parameters_atomically([Parameter('gain', value=5.0),
                                          Parameter('nope', value=1)])
    assert server.get_parameter('gain').value == 1.5
    assert server.get_parameter_types(['gain', 'mode']) == [3, 4]


def test_a_reply_carrying_another_clients_handle_is_not_taken(nodes):
    server, probe = nodes
    client = probe.create_client(GetParameters, '/robot/safety_filter/get_parameters')
    assert client.wait_for_service(timeout_sec=10)
    future = client.call_async(GetParameters.Request(names=['gain']))
    (sequence,) = client._futures
    writer = _matched_writer(server, 'rr/robot/safety_filter/get_parametersReply',
                             'rcl_interfaces/srv/GetParameters_Response')
    deadline = time.monotonic() + 10
    stranger = services.RequestHeader(client._writer_handle ^ 1, sequence)
    cdr = messages.serialize_message(GetParameters.Response())
    ddspy_write(writer._ref, services.encode_sample(header=stranger, cdr=cdr))
    for _ in range(20):
        rclpy.spin_once(probe, timeout_sec=0.01)
    assert not future.done()
    while not future.done() and time.monotonic() < deadline:
        rclpy.spin_once(server, timeout_sec=0.01)
        rclpy.spin_once(probe, timeout_sec=0.01)
    assert [v.double_value for v in future.result().values] == [1.5]


def test_each_matched_endpoint_is_read_once_however_many_requests(nodes, monkeypatch):
    """cyclonedds-python's matched-endpoint data calls leak native memory per call for an
    endpoint with USER_DATA: over many requests (one client, then a new client per request as
    ``ros2 param get`` does) each matched endpoint is read at most once."""
    server, probe = nodes
    reads = []
    for cls, name in ((DataReader, 'get_matched_publication_data'),
                      (DataWriter, 'get_matched_subscription_data')):
        original = getattr(cls, name)

        def counted(entity, handle, original=original, name=name):
            reads.append((name, entity._ref, handle))
            return original(entity, handle)
        monkeypatch.setattr(cls, name, counted)
    name = '/robot/safety_filter/get_parameters'
    client = probe.create_client(GetParameters, name)
    assert client.wait_for_service(timeout_sec=10)
    for _ in range(30):
        future = client.call_async(GetParameters.Request(names=['gain']))
        deadline = time.monotonic() + 10
        while not future.done() and time.monotonic() < deadline:
            rclpy.spin_once(server, timeout_sec=0.01)
            rclpy.spin_once(probe, timeout_sec=0.01)
        assert [v.double_value for v in future.result().values] == [1.5]
    # the client's two endpoints read the service's two, and the service the client's two
    assert len(reads) <= 4 and len(set(reads)) == len(reads)
    probe.destroy_client(client)
    for _ in range(5):
        reply = _call(server, probe, GetParameters, name, GetParameters.Request(names=['gain']))
        assert [v.double_value for v in reply.values] == [1.5]
    assert len(reads) <= 4 * 6 and len(set(reads)) == len(reads)
