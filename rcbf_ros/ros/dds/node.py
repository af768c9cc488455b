"""rclpy-compatible ``Node`` over Cyclone DDS: publishers, subscriptions, timers, parameters.

ROS 2 wire conventions (so stock Jazzy nodes interoperate): topic ``/a/b`` is the DDS topic
``rt/a/b`` of type ``pkg::msg::dds_::Type_`` (XCDR1, ``@final``); every endpoint carries USER_DATA
``typehash=RIHS01_<hex>;``; QoS as rmw_cyclonedds maps it (see :mod:`.qos`).
"""
from __future__ import annotations

from dataclasses import dataclass
import enum
import sys
import threading
import time
from typing import Any, Callable, Iterable, Sequence

from cyclonedds._clayer import ddspy_take, ddspy_write
from cyclonedds.builtin import (
    BuiltinDataReader,
    BuiltinTopicDcpsPublication,
    BuiltinTopicDcpsSubscription,
)
from cyclonedds.core import InstanceState, ReadCondition, SampleState, ViewState
from cyclonedds.pub import DataWriter
from cyclonedds.sub import DataReader
from cyclonedds.topic import Topic

from rcbf_ros.ros.dds import messages
from rcbf_ros.ros.dds.arguments import (
    check_namespace,
    check_node_name,
    parse_ros_arguments,
    resolve_topic_name,
)
from rcbf_ros.ros.dds.arguments import (
    parameter_overrides as collect_parameter_overrides,
)
from rcbf_ros.ros.dds.context import (
    Context,
    default_context,
    delete_entity,
    new_ready_queue,
    new_wait_objects,
)
from rcbf_ros.ros.dds.qos import as_profile, from_cyclone_qos, QoSProfile, to_cyclone_qos

_ANY_SAMPLE = SampleState.Any | ViewState.Any | InstanceState.Any
_TAKE_BATCH = 256
UNDECODABLE_WARNING_PERIOD_S = 1.0
"""Shortest interval between two warnings about undecodable samples on one subscription."""


# ----------------------------------------------------------------------------- time, logging
class Duration:
    """rclpy.duration.Duration subset (nanoseconds)."""

    def __init__(self, *, seconds: float = 0.0, nanoseconds: int = 0) -> None:
        self.nanoseconds = int(seconds * 1e9) + int(nanoseconds)

    def __repr__(self) -> str:
        return f'Duration(nanoseconds={self.nanoseconds})'

    def __eq__(self, other: object) -> bool:
        return isinstance(other, Duration) and other.nanoseconds == self.nanoseconds


class Time:
    """rclpy.time.Time subset: wall-clock (ROS system time) nanoseconds since the epoch."""

    def __init__(self, *, seconds: float = 0.0, nanoseconds: int = 0) -> None:
        self.nanoseconds = int(seconds * 1e9) + int(nanoseconds)

    def seconds_nanoseconds(self) -> tuple[int, int]:
        return divmod(self.nanoseconds, 10**9)

    def to_msg(self) -> messages.Message:
        """A ``builtin_interfaces/msg/Time``."""
        sec, nanosec = self.seconds_nanoseconds()
        return messages.get_message('builtin_interfaces/msg/Time')(sec=sec, nanosec=nanosec)

    @classmethod
    def from_msg(cls, msg: Any) -> Time:
        return cls(nanoseconds=msg.sec * 10**9 + msg.nanosec)

    def __sub__(self, other: Time | Duration) -> Time | Duration:
        if isinstance(other, Time):
            return Duration(nanoseconds=self.nanoseconds - other.nanoseconds)
        return Time(nanoseconds=self.nanoseconds - other.nanoseconds)

    def __add__(self, other: Duration) -> Time:
        return Time(nanoseconds=self.nanoseconds + other.nanoseconds)

    def __eq__(self, other: object) -> bool:
        return isinstance(other, Time) and other.nanoseconds == self.nanoseconds

    def __lt__(self, other: Time) -> bool:
        return self.nanoseconds < other.nanoseconds

    def __repr__(self) -> str:
        return f'Time(nanoseconds={self.nanoseconds})'


class Clock:
    """rclpy.clock.Clock subset (system time)."""

    def now(self) -> Time:
        return Time(nanoseconds=time.time_ns())


class LoggingSeverity(enum.IntEnum):
    """rclpy.logging.LoggingSeverity."""

    UNSET = 0
    DEBUG = 10
    INFO = 20
    WARN = 30
    ERROR = 40
    FATAL = 50


_LEVEL_NAMES = {'debug': LoggingSeverity.DEBUG, 'info': LoggingSeverity.INFO,
                'warn': LoggingSeverity.WARN, 'warning': LoggingSeverity.WARN,
                'error': LoggingSeverity.ERROR, 'fatal': LoggingSeverity.FATAL}


class Logger:
    """rcutils-style logger writing ``[LEVEL] [time] [name]: message`` to stderr."""

    def __init__(self, name: str, level: LoggingSeverity = LoggingSeverity.INFO) -> None:
        self.name = name
        self.level = level
        self._once: set[tuple[str, str]] = set()
        self._last: dict[tuple[str, str], float] = {}

    def get_child(self, suffix: str) -> Logger:
        return Logger(f'{self.name}.{suffix}', self.level)

    def set_level(self, level: LoggingSeverity | int) -> None:
        self.level = LoggingSeverity(level)

    def get_effective_level(self) -> LoggingSeverity:
        return self.level

    def _log(self, severity: LoggingSeverity, message: str, *, once: bool = False,
             throttle_duration_sec: float | None = None, skip_first: bool = False,
             **_ignored: Any) -> bool:
        if severity < self.level:
            return False
        key = (severity.name, str(message))
        if once:
            if key in self._once:
                return False
            self._once.add(key)
        if throttle_duration_sec is not None or skip_first:
            now = time.monotonic()
            last = self._last.get(key)
            if last is None:
                self._last[key] = now
                if skip_first:
                    return False
            elif throttle_duration_sec is not None and now - last < throttle_duration_sec:
                return False
            else:
                self._last[key] = now
        sys.stderr.write(f'[{severity.name}] [{time.time():.9f}] [{self.name}]: {message}\n')
        sys.stderr.flush()
        return True

    def debug(self, message: str, **kwargs: Any) -> bool:
        return self._log(LoggingSeverity.DEBUG, message, **kwargs)

    def info(self, message: str, **kwargs: Any) -> bool:
        return self._log(LoggingSeverity.INFO, message, **kwargs)

    def warning(self, message: str, **kwargs: Any) -> bool:
        return self._log(LoggingSeverity.WARN, message, **kwargs)

    warn = warning

    def error(self, message: str, **kwargs: Any) -> bool:
        return self._log(LoggingSeverity.ERROR, message, **kwargs)

    def fatal(self, message: str, **kwargs: Any) -> bool:
        return self._log(LoggingSeverity.FATAL, message, **kwargs)


# ----------------------------------------------------------------------------- parameters
class ParameterNotDeclaredException(KeyError):
    """get_parameter() of a name that was never declared (rclpy.exceptions')."""


class ParameterAlreadyDeclaredException(ValueError):
    """declare_parameter() twice for one name (rclpy.exceptions')."""


class InvalidParameterTypeException(TypeError):
    """An override's type differs from the declared default's (rclpy.exceptions')."""


class Parameter:
    """rclpy.parameter.Parameter subset: ``name``, ``value``, ``type_``."""

    class Type(enum.IntEnum):
        NOT_SET = 0
        BOOL = 1
        INTEGER = 2
        DOUBLE = 3
        STRING = 4
        BYTE_ARRAY = 5
        BOOL_ARRAY = 6
        INTEGER_ARRAY = 7
        DOUBLE_ARRAY = 8
        STRING_ARRAY = 9

        @classmethod
        def from_parameter_value(cls, value: Any) -> Parameter.Type:
            """The ROS parameter type of a Python value (``ValueError`` if none fits)."""
            if value is None:
                return cls.NOT_SET
            if isinstance(value, bool):
                return cls.BOOL
            if isinstance(value, int):
                return cls.INTEGER
            if isinstance(value, float):
                return cls.DOUBLE
            if isinstance(value, str):
                return cls.STRING
            if isinstance(value, (bytes, bytearray)):
                return cls.BYTE_ARRAY
            if isinstance(value, (list, tuple)):
                if all(isinstance(v, bool) for v in value):
                    return cls.BOOL_ARRAY if value else cls.NOT_SET
                if all(isinstance(v, int) and not isinstance(v, bool) for v in value):
                    return cls.INTEGER_ARRAY
                if all(isinstance(v, float) for v in value):
                    return cls.DOUBLE_ARRAY
                if all(isinstance(v, str) for v in value):
                    return cls.STRING_ARRAY
            raise ValueError(f'{value!r} is not a valid ROS parameter value (scalars or '
                             'homogeneous lists of bool/int/float/str)')

    def __init__(self, name: str, type_: Parameter.Type | None = None,
                 value: Any = None) -> None:
        if type_ is not None and not isinstance(type_, Parameter.Type) and value is None:
            type_, value = None, type_  # Parameter(name, value) convenience
        self.name = name
        self.value = list(value) if isinstance(value, tuple) else value
        self.type_ = Parameter.Type.from_parameter_value(value) if type_ is None else type_

    def get_parameter_value(self) -> Any:
        return self.value

    def __repr__(self) -> str:
        return f'Parameter({self.name!r}, {self.type_.name}, {self.value!r})'


# ----------------------------------------------------------------------------- endpoints
class Publisher:
    """rclpy.publisher.Publisher subset."""

    def __init__(self, node: Node, msg_type: Any, topic_name: str, qos: QoSProfile) -> None:
        self.msg_type = msg_type
        self.topic_name = topic_name
        self.qos_profile = qos
        self._type_name = messages.message_type_name(msg_type)
        self._topic = node._dds_topic(topic_name, self._type_name)
        self._writer = DataWriter(node.context.participant, self._topic,
                                  qos=to_cyclone_qos(qos, _user_data(self._type_name)))

    def publish(self, msg: Any) -> None:
        """Publish a message instance, or already serialized CDR bytes (as rclpy allows)."""
        if self._writer is None:
            raise RuntimeError(f'publisher on {self.topic_name!r} has been destroyed')
        if isinstance(msg, (bytes, bytearray, memoryview)):
            data = bytes(msg)
        else:
            if getattr(msg, '_type_name', None) != self._type_name:
                raise TypeError(f'publisher on {self.topic_name!r} expects {self._type_name}, '
                                f'got {type(msg).__name__}')
            data = messages.serialize_message(msg)
        ret = ddspy_write(self._writer._ref, messages.dds_payload(data))
        if isinstance(ret, int) and ret < 0:
            raise RuntimeError(f'DDS write on {self.topic_name!r} failed with code {ret}')

    def get_subscription_count(self) -> int:
        """Matched subscriptions (any process, including this one)."""
        return self._writer.get_publication_matched_status().current_count

    def destroy(self) -> None:
        delete_entity(self._writer)
        self._writer = None


class Subscription:
    """rclpy.subscription.Subscription subset; ``raw=True`` delivers CDR ``bytes``.

    A sample that does not decode as the topic's type (DDS has checked its structure, but not,
    e.g., that its strings are UTF-8) never reaches the callback nor escapes into the executor:
    it is dropped, counted in :attr:`undecodable_count`, and reported by a one-line warning
    naming the topic, at most once per :data:`UNDECODABLE_WARNING_PERIOD_S`. A node that must
    answer such samples subscribes with ``raw=True`` and decodes them itself.
    """

    def __init__(self, node: Node, msg_type: Any, topic_name: str,
                 callback: Callable[[Any], None], qos: QoSProfile, raw: bool) -> None:
        self.undecodable_count = 0
        """Samples dropped because they did not decode (since creation)."""
        self._logger = node.get_logger()
        self._last_warning_ns: int | None = None
        self._unreported = 0
        self.msg_type = msg_type
        self.topic_name = topic_name
        self.callback = callback
        self.qos_profile = qos
        self.raw = raw
        self._type_name = messages.message_type_name(msg_type)
        self._topic = node._dds_topic(topic_name, self._type_name)
        self._reader = DataReader(node.context.participant, self._topic,
                                  qos=to_cyclone_qos(qos, _user_data(self._type_name)))
        self._condition = ReadCondition(self._reader, _ANY_SAMPLE)

    def _take_ready(self) -> list[Callable[[], None]]:
        """Take every received sample now; return one work item per valid sample."""
        if self._reader is None:
            return []
        work: list[Callable[[], None]] = []
        while True:
            samples = ddspy_take(self._reader._ref, _ANY_SAMPLE, _TAKE_BATCH)
            if isinstance(samples, int):
                raise RuntimeError(f'DDS take on {self.topic_name!r} failed with code {samples}')
            work.extend(self._deliver_later(data) for data, info in samples if info.valid_data)
            if len(samples) < _TAKE_BATCH:
                return work

    def _deliver_later(self, data: bytes) -> Callable[[], None]:
        def deliver() -> None:
            if self.raw:
                self.callback(bytes(data))
                return
            try:
                message = messages.deserialize_message(data, self._type_name)
            except messages.DeserializationError as exc:
                self._drop_undecodable(exc)
                return
            self.callback(message)
        return deliver

    def _drop_undecodable(self, exc: messages.DeserializationError) -> None:
        """Count an undecodable sample and say so, throttled (the callback never sees it)."""
        self.undecodable_count += 1
        self._unreported += 1
        now = time.monotonic_ns()
        period_ns = int(UNDECODABLE_WARNING_PERIOD_S * 1e9)
        if self._last_warning_ns is not None and now - self._last_warning_ns < period_ns:
            return
        self._last_warning_ns = now
        self._logger.warning(
            f'{self.topic_name}: dropped {self._unreported} undecodable sample(s) '
            f'({self.undecodable_count} since start); last: {exc}')
        self._unreported = 0

    def get_publisher_count(self) -> int:
        return self._reader.get_subscription_matched_status().current_count

    def destroy(self) -> None:
        delete_entity(self._condition)
        delete_entity(self._reader)
        self._reader = self._condition = None


class Timer:
    """rclpy.timer.Timer subset on the monotonic clock; missed periods are skipped, not queued."""

    def __init__(self, period_ns: int, callback: Callable[[], None]) -> None:
        if period_ns <= 0:
            raise ValueError(f'timer period must be positive, got {period_ns} ns')
        self.timer_period_ns = period_ns
        self.callback = callback
        self._canceled = False
        self._next_ns = time.monotonic_ns() + period_ns

    def _due(self, now: int) -> bool:
        if self._canceled or now < self._next_ns:
            return False
        missed = (now - self._next_ns) // self.timer_period_ns
        self._next_ns += (missed + 1) * self.timer_period_ns
        return True

    def _fire(self) -> None:
        if not self._canceled:
            self.callback()

    def cancel(self) -> None:
        self._canceled = True

    def reset(self) -> None:
        self._canceled = False
        self._next_ns = time.monotonic_ns() + self.timer_period_ns

    def is_canceled(self) -> bool:
        return self._canceled

    def time_until_next_call(self) -> int | None:
        return None if self._canceled else self._next_ns - time.monotonic_ns()

    def destroy(self) -> None:
        self._canceled = True


class TopicEndpointTypeEnum(enum.IntEnum):
    """rclpy.topic_endpoint_info.TopicEndpointTypeEnum."""

    INVALID = 0
    PUBLISHER = 1
    SUBSCRIPTION = 2


@dataclass(frozen=True)
class TopicEndpointInfo:
    """rclpy.topic_endpoint_info.TopicEndpointInfo subset: one endpoint as discovery shows it.

    Node names travel in ROS 2's ``ros_discovery_info``, which this runtime does not read, so
    they are rmw's placeholders for endpoints of unknown nodes; ``endpoint_gid`` is the DDS
    GUID, whose first 12 bytes name the participant (one per process).
    """

    node_name: str
    node_namespace: str
    topic_type: str
    endpoint_type: TopicEndpointTypeEnum
    endpoint_gid: list[int]
    qos_profile: QoSProfile


def _user_data(type_name: str) -> bytes:
    return f'typehash={messages.type_hash(type_name)};'.encode()


# ----------------------------------------------------------------------------- node
class Node:
    """rclpy.node.Node subset over Cyclone DDS (see the module docstring)."""

    def __init__(self, node_name: str, *, context: Context | None = None,
                 cli_args: Sequence[str] | None = None, namespace: str | None = None,
                 use_global_arguments: bool = True,
                 parameter_overrides: Iterable[Parameter] | None = None,
                 allow_undeclared_parameters: bool = False,
                 automatically_declare_parameters_from_overrides: bool = False,
                 **_ignored: Any) -> None:
        self.context = default_context if context is None else context
        if not self.context.ok() or self.context.participant is None:
            raise RuntimeError('rclpy.init() must be called before creating a Node')
        arguments = [self.context.arguments] if use_global_arguments else []
        arguments.append(parse_ros_arguments(['--ros-args', *cli_args] if cli_args and
                                             '--ros-args' not in cli_args else cli_args))
        original_name = check_node_name(node_name)
        name, ns = original_name, namespace or '/'
        for args in arguments:
            name = args.node_name or name
            ns = args.namespace or ns
            for rule in args.remaps:
                if rule.match == '__node' and rule.node == original_name:
                    name = rule.replacement
        self._name = check_node_name(name)
        self._namespace = check_namespace(ns)
        self._remaps = [rule for args in reversed(arguments) for rule in args.remaps
                        if rule.node in (None, original_name, self._name)]
        log_level = next((a.log_level for a in reversed(arguments) if a.log_level), 'info')
        if log_level not in ('debug', 'info', 'warn', 'warning', 'error', 'fatal'):
            raise ValueError(f'--log-level {log_level!r} is not debug|info|warn|error|fatal')
        self._logger = Logger(self.get_fully_qualified_name().lstrip('/').replace('/', '.'),
                              {'debug': LoggingSeverity.DEBUG, 'info': LoggingSeverity.INFO,
                               'warn': LoggingSeverity.WARN, 'warning': LoggingSeverity.WARN,
                               'error': LoggingSeverity.ERROR,
                               'fatal': LoggingSeverity.FATAL}[log_level])
        self._overrides = collect_parameter_overrides(arguments, self._name,
                                                      self.get_fully_qualified_name())
        for parameter in parameter_overrides or ():
            self._overrides[parameter.name] = parameter.value
        self._allow_undeclared = allow_undeclared_parameters
        self._parameters: dict[str, Parameter] = {}
        self._clock = Clock()
        self._topics: dict[tuple[str, str], Topic] = {}
        self._publishers: list[Publisher] = []
        self._subscriptions: list[Subscription] = []
        self._timers: list[Timer] = []
        self._ready = new_ready_queue()
        self._spin_lock = threading.Lock()
        self._waitset, self._guard = new_wait_objects(self.context.participant)
        self._builtin_readers: list[tuple[BuiltinDataReader, ReadCondition, ReadCondition]] \
            | None = None
        self._endpoint_cache: dict[Any, list[Any]] = {}
        self.context.add_node(self)
        if automatically_declare_parameters_from_overrides:
            for name_, value in self._overrides.items():
                self.declare_parameter(name_, value)

    # names ----------------------------------------------------------------------------------
    def get_name(self) -> str:
        return self._name

    def get_namespace(self) -> str:
        return self._namespace

    def get_fully_qualified_name(self) -> str:
        return self._namespace.rstrip('/') + '/' + self._name

    def resolve_topic_name(self, topic: str, *, only_expand: bool = False) -> str:
        """Fully qualified name of ``topic`` for this node (remaps applied unless only_expand)."""
        return resolve_topic_name(topic, self._name, self._namespace,
                                  () if only_expand else self._remaps)

    def get_logger(self) -> Logger:
        return self._logger

    def get_clock(self) -> Clock:
        return self._clock

    # endpoints ------------------------------------------------------------------------------
    def _dds_topic(self, topic_name: str, type_name: str) -> Topic:
        key = (topic_name, type_name)
        if key not in self._topics:
            self._topics[key] = Topic(self.context.participant, 'rt' + topic_name,
                                      messages.idl_struct(type_name))
        return self._topics[key]

    def create_publisher(self, msg_type: Any, topic: str, qos_profile: QoSProfile | int,
                         **_ignored: Any) -> Publisher:
        publisher = Publisher(self, msg_type, self.resolve_topic_name(topic),
                              as_profile(qos_profile))
        self._publishers.append(publisher)
        return publisher

    def create_subscription(self, msg_type: Any, topic: str, callback: Callable[[Any], None],
                            qos_profile: QoSProfile | int, *, raw: bool = False,
                            **_ignored: Any) -> Subscription:
        subscription = Subscription(self, msg_type, self.resolve_topic_name(topic), callback,
                                    as_profile(qos_profile), raw)
        self._waitset.attach(subscription._condition)
        self._subscriptions.append(subscription)
        return subscription

    def create_timer(self, timer_period_sec: float, callback: Callable[[], None],
                     **_ignored: Any) -> Timer:
        timer = Timer(int(round(timer_period_sec * 1e9)), callback)
        self._timers.append(timer)
        self._wake()
        return timer

    def destroy_publisher(self, publisher: Publisher) -> bool:
        if publisher not in self._publishers:
            return False
        self._publishers.remove(publisher)
        publisher.destroy()
        return True

    def destroy_subscription(self, subscription: Subscription) -> bool:
        if subscription not in self._subscriptions:
            return False
        self._subscriptions.remove(subscription)
        self._waitset.detach(subscription._condition)
        subscription.destroy()
        return True

    def destroy_timer(self, timer: Timer) -> bool:
        if timer not in self._timers:
            return False
        self._timers.remove(timer)
        timer.destroy()
        return True

    def _wake(self) -> None:
        if self._guard is not None:
            self._guard.set(True)

    # parameters -----------------------------------------------------------------------------
    def declare_parameter(self, name: str, value: Any = None, descriptor: Any = None,
                          ignore_override: bool = False) -> Parameter:
        """Declare ``name`` with default ``value``; a command-line/file override wins.

        Raises:
            ParameterAlreadyDeclaredException: ``name`` was declared before.
            InvalidParameterTypeException: the override's type differs from the default's.
        """
        if isinstance(value, Parameter.Type):  # declare_parameter(name, Parameter.Type.X)
            declared_type, value = value, None
        else:
            declared_type = Parameter.Type.from_parameter_value(value)
        if name in self._parameters:
            raise ParameterAlreadyDeclaredException(f'parameter {name!r} already declared')
        if not ignore_override and name in self._overrides:
            override = self._overrides[name]
            try:
                override_type = Parameter.Type.from_parameter_value(override)
            except ValueError as exc:
                raise InvalidParameterTypeException(f'parameter {name!r}: {exc}') from exc
            compatible = (declared_type == Parameter.Type.NOT_SET
                          or override_type == declared_type
                          or (override_type == Parameter.Type.NOT_SET
                              and isinstance(override, list) and declared_type.name.endswith(
                                  '_ARRAY')))
            if not compatible:
                raise InvalidParameterTypeException(
                    f'parameter {name!r} of node {self.get_fully_qualified_name()!r}: override '
                    f'{override!r} is {override_type.name}, but the default {value!r} is '
                    f'{declared_type.name}')
            value = override
        parameter = Parameter(name, value=value)
        self._parameters[name] = parameter
        return parameter

    def declare_parameters(self, namespace: str, parameters: Iterable[tuple],
                           ignore_override: bool = False) -> list[Parameter]:
        """Declare ``(name,)``, ``(name, default)`` or ``(name, default, descriptor)`` items."""
        declared = []
        for item in parameters:
            if not isinstance(item, tuple) or not 1 <= len(item) <= 3:
                raise TypeError(f'declare_parameters items must be (name[, value[, '
                                f'descriptor]]) tuples, got {item!r}')
            full = f'{namespace}.{item[0]}' if namespace else item[0]
            declared.append(self.declare_parameter(full, *item[1:2],
                                                   ignore_override=ignore_override))
        return declared

    def has_parameter(self, name: str) -> bool:
        return name in self._parameters

    def get_parameter(self, name: str) -> Parameter:
        if name in self._parameters:
            return self._parameters[name]
        if self._allow_undeclared:
            return Parameter(name, value=None)
        raise ParameterNotDeclaredException(
            f'parameter {name!r} is not declared on node {self.get_fully_qualified_name()!r}')

    def get_parameters(self, names: Iterable[str]) -> list[Parameter]:
        return [self.get_parameter(name) for name in names]

    def get_parameters_by_prefix(self, prefix: str) -> dict[str, Parameter]:
        dotted = prefix + '.' if prefix else ''
        return {name[len(dotted):]: p for name, p in self._parameters.items()
                if name.startswith(dotted)}

    def set_parameters(self, parameters: Iterable[Parameter]) -> list[bool]:
        results = []
        for parameter in parameters:
            if parameter.name not in self._parameters and not self._allow_undeclared:
                raise ParameterNotDeclaredException(f'parameter {parameter.name!r} not declared')
            self._parameters[parameter.name] = Parameter(parameter.name, value=parameter.value)
            results.append(True)
        return results

    # graph ----------------------------------------------------------------------------------
    def _alive_endpoints(self, kinds: tuple[Any, ...] = (
            BuiltinTopicDcpsPublication, BuiltinTopicDcpsSubscription)) -> list[Any]:
        """Discovered (alive) endpoints of the given built-in topic kinds, local ones included.

        Reading them all converts every endpoint's QoS in Python (about 0.4 ms each), so the
        list of a kind is kept until discovery reports a change (an unread sample: a new
        endpoint, or one that went away).
        """
        if self._builtin_readers is None:
            alive = SampleState.Any | ViewState.Any | InstanceState.Alive
            unread = SampleState.NotRead | ViewState.Any | InstanceState.Any
            self._builtin_readers = []
            for kind in (BuiltinTopicDcpsPublication, BuiltinTopicDcpsSubscription):
                reader = BuiltinDataReader(self.context.participant, kind)
                self._builtin_readers.append(
                    (reader, ReadCondition(reader, alive), ReadCondition(reader, unread)))
            self._endpoint_cache = {}
        endpoints = []
        for kind, (reader, alive_condition, unread_condition) in zip(
                (BuiltinTopicDcpsPublication, BuiltinTopicDcpsSubscription),
                self._builtin_readers):
            if kind not in kinds:
                continue
            changed = reader.read(N=64, condition=unread_condition)  # any will do
            if changed or kind not in self._endpoint_cache:
                self._endpoint_cache[kind] = reader.read(N=100000, condition=alive_condition)
            endpoints.extend(self._endpoint_cache[kind])
        return endpoints

    def get_topic_names_and_types(self, no_demangle: bool = False) -> list[tuple[str, list[str]]]:
        """``[(topic, [type, ...]), ...]`` of every ROS topic seen by DDS discovery, sorted."""
        topics: dict[str, set[str]] = {}
        for endpoint in self._alive_endpoints():
            if no_demangle:
                topics.setdefault(endpoint.topic_name, set()).add(endpoint.type_name)
            elif endpoint.topic_name.startswith('rt/'):
                topics.setdefault(endpoint.topic_name[2:], set()).add(
                    messages.ros_type_name(endpoint.type_name))
        return sorted((name, sorted(types)) for name, types in topics.items())

    def get_publishers_info_by_topic(self, topic_name: str,
                                     no_mangle: bool = False) -> list[TopicEndpointInfo]:
        """Publishers of ``topic_name`` (expanded, not remapped, as rclpy does) in the graph."""
        return self._endpoints_info(topic_name, no_mangle, TopicEndpointTypeEnum.PUBLISHER)

    def get_subscriptions_info_by_topic(self, topic_name: str,
                                        no_mangle: bool = False) -> list[TopicEndpointInfo]:
        """Subscriptions of ``topic_name`` (expanded, not remapped) in the graph."""
        return self._endpoints_info(topic_name, no_mangle, TopicEndpointTypeEnum.SUBSCRIPTION)

    def _endpoints_info(self, topic_name: str, no_mangle: bool,
                        kind: TopicEndpointTypeEnum) -> list[TopicEndpointInfo]:
        dds_name = topic_name if no_mangle else 'rt' + self.resolve_topic_name(
            topic_name, only_expand=True)
        builtin = (BuiltinTopicDcpsPublication if kind == TopicEndpointTypeEnum.PUBLISHER
                   else BuiltinTopicDcpsSubscription)
        return [TopicEndpointInfo(node_name='_NODE_NAME_UNKNOWN_',
                                  node_namespace='_NODE_NAMESPACE_UNKNOWN_',
                                  topic_type=messages.ros_type_name(e.type_name),
                                  endpoint_type=kind, endpoint_gid=list(e.key.bytes),
                                  qos_profile=from_cyclone_qos(e.qos))
                for e in self._alive_endpoints((builtin,)) if e.topic_name == dds_name]

    def count_publishers(self, topic_name: str) -> int:
        """Alive publishers of ``topic_name`` (resolved for this node) in the DDS graph."""
        dds_name = 'rt' + self.resolve_topic_name(topic_name)
        return sum(1 for e in self._alive_endpoints((BuiltinTopicDcpsPublication,))
                   if e.topic_name == dds_name)

    def count_subscribers(self, topic_name: str) -> int:
        """Alive subscriptions of ``topic_name`` (resolved for this node) in the DDS graph."""
        dds_name = 'rt' + self.resolve_topic_name(topic_name)
        return sum(1 for e in self._alive_endpoints((BuiltinTopicDcpsSubscription,))
                   if e.topic_name == dds_name)

    # teardown -------------------------------------------------------------------------------
    def destroy_node(self) -> None:
        """Delete every DDS entity of this node (idempotent)."""
        if self._waitset is None:
            return
        for timer in self._timers:
            timer.destroy()
        for subscription in self._subscriptions:
            self._waitset.detach(subscription._condition)
            subscription.destroy()
        for publisher in self._publishers:
            publisher.destroy()
        for reader, alive_condition, unread_condition in self._builtin_readers or ():
            delete_entity(alive_condition)
            delete_entity(unread_condition)
            delete_entity(reader)
        self._timers, self._subscriptions, self._publishers = [], [], []
        self._ready.clear()
        waitset, guard = self._waitset, self._guard
        self._waitset = self._guard = None
        self._builtin_readers = None
        self._endpoint_cache = {}
        delete_entity(waitset)
        delete_entity(guard)
        for topic in self._topics.values():
            delete_entity(topic)
        self._topics.clear()
        self.context.remove_node(self)

