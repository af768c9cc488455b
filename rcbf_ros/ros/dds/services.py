"""ROS 2 services and clients over Cyclone DDS, in rmw_cyclonedds_cpp's wire format.

A service ``/a/b`` of type ``pkg/srv/T`` is two DDS topics (rmw_cyclonedds_cpp 2.2,
``rmw_init_cs``): requests on ``rq/a/bRequest`` of type ``pkg::srv::dds_::T_Request_`` and
replies on ``rr/a/bReply`` of type ``pkg::srv::dds_::T_Response_``. Every sample, request or
reply, is the CDR encapsulation header, then a 16-byte request header in the stream's byte
order (the client's request writer's instance handle as ``uint64``, the request's sequence
number as ``int64``), then the fields of the request or response (:func:`encode_sample`); the
service copies the header into its reply, and a client keeps only replies that carry its own
writer's handle.

Endpoints: the service's request reader and reply writer both carry USER_DATA
``serviceid=<id>;typehash=<RIHS01 of their type>;``, a client's request writer and reply reader
``clientid=<id>;...``, the id being the participant's GUID prefix and a per-process counter
(:func:`endpoint_id`). A client counts a service as available once a matched request reader and
a matched reply writer carry the same ``serviceid`` (:meth:`Client.service_is_available`). A
service replies only once its reply writer has matched the reply reader whose ``clientid`` the
request's writer carries: rmw blocks up to 100 ms for that; here the reply waits, without
blocking the executor, up to :data:`REPLY_READER_WAIT_S`, and is dropped with a warning if the
client's reader never shows up (or at once, silently, if the client is gone).

QoS: what rmw gives services (reliable, volatile, keep-last; ``qos_profile_services_default``
depth 10, ``qos_profile_parameters`` depth 1000).

Service types: rosbags' type store has no services, so their two halves are registered from
their definitions (:func:`register_service_type`); rcl_interfaces' parameter services are
registered on first use (:func:`get_service`). Requests are served, and replies delivered to
futures, by the node's executor between other callbacks, one at a time.
"""
from __future__ import annotations

import functools
import itertools
import struct
import threading
import time
from typing import Any, Callable

from cyclonedds.core import InstanceState, Policy, ReadCondition, SampleState, ViewState
from cyclonedds.idl import IdlStruct, make_idl_struct
from cyclonedds.idl import types as idl_types
from cyclonedds.pub import DataWriter
from cyclonedds.sub import DataReader
from cyclonedds.topic import Topic
from rosbags.typesys import get_types_from_msg

from rcbf_ros.ros.dds import messages
from rcbf_ros.ros.dds.context import delete_entity, spin_once
from rcbf_ros.ros.dds.endpoints import DropsUndecodable, take_valid, write_payload
from rcbf_ros.ros.dds.qos import QoSProfile, to_cyclone_qos

REQUEST_TOPIC_PREFIX = 'rq'
"""DDS topic of a service's requests: ``rq<service name>Request``."""
REPLY_TOPIC_PREFIX = 'rr'
"""DDS topic of a service's replies: ``rr<service name>Reply``."""
REPLY_READER_WAIT_S = 1.0
"""Longest a reply waits for the reply writer to match the requesting client's reply reader."""

qos_profile_services_default = QoSProfile(depth=10)
"""rclpy's default QoS of services and clients: reliable, volatile, keep-last 10."""
qos_profile_parameters = QoSProfile(depth=1000)
"""rclpy's QoS of the parameter services: reliable, volatile, keep-last 1000."""

_ANY_SAMPLE = SampleState.Any | ViewState.Any | InstanceState.Any
_TAKE_BATCH = 64
_HEADERS = {b'\x00\x01': struct.Struct('<Qq'), b'\x00\x00': struct.Struct('>Qq')}
_HEADER_SIZE = 16
_UINT64 = (1 << 64) - 1
_endpoint_counter = itertools.count(1)
_sequence_counter = itertools.count(1)
_counter_lock = threading.Lock()


# ----------------------------------------------------------------------------- wire format
class RequestHeader(tuple):
    """``(client_guid, sequence_number)``: what rmw prefixes to every request and reply."""

    __slots__ = ()

    def __new__(cls, client_guid: int, sequence_number: int) -> RequestHeader:
        return super().__new__(cls, (client_guid, sequence_number))

    @property
    def client_guid(self) -> int:
        """The instance handle of the client's request writer (in the client's process)."""
        return self[0]

    @property
    def sequence_number(self) -> int:
        return self[1]


def encode_sample(*, header: RequestHeader, cdr: bytes) -> bytes:
    """The DDS payload of a request or reply: ``cdr`` (a serialized message, with its
    encapsulation header) with the request header spliced in after the encapsulation.

    The header is 16 bytes, so the fields after it keep their CDR alignment.

    Raises:
        ValueError: ``cdr`` is not a plain-CDR stream.
    """
    layout = _HEADERS.get(bytes(cdr[:2]))
    if layout is None or len(cdr) < 4:
        raise ValueError(f'not a plain CDR stream (encapsulation {bytes(cdr[:4]).hex()})')
    body = cdr[:4] + layout.pack(header.client_guid, header.sequence_number) + cdr[4:]
    return messages.dds_payload(body)


def decode_sample(data: bytes | memoryview) -> tuple[RequestHeader, bytes]:
    """Inverse of :func:`encode_sample`: the request header and the message's CDR stream.

    Raises:
        messages.DeserializationError: too short for the header, or not plain CDR.
    """
    view = memoryview(data).cast('B')
    layout = _HEADERS.get(bytes(view[:2]))
    if layout is None or len(view) < 4 + _HEADER_SIZE:
        raise messages.DeserializationError(
            f'not a ROS 2 service sample: {len(view)} bytes, encapsulation '
            f'{bytes(view[:4]).hex() or "missing"} (expected plain CDR and a 16-byte header)')
    guid, sequence = layout.unpack_from(view, 4)
    return RequestHeader(guid, sequence), bytes(view[:4]) + bytes(view[4 + _HEADER_SIZE:])


def endpoint_id(*, participant_guid: bytes, counter: int) -> str:
    """rmw's client/service id: the participant's 12-byte GUID prefix and a big-endian 32-bit
    counter, written as hex bytes joined by dots, the first two digits wide."""
    raw = bytes(participant_guid[:12]) + (counter & 0xFFFFFFFF).to_bytes(4, 'big')
    return f'{raw[0]:02x}' + ''.join(f'.{byte:x}' for byte in raw[1:])


def user_data_value(qos: Any, key: str) -> str | None:
    """The value of ``key`` in an endpoint's USER_DATA ``key=value;...`` list, if any."""
    user_data = None if qos is None else qos[Policy.Userdata]
    if user_data is None:
        return None
    for item in user_data.data.decode('utf-8', 'replace').split(';'):
        name, sep, value = item.partition('=')
        if sep and name == key:
            return value
    return None


_type_hash = functools.cache(messages.type_hash)
"""RIHS01 of a type, computed once (rosbags hashes the whole description on every call)."""


def _new_endpoint_id(participant: Any) -> str:
    with _counter_lock:
        counter = next(_endpoint_counter)
    return endpoint_id(participant_guid=participant.guid.bytes, counter=counter)


# ----------------------------------------------------------------------------- service types
class ServiceType:
    """Base of the generated service classes: ``Request`` and ``Response`` message classes, as
    rclpy's generated ``pkg.srv.T`` has them."""

    Request: type[messages.Message]
    Response: type[messages.Message]
    _type_name: str = ''


_RCL_INTERFACES_SERVICES = {
    'rcl_interfaces/srv/DescribeParameters': ('string[] names',
                                              'ParameterDescriptor[] descriptors'),
    'rcl_interfaces/srv/GetParameters': ('string[] names', 'ParameterValue[] values'),
    'rcl_interfaces/srv/GetParameterTypes': ('string[] names', 'uint8[] types'),
    'rcl_interfaces/srv/ListParameters': (
        'uint64 DEPTH_RECURSIVE=0\nstring[] prefixes\nuint64 depth',
        'ListParametersResult result'),
    'rcl_interfaces/srv/SetParameters': ('Parameter[] parameters',
                                         'SetParametersResult[] results'),
    'rcl_interfaces/srv/SetParametersAtomically': ('Parameter[] parameters',
                                                   'SetParametersResult result'),
}
"""The fields of rcl_interfaces' parameter services (Jazzy), request and response."""

_service_types: dict[str, type[ServiceType]] = {}
_registry_lock = threading.Lock()


def _service_type_name(type_name: str) -> str:
    parts = type_name.split('/')
    if len(parts) == 2:
        parts = [parts[0], 'srv', parts[1]]
    if len(parts) != 3 or parts[1] != 'srv' or not all(parts):
        raise ValueError(f'service type name {type_name!r} is not of the form pkg/srv/Type')
    return '/'.join(parts)


def register_service_type(type_name: str, *, request: str, response: str
                          ) -> type[ServiceType]:
    """Register ``pkg/srv/T`` from the two halves of its ``.srv`` definition (message
    definition syntax; names of other messages relative to ``pkg/msg``); its class.

    Registering the same definition twice gives the same class.

    Raises:
        ValueError: a malformed name or definition, or one that differs from an earlier one.
    """
    type_name = _service_type_name(type_name)
    package, _, name = type_name.split('/')
    with _registry_lock:
        store = messages.typestore()
        halves: dict[str, Any] = {}
        for suffix, text in (('Request', request), ('Response', response)):
            try:
                parsed = get_types_from_msg(text, f'{package}/msg/{name}_{suffix}')
            except Exception as exc:  # noqa: BLE001 - rosbags' parser raises several kinds
                raise ValueError(f'{type_name} {suffix.lower()}: {exc}') from exc
            halves[f'{type_name}_{suffix}'] = parsed[f'{package}/msg/{name}_{suffix}']
        try:
            store.register(halves)
        except Exception as exc:  # noqa: BLE001 - TypesysError: a different earlier definition
            raise ValueError(f'{type_name}: {exc}') from exc
        if type_name not in _service_types:
            cls = type(name, (ServiceType,), {
                '__doc__': f'ROS 2 service {type_name}.', '_type_name': type_name,
                'Request': messages.get_message(f'{type_name}_Request'),
                'Response': messages.get_message(f'{type_name}_Response')})
            cls.__module__ = f'{package}.srv'
            _service_types[type_name] = cls
        return _service_types[type_name]


def get_service(type_name: str) -> type[ServiceType]:
    """The class of a registered service type (rcl_interfaces' parameter services always).

    Raises:
        ValueError: the type was never registered.
    """
    type_name = _service_type_name(type_name)
    if type_name not in _service_types and type_name in _RCL_INTERFACES_SERVICES:
        request, response = _RCL_INTERFACES_SERVICES[type_name]
        register_service_type(type_name, request=request, response=response)
    if type_name not in _service_types:
        raise ValueError(f'unknown service type {type_name!r} (register it with '
                         'register_service_type)')
    return _service_types[type_name]


def service_type_name(srv_type: type[ServiceType] | str) -> str:
    """The ``pkg/srv/T`` name of a service class or name."""
    if isinstance(srv_type, str):
        return get_service(srv_type)._type_name
    name = getattr(srv_type, '_type_name', '')
    if not name or not hasattr(srv_type, 'Request') or not hasattr(srv_type, 'Response'):
        raise TypeError(f'{srv_type!r} is not a service class')
    return name


def sample_idl_struct(type_name: str) -> type[IdlStruct]:
    """The Cyclone ``IdlStruct`` of a request or response sample as rmw lays it out: the
    request header's two integers, then the message's fields; named ``pkg::srv::dds_::T_``."""
    with _registry_lock:
        if type_name not in _sample_structs:
            members: dict[str, Any] = {'rmw_client_guid_': idl_types.uint64,
                                       'rmw_sequence_number_': idl_types.int64}
            members.update(messages.idl_struct(type_name).__annotations__)
            _sample_structs[type_name] = make_idl_struct(
                type_name.rsplit('/', 1)[1] + '_', messages.dds_type_name(type_name), members)
        return _sample_structs[type_name]


_sample_structs: dict[str, type[IdlStruct]] = {}


# ----------------------------------------------------------------------------- futures
class Future:
    """rclpy.task.Future subset: a result set once, by the executor."""

    def __init__(self) -> None:
        self._done = threading.Event()
        self._result: Any = None
        self._cancelled = False
        self._callbacks: list[Callable[[Future], None]] = []

    def done(self) -> bool:
        return self._done.is_set()

    def cancelled(self) -> bool:
        return self._cancelled

    def cancel(self) -> None:
        if not self.done():
            self._cancelled = True
            self._finish()

    def result(self) -> Any:
        """The result (None while not done)."""
        return self._result

    def set_result(self, result: Any) -> None:
        self._result = result
        self._finish()

    def add_done_callback(self, callback: Callable[[Future], None]) -> None:
        if self.done():
            callback(self)
        else:
            self._callbacks.append(callback)

    def _finish(self) -> None:
        self._done.set()
        callbacks, self._callbacks = self._callbacks, []
        for callback in callbacks:
            callback(self)

    def _wait(self, timeout_sec: float | None) -> bool:
        return self._done.wait(timeout_sec)


# ----------------------------------------------------------------------------- endpoints
class MatchedEndpoints:
    """The QoS of the endpoints matched with one reader or writer of ours, each read once.

    cyclonedds-python's ``get_matched_publication_data`` and ``get_matched_subscription_data``
    leak native memory on every call for an endpoint that carries USER_DATA, as every rmw
    client and service endpoint does; called per request, they grew a node by about 0.3 KB a
    request. Cyclone never reuses an instance handle, so the QoS is kept per handle and
    forgotten once that endpoint is no longer matched: each matched endpoint is read at most
    once, and the cache holds no more than what is matched.
    """

    def __init__(self, entity: DataReader | DataWriter, *, publications: bool) -> None:
        """``entity``: our reader (``publications``: its matched writers) or our writer (its
        matched readers)."""
        self._entity = entity
        self._publications = publications
        self._qos: dict[int, Any] = {}

    def handles(self) -> list[int]:
        """Instance handles of the endpoints matched now (unsigned); forgets the others."""
        handles = [handle & _UINT64 for handle in (
            self._entity.get_matched_publications() if self._publications
            else self._entity.get_matched_subscriptions())]
        matched = set(handles)
        if not self._qos.keys() <= matched:
            self._qos = {h: qos for h, qos in self._qos.items() if h in matched}
        return handles

    def qos(self, handle: int) -> Any | None:
        """The QoS of the matched endpoint ``handle`` (from :meth:`handles`); None if it is
        not matched (any more)."""
        handle &= _UINT64
        if handle not in self._qos:
            read = (self._entity.get_matched_publication_data if self._publications
                    else self._entity.get_matched_subscription_data)
            data = read(handle)
            if data is None:
                return None
            self._qos[handle] = data.qos
        return self._qos[handle]

    def user_data_values(self, key: str) -> list[str | None]:
        """``key``'s value in the USER_DATA of each endpoint matched now."""
        values = []
        for handle in self.handles():
            qos = self.qos(handle)
            if qos is not None:
                values.append(user_data_value(qos, key))
        return values


class _Endpoint(DropsUndecodable):
    """What a service and a client share: a reader and a writer on the two topics."""

    def __init__(self, node: Any, srv_type: type[ServiceType] | str, service_name: str,
                 qos: QoSProfile, *, is_service: bool) -> None:
        self.srv_type = get_service(srv_type) if isinstance(srv_type, str) else srv_type
        type_name = service_type_name(self.srv_type)
        self.srv_name = service_name
        self.qos_profile = qos
        self._logger = node.get_logger()
        self._init_undecodable(logger=self._logger, name=service_name)
        participant = node.context.participant
        self.endpoint_id = _new_endpoint_id(participant)
        request_type, reply_type = f'{type_name}_Request', f'{type_name}_Response'
        read_type, write_type = (request_type, reply_type) if is_service else (
            reply_type, request_type)
        self._read_type, self._write_type = read_type, write_type
        topics = {request_type: f'{REQUEST_TOPIC_PREFIX}{service_name}Request',
                  reply_type: f'{REPLY_TOPIC_PREFIX}{service_name}Reply'}
        key = 'serviceid' if is_service else 'clientid'
        self._reader_topic = Topic(participant, topics[read_type], sample_idl_struct(read_type))
        self._writer_topic = Topic(participant, topics[write_type],
                                   sample_idl_struct(write_type))
        self._writer = DataWriter(participant, self._writer_topic, qos=to_cyclone_qos(
            qos, self._user_data(key, write_type)))
        self._reader = DataReader(participant, self._reader_topic, qos=to_cyclone_qos(
            qos, self._user_data(key, read_type)))
        self._condition = ReadCondition(self._reader, _ANY_SAMPLE)
        self._matched_writers = MatchedEndpoints(self._reader, publications=True)
        """The other side's endpoints writing to our reader (a client's request writers, or
        a service's reply writers)."""
        self._matched_readers = MatchedEndpoints(self._writer, publications=False)
        """The other side's endpoints reading our writer."""
        self._pending: list[tuple[int, int, RequestHeader, Any]] = []
        """A service's replies waiting for their client's reader (the executor looks at an
        endpoint with some on every pass, samples or not)."""

    def _user_data(self, key: str, type_name: str) -> bytes:
        return f'{key}={self.endpoint_id};typehash={_type_hash(type_name)};'.encode()

    def _take(self) -> list[tuple[bytes, Any]]:
        """Every valid sample received so far, with its sample info."""
        if self._reader is None:
            return []
        return take_valid(self._reader, batch=_TAKE_BATCH, name=repr(self.srv_name))

    def _decode(self, data: bytes) -> tuple[RequestHeader, Any] | None:
        """Header and message of a sample, or None (counted, warned about) if undecodable."""
        try:
            header, cdr = decode_sample(data)
            return header, messages.deserialize_message(cdr, self._read_type)
        except messages.DeserializationError as exc:
            self._drop_undecodable(exc)
            return None

    def _write(self, header: RequestHeader, message: Any) -> None:
        write_payload(self._writer, encode_sample(header=header,
                                                  cdr=messages.serialize_message(message)),
                      name=repr(self.srv_name))

    def destroy(self) -> None:
        for entity in (self._condition, self._reader, self._writer, self._reader_topic,
                       self._writer_topic):
            delete_entity(entity)
        self._condition = self._reader = self._writer = None
        self._reader_topic = self._writer_topic = None


class Service(_Endpoint):
    """rclpy.service.Service subset: ``callback(request, response) -> response``."""

    def __init__(self, node: Any, srv_type: type[ServiceType] | str, service_name: str,
                 callback: Callable[[Any, Any], Any], qos: QoSProfile) -> None:
        super().__init__(node, srv_type, service_name, qos, is_service=True)
        self.callback = callback

    def _take_ready(self) -> list[Callable[[], None]]:
        """Send replies that were waiting for their client; one work item per request."""
        if self._pending:
            self._retry_pending()
        return [self._serve_later(data, info.publication_handle)
                for data, info in self._take()]

    def _serve_later(self, data: bytes, writer_handle: int) -> Callable[[], None]:
        def serve() -> None:
            decoded = self._decode(data)
            if decoded is None or self._writer is None:
                return
            header, request = decoded
            response = self.callback(request, self.srv_type.Response())
            if not isinstance(response, self.srv_type.Response):
                raise TypeError(f'service {self.srv_name!r}: the callback returned '
                                f'{type(response).__name__}, expected '
                                f'{self.srv_type.Response._type_name}')
            deadline = time.monotonic_ns() + int(REPLY_READER_WAIT_S * 1e9)
            self._send_or_hold(deadline, writer_handle, header, response)
        return serve

    def _send_or_hold(self, deadline: int, writer_handle: int, header: RequestHeader,
                      response: Any) -> bool:
        """Send the reply if the client's reply reader is matched; drop it if the client is
        gone or the deadline passed; else keep it pending. True if it is settled."""
        presence = self._client_presence(writer_handle)
        if presence == 'gone':
            return True
        if presence == 'ready':
            self._write(header, response)
            return True
        if time.monotonic_ns() >= deadline:
            self._logger.warning(
                f'{self.srv_name}: reply to request {header.sequence_number} dropped: the '
                f"client's reply reader was not matched within {REPLY_READER_WAIT_S} s")
            return True
        self._pending.append((deadline, writer_handle, header, response))
        return False

    def _retry_pending(self) -> None:
        pending, self._pending = self._pending, []
        for deadline, writer_handle, header, response in pending:
            self._send_or_hold(deadline, writer_handle, header, response)

    def _client_presence(self, writer_handle: int) -> str:
        """``'ready'``: the reply writer has matched the reader of the client whose request
        writer is ``writer_handle`` (or that writer names no client id); ``'gone'``: that
        writer is no longer matched; ``'waiting'``: neither."""
        writer_handle &= _UINT64
        if writer_handle not in self._matched_writers.handles():
            return 'gone'
        writer = self._matched_writers.qos(writer_handle)
        if writer is None:
            return 'gone'
        client = user_data_value(writer, 'clientid')
        if client is None or client in self._matched_readers.user_data_values('clientid'):
            return 'ready'
        return 'waiting'


class Client(_Endpoint):
    """rclpy.client.Client subset: ``call_async``, ``call``, ``wait_for_service``."""

    def __init__(self, node: Any, srv_type: type[ServiceType] | str, service_name: str,
                 qos: QoSProfile) -> None:
        super().__init__(node, srv_type, service_name, qos, is_service=False)
        self._node = node
        self._writer_handle = self._writer.instance_handle & _UINT64  # Python gives it signed
        self._futures: dict[int, Future] = {}

    def service_is_available(self) -> bool:
        """True once a service's request reader and reply writer are both matched (the same
        ``serviceid`` on both, or any pair if the service gives none)."""
        readers = self._matched_readers.user_data_values('serviceid')
        writers = self._matched_writers.user_data_values('serviceid')
        if not readers or not writers:
            return False
        ids = {value for value in readers if value is not None}
        return not ids or any(value in ids for value in writers)

    def wait_for_service(self, timeout_sec: float | None = None) -> bool:
        """Wait until :meth:`service_is_available` (polled every 10 ms); False on timeout."""
        deadline = None if timeout_sec is None else time.monotonic() + timeout_sec
        while not self.service_is_available():
            if deadline is not None and time.monotonic() >= deadline:
                return False
            time.sleep(0.01)
        return True

    def call_async(self, request: Any) -> Future:
        """Send ``request``; the future gets the response when the node's executor takes it."""
        if not isinstance(request, self.srv_type.Request):
            raise TypeError(f'client of {self.srv_name!r} expects '
                            f'{self.srv_type.Request._type_name}, got {type(request).__name__}')
        with _counter_lock:
            sequence = next(_sequence_counter)
        future = Future()
        self._futures[sequence] = future
        future.add_done_callback(
            lambda done: self._futures.pop(sequence, None) if done.cancelled() else None)
        self._write(RequestHeader(self._writer_handle, sequence), request)
        return future

    def call(self, request: Any, timeout_sec: float | None = None) -> Any:
        """Send ``request`` and wait for the response (None on timeout).

        If no other thread spins the node, this one does (rclpy would wait forever)."""
        future = self.call_async(request)
        deadline = None if timeout_sec is None else time.monotonic() + timeout_sec
        while not future.done():
            left = None if deadline is None else deadline - time.monotonic()
            if left is not None and left <= 0:
                future.cancel()
                return None
            if self._node._spin_lock.locked():
                future._wait(0.05 if left is None else min(left, 0.05))
            else:
                spin_once(self._node, timeout_sec=0.05 if left is None else min(left, 0.05))
        return future.result()

    def _take_ready(self) -> list[Callable[[], None]]:
        """One work item per reply to one of this client's pending requests."""
        work: list[Callable[[], None]] = []
        for data, _info in self._take():
            decoded = self._decode(data)
            if decoded is None:
                continue
            header, response = decoded
            if header.client_guid != self._writer_handle:
                continue  # a reply to another client of the same service
            future = self._futures.pop(header.sequence_number, None)
            if future is not None and not future.done():
                work.append(lambda future=future, response=response:
                            future.set_result(response))
        return work

    def destroy(self) -> None:
        for future in list(self._futures.values()):
            future.cancel()
        self._futures.clear()
        super().destroy()
