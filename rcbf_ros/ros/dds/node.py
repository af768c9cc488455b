"""rclpy-compatible ``Node`` over Cyclone DDS: publishers, subscriptions, timers, parameters.

ROS 2 wire conventions (so stock Jazzy nodes interoperate): topic ``/a/b`` is the DDS topic
``rt/a/b`` of type ``pkg::msg::dds_::Type_`` (XCDR1, ``@final``); every endpoint carries USER_DATA
``typehash=RIHS01_<hex>;``; QoS as rmw_cyclonedds maps it (see :mod:`.qos`).
"""
from __future__ import annotations

import array
from dataclasses import dataclass
import enum
import math
import sys
import threading
import time
from typing import Any, Callable, Iterable, Sequence
import warnings

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

from rcbf_ros.ros.dds import messages, services
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
from rcbf_ros.ros.dds.graph import gid_of, node_of_endpoint
from rcbf_ros.ros.dds.qos import as_profile, from_cyclone_qos, QoSProfile, to_cyclone_qos
from rcbf_ros.ros.dds.rosout import LOG_TYPE, ROSOUT_TOPIC, RosoutWriter
from rcbf_ros.ros.dds.time_source import TimeSource

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
    """rclpy.clock.ROSClock subset: system time, or the time ``/clock`` gives while the node's
    ``use_sim_time`` is true (:mod:`.time_source`)."""

    def __init__(self) -> None:
        self._ros_time_ns: int | None = None

    @property
    def ros_time_is_active(self) -> bool:
        return self._ros_time_ns is not None

    def _set_ros_time(self, nanoseconds: int | None) -> None:
        """Override the time (None: back to the system time)."""
        self._ros_time_ns = nanoseconds

    def now(self) -> Time:
        ros_time_ns = self._ros_time_ns
        return Time(nanoseconds=time.time_ns() if ros_time_ns is None else ros_time_ns)


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
    """rcutils-style logger writing ``[LEVEL] [time] [name]: message`` to stderr, and, for a
    node's logger and its children, the same line to ``/rosout`` (:mod:`.rosout`)."""

    def __init__(self, name: str, level: LoggingSeverity = LoggingSeverity.INFO,
                 rosout: RosoutWriter | None = None) -> None:
        self.name = name
        self.level = level
        self._rosout = rosout
        self._once: set[tuple[str, str]] = set()
        self._last: dict[tuple[str, str], float] = {}

    def get_child(self, suffix: str) -> Logger:
        return Logger(f'{self.name}.{suffix}', self.level, self._rosout)

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
        stamp_ns = time.time_ns()
        sys.stderr.write(f'[{severity.name}] [{stamp_ns // 10**9}.{stamp_ns % 10**9:09d}] '
                         f'[{self.name}]: {message}\n')
        sys.stderr.flush()
        if self._rosout is not None:
            caller = sys._getframe(2)  # the caller of debug() ... fatal()
            self._rosout.write(stamp_ns=stamp_ns, level=int(severity), name=self.name,
                               msg=str(message), file=caller.f_code.co_filename,
                               function=caller.f_code.co_name, line=caller.f_lineno)
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
class ParameterException(Exception):
    """Base of the parameter errors (rclpy.exceptions')."""

    def __init__(self, error_msg: str, parameters: str | list[str]) -> None:
        super().__init__(f'{error_msg}: {parameters}')


class ParameterNotDeclaredException(ParameterException):
    """get_parameter() / set_parameters() of a name that was never declared."""

    def __init__(self, parameters: str | list[str]) -> None:
        super().__init__('Invalid access to undeclared parameter(s)', parameters)


class ParameterAlreadyDeclaredException(ParameterException):
    """declare_parameter() twice for one name."""

    def __init__(self, parameters: str | list[str]) -> None:
        super().__init__('Parameter(s) already declared', parameters)


class InvalidParameterTypeException(ParameterException):
    """A value (an override, or a set) of another type than the parameter's static type."""

    def __init__(self, desired_parameter: Parameter, expected_type: str) -> None:
        value = desired_parameter.value
        super().__init__(
            f"Trying to set parameter '{desired_parameter.name}' to '{value}' of type "
            f"'{Parameter.Type.from_parameter_value(value).name}', expecting type "
            f"'{expected_type}'", desired_parameter.name)


class InvalidParameterValueException(ParameterException):
    """A value refused for another reason than its type (e.g. undeclaring a static one)."""

    def __init__(self, parameter: str, value: Any, reason: str) -> None:
        super().__init__(f'Invalid parameter value ({value}) for parameter. Reason: {reason}',
                         parameter)


class ParameterUninitializedException(ParameterException):
    """get_parameter() of a statically typed parameter that has no value."""

    def __init__(self, parameter_name: str) -> None:
        super().__init__(f"The parameter '{parameter_name}' is not initialized", parameter_name)


class ParameterImmutableException(ParameterException):
    """undeclare_parameter() of a read-only parameter."""

    def __init__(self, parameter_name: str) -> None:
        super().__init__('Attempted to modify read-only parameter', parameter_name)


class Parameter:
    """rclpy.parameter.Parameter: ``name``, ``type_``, ``value`` (NOT_SET: ``None``)."""

    class Type(enum.Enum):
        """rclpy.parameter.Parameter.Type (values: rcl_interfaces/msg/ParameterType)."""

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
            """The type rclpy infers from a Python value (an empty list is a BYTE_ARRAY).

            Raises:
                TypeError: no parameter type holds the value.
            """
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
            if isinstance(value, (list, tuple, array.array)):
                for kind, item_types in ((cls.BYTE_ARRAY, bytes), (cls.BOOL_ARRAY, bool),
                                         (cls.INTEGER_ARRAY, int), (cls.DOUBLE_ARRAY, float),
                                         (cls.STRING_ARRAY, str)):
                    if all(isinstance(v, item_types) for v in value):
                        return kind
                raise TypeError(f"The given value is not a list of one of the allowed types "
                                f"'{value}'.")
            raise TypeError(f"The given value is not one of the allowed types '{value}'.")

        def check(self, value: Any) -> bool:
            """True if ``value`` is a value of this type."""
            if self is Parameter.Type.NOT_SET:
                return value is None
            scalar = {Parameter.Type.BOOL: bool, Parameter.Type.INTEGER: int,
                      Parameter.Type.DOUBLE: float, Parameter.Type.STRING: str}.get(self)
            if scalar is not None:
                return isinstance(value, scalar)
            if self is Parameter.Type.BYTE_ARRAY:
                return isinstance(value, (list, tuple)) and all(
                    isinstance(v, bytes) and len(v) == 1 for v in value)
            item = {Parameter.Type.BOOL_ARRAY: bool, Parameter.Type.INTEGER_ARRAY: int,
                    Parameter.Type.DOUBLE_ARRAY: float, Parameter.Type.STRING_ARRAY: str}[self]
            containers = ((list, tuple, array.array) if item in (int, float)
                          else (list, tuple))
            return isinstance(value, containers) and all(isinstance(v, item) for v in value)

    def __init__(self, name: str, type_: Parameter.Type | None = None,
                 value: Any = None) -> None:
        if type_ is None:
            type_ = Parameter.Type.from_parameter_value(value)
        if not isinstance(type_, Parameter.Type):
            raise TypeError(f"type must be an instance of '{Parameter.Type!r}'")
        if not type_.check(value):
            raise ValueError(f"Type '{type_}' and value '{value}' do not agree")
        self._name = name
        self._type = type_
        self._value = value

    @property
    def name(self) -> str:
        return self._name

    @property
    def type_(self) -> Parameter.Type:
        return self._type

    @property
    def value(self) -> Any:
        return self._value

    def __repr__(self) -> str:
        return f'Parameter({self.name!r}, {self.type_.name}, {self.value!r})'


def parameter_descriptor(**fields: Any) -> Any:
    """A new ``rcl_interfaces/msg/ParameterDescriptor`` (rclpy's class of that name)."""
    return messages.get_message('rcl_interfaces/msg/ParameterDescriptor')(**fields)


def _set_parameters_result(successful: bool, reason: str = '') -> Any:
    return messages.get_message('rcl_interfaces/msg/SetParametersResult')(
        successful=successful, reason=reason)


PARAMETER_SEPARATOR = '.'
"""What separates the levels of a parameter name (rclpy's PARAMETER_SEPARATOR_STRING)."""
DEPTH_RECURSIVE = 0
"""``list_parameters`` depth that lists every level (rcl_interfaces/srv/ListParameters)."""
PARAM_REL_TOL = 1e-6
"""Relative tolerance of a floating-point range's edges and steps (rclpy's Node.PARAM_REL_TOL)."""

def _in_range(parameter: Parameter, bounds: Any, *, integer: bool) -> Any:
    """A SetParametersResult: ``parameter`` within an Integer/FloatingPointRange, on a step.

    The edges are always in; a floating-point value within :data:`PARAM_REL_TOL` of an edge or
    of a step counts as on it.
    """
    low, high = sorted((bounds.from_value, bounds.to_value))
    value = parameter.value

    def close(a: float, b: float) -> bool:
        return a == b if integer else math.isclose(a, b, rel_tol=PARAM_REL_TOL)

    if close(value, low) or close(value, high):
        return _set_parameters_result(True)
    if not low < value < high:
        dot = '.' if integer else ''
        return _set_parameters_result(
            False, f'Parameter {parameter.name} out of range{dot} Min: {low}, Max: {high}, '
                   f'value: {value}')
    if bounds.step == 0:
        return _set_parameters_result(True)
    if integer:
        on_step = (value - low) % bounds.step == 0
        text = 'is not a valid step'
    else:
        on_step = close(low + round((value - low) / bounds.step) * bounds.step, value)
        text = 'is not close enough to a valid step'
    if on_step:
        return _set_parameters_result(True)
    return _set_parameters_result(
        False, f'The parameter value for {parameter.name} {text}. Min: {low}, max: {high}, '
               f'value: {value}, step: {bounds.step}')


PreSetCallback = Callable[[list[Parameter]], list[Parameter]]
"""Gets the parameters about to be set; returns the list to set instead (all at once)."""
OnSetCallback = Callable[[list[Parameter]], Any]
"""Gets the parameters about to be set; returns a SetParametersResult (False: refuse all)."""
PostSetCallback = Callable[[list[Parameter]], None]
"""Gets the parameters that were just set."""


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
    """rclpy.timer.Timer subset; missed periods are skipped, not queued.

    It runs on the monotonic clock, or, while ``clock`` (the node's) follows ``/clock``
    (``use_sim_time``), on that time as rcl's ROS-time timers do: due when the simulated time
    reaches the next period; restarted one period after the time jumps back beyond the last
    call. A switch of ``use_sim_time`` restarts the period in the new time.
    """

    def __init__(self, period_ns: int, callback: Callable[[], None],
                 clock: Clock | None = None) -> None:
        if period_ns <= 0:
            raise ValueError(f'timer period must be positive, got {period_ns} ns')
        self.timer_period_ns = period_ns
        self.callback = callback
        self._canceled = False
        self._clock = clock
        self._ros_time = self._ros_time_active()
        self._next_ns = self._now() + period_ns

    def _ros_time_active(self) -> bool:
        return self._clock is not None and self._clock.ros_time_is_active

    def _now(self) -> int:
        return self._clock.now().nanoseconds if self._ros_time else time.monotonic_ns()

    def _on_steady_clock(self) -> bool:
        """True unless the timer follows ``/clock`` (then no steady deadline applies)."""
        return not self._ros_time

    def _follow_switch(self) -> bool:
        """Restart the period if ``use_sim_time`` switched since the last look; True if so."""
        if self._ros_time_active() == self._ros_time:
            return False
        self._ros_time = not self._ros_time
        self._next_ns = self._now() + self.timer_period_ns
        return True

    def _due(self, now: int) -> bool:
        """True if a call is due at ``now`` (monotonic ns; ignored on simulated time)."""
        if self._canceled or self._follow_switch():
            return False
        if self._ros_time:
            now = self._now()
            if now < self._next_ns - self.timer_period_ns:  # jumped back past the last call
                self._next_ns = now + self.timer_period_ns
                return False
        if now < self._next_ns:
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
        self._follow_switch()
        self._next_ns = self._now() + self.timer_period_ns

    def is_canceled(self) -> bool:
        return self._canceled

    def time_until_next_call(self) -> int | None:
        if self._canceled:
            return None
        self._follow_switch()
        return self._next_ns - self._now()

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

    Node names come from ROS 2's ``ros_discovery_info`` (:mod:`.graph`), with rmw's
    placeholders where no node claims the endpoint; ``endpoint_gid`` is the 16-byte DDS GUID,
    whose first 12 bytes name the participant (one per process).
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
                 start_parameter_services: bool = True, enable_rosout: bool = True,
                 **_ignored: Any) -> None:
        self.context = default_context if context is None else context
        if not self.context.ok() or self.context.participant is None:
            raise RuntimeError('rclpy.init() must be called before creating a Node')
        arguments = [self.context.arguments] if use_global_arguments else []
        # As rcl: only words after --ros-args are ROS arguments (others are the program's).
        arguments.append(parse_ros_arguments(cli_args))
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
        self._parameter_overrides = {
            name: Parameter(name, value=value) for name, value in
            collect_parameter_overrides(arguments, self.get_fully_qualified_name()).items()}
        self._parameter_overrides.update({p.name: p for p in parameter_overrides or ()})
        self._allow_undeclared = allow_undeclared_parameters
        self._parameters: dict[str, Parameter] = {}
        self._descriptors: dict[str, Any] = {}
        self._pre_set_parameters_callbacks: list[PreSetCallback] = []
        self._on_set_parameters_callbacks: list[OnSetCallback] = []
        self._post_set_parameters_callbacks: list[PostSetCallback] = []
        if automatically_declare_parameters_from_overrides:  # as rclpy: static, typed by value
            self.declare_parameters('', [(name, parameter.value, parameter_descriptor())
                                         for name, parameter in self._parameter_overrides.items()],
                                    ignore_override=True)
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
        self._service_endpoints: list[services.Service | services.Client] = []
        self._services_polled_ns = 0
        self.context.add_node(self)
        self._graph_node = self.context.graph.add_node(name=self._name,
                                                       namespace=self._namespace)
        self._rosout: RosoutWriter | None = None
        if enable_rosout and self.context.arguments.rosout_logs:  # as rcl: global args only
            self._rosout = RosoutWriter(self.context.participant,
                                        self._dds_topic(ROSOUT_TOPIC, LOG_TYPE))
            self.context.graph.add_endpoint(self._graph_node, gid_of(self._rosout.writer),
                                            is_reader=False)
            self._logger._rosout = self._rosout
        try:
            self._time_source = TimeSource(node=self)
        except Exception:  # e.g. a use_sim_time override that is not a bool: no node is left
            self.destroy_node()
            raise
        if start_parameter_services:  # as rclpy: ros2 param reaches every node
            from rcbf_ros.ros.dds.parameter_service import ParameterService
            self._parameter_service = ParameterService(self)

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
        self.context.graph.add_endpoint(self._graph_node, gid_of(publisher._writer),
                                        is_reader=False)
        return publisher

    def create_subscription(self, msg_type: Any, topic: str, callback: Callable[[Any], None],
                            qos_profile: QoSProfile | int, *, raw: bool = False,
                            **_ignored: Any) -> Subscription:
        subscription = Subscription(self, msg_type, self.resolve_topic_name(topic), callback,
                                    as_profile(qos_profile), raw)
        self._waitset.attach(subscription._condition)
        self._subscriptions.append(subscription)
        self.context.graph.add_endpoint(self._graph_node, gid_of(subscription._reader),
                                        is_reader=True)
        return subscription

    def create_timer(self, timer_period_sec: float, callback: Callable[[], None],
                     **_ignored: Any) -> Timer:
        timer = Timer(int(round(timer_period_sec * 1e9)), callback, self._clock)
        self._timers.append(timer)
        self._wake()
        return timer

    def destroy_publisher(self, publisher: Publisher) -> bool:
        if publisher not in self._publishers:
            return False
        self._publishers.remove(publisher)
        self.context.graph.remove_endpoint(self._graph_node, gid_of(publisher._writer),
                                           is_reader=False)
        publisher.destroy()
        return True

    def destroy_subscription(self, subscription: Subscription) -> bool:
        if subscription not in self._subscriptions:
            return False
        self._subscriptions.remove(subscription)
        self._waitset.detach(subscription._condition)
        self.context.graph.remove_endpoint(self._graph_node, gid_of(subscription._reader),
                                           is_reader=True)
        subscription.destroy()
        return True

    def destroy_timer(self, timer: Timer) -> bool:
        if timer not in self._timers:
            return False
        self._timers.remove(timer)
        timer.destroy()
        return True

    def create_service(self, srv_type: Any, srv_name: str,
                       callback: Callable[[Any, Any], Any], *,
                       qos_profile: QoSProfile = services.qos_profile_services_default,
                       **_ignored: Any) -> services.Service:
        """Serve ``srv_name``: ``callback(request, response)`` returns the response."""
        return self._add_service_endpoint(services.Service(
            self, srv_type, self.resolve_topic_name(srv_name), callback,
            as_profile(qos_profile)))

    def create_client(self, srv_type: Any, srv_name: str, *,
                      qos_profile: QoSProfile = services.qos_profile_services_default,
                      **_ignored: Any) -> services.Client:
        return self._add_service_endpoint(services.Client(
            self, srv_type, self.resolve_topic_name(srv_name), as_profile(qos_profile)))

    def _add_service_endpoint(self, endpoint: Any) -> Any:
        self._waitset.attach(endpoint._condition)
        self._service_endpoints.append(endpoint)
        # As rmw_cyclonedds: a service's (or client's) reader and writer are the node's
        # endpoints in ros_discovery_info, so ros2 node info lists them.
        self.context.graph.add_endpoint(self._graph_node, gid_of(endpoint._reader),
                                        is_reader=True)
        self.context.graph.add_endpoint(self._graph_node, gid_of(endpoint._writer),
                                        is_reader=False)
        return endpoint

    def destroy_service(self, service: services.Service) -> bool:
        return self._destroy_service_endpoint(service)

    def destroy_client(self, client: services.Client) -> bool:
        return self._destroy_service_endpoint(client)

    def _destroy_service_endpoint(self, endpoint: Any) -> bool:
        if endpoint not in self._service_endpoints:
            return False
        self._service_endpoints.remove(endpoint)
        self._waitset.detach(endpoint._condition)
        self.context.graph.remove_endpoint(self._graph_node, gid_of(endpoint._reader),
                                           is_reader=True)
        self.context.graph.remove_endpoint(self._graph_node, gid_of(endpoint._writer),
                                           is_reader=False)
        endpoint.destroy()
        return True

    def _wake(self) -> None:
        if self._guard is not None:
            self._guard.set(True)

    # parameters -----------------------------------------------------------------------------
    # The rules are rclpy's (node.py: declare_parameters, _apply_descriptor, get_parameter,
    # _set_parameters_atomically_common): a parameter declared with a value is statically typed
    # by that value unless its descriptor says dynamic_typing; Parameter.Type declares the type
    # without a value (then get_parameter raises until one is set); overrides must have the
    # declared type; a NOT_SET value cannot be a static default. The descriptor passed in is
    # kept and modified (its name and type), as rclpy does.
    #
    # Setting goes through three lists of callbacks, each newest first: pre-set (set_parameters*
    # only: each returns a list, their concatenation is set instead), on-set (declarations too:
    # the first that refuses stops the set, and its reason is the result) and post-set (after
    # the values are stored). set_parameters runs that once per parameter, in order;
    # set_parameters_atomically once for the whole list, all or nothing; a declaration once per
    # declared parameter (an on-set refusal raises there).
    def declare_parameter(self, name: str, value: Any = None, descriptor: Any = None,
                          ignore_override: bool = False) -> Parameter:
        """Declare ``name`` with default ``value`` (or a ``Parameter.Type``); an override wins.

        Raises:
            ParameterAlreadyDeclaredException: ``name`` was declared before.
            InvalidParameterTypeException: the override's type is not the declared type.
            ValueError: a static declaration without a type (default None or NOT_SET).
        """
        if value is None and descriptor is None:
            item: tuple = (name,)
        else:
            item = (name, value, parameter_descriptor() if descriptor is None else descriptor)
        return self.declare_parameters('', [item], ignore_override)[0]

    def declare_parameters(self, namespace: str, parameters: Iterable[tuple],
                           ignore_override: bool = False) -> list[Parameter]:
        """Declare ``(name,)``, ``(name, Parameter.Type)`` or ``(name, value, descriptor)``
        items, each as :meth:`declare_parameter`; nothing is declared if one was before."""
        descriptor_type = type(parameter_descriptor())
        declared: list[Parameter] = []
        descriptors: dict[str, Any] = {}
        for index, item in enumerate(parameters):
            if not 1 <= len(item) <= 3:
                raise TypeError(f'Invalid parameter tuple length at index {index} in parameters '
                                f'list: {item}; expecting length between 1 and 3')
            name = item[0]
            if not isinstance(name, str):
                raise TypeError(f'First element {name} at index {index} in parameters list is '
                                'not a str.')
            if namespace:
                name = f'{namespace}.{name}'
            second = item[1] if len(item) > 1 else None
            descriptor = item[2] if len(item) > 2 else parameter_descriptor()
            if not isinstance(descriptor, descriptor_type):
                raise TypeError(f'Third element {descriptor} at index {index} in parameters '
                                'list is not a ParameterDescriptor.')
            if len(item) == 1:
                warnings.warn(f"when declaring parameter named '{name}', declaring a parameter "
                              'only providing its name is deprecated', stacklevel=3)
                descriptor.dynamic_typing = True
            value = None
            if isinstance(second, Parameter.Type):
                if second is Parameter.Type.NOT_SET:
                    raise ValueError(f'Cannot declare parameter {{{name}}} as statically typed '
                                     'of type NOT_SET')
                if descriptor.dynamic_typing:
                    raise ValueError(f'When declaring parameter {{{name}}} passing a descriptor '
                                     'with `dynamic_typing=True` is not allowed when the '
                                     'parameter type is provided')
                descriptor.type = second.value
            else:
                value = second
                if not descriptor.dynamic_typing:
                    descriptor.type = Parameter.Type.from_parameter_value(value).value
                    if descriptor.type == Parameter.Type.NOT_SET.value:
                        raise ValueError('Cannot declare a statically typed parameter with '
                                         f'default value of type PARAMETER_NOT_SET ({name!r})')
            if not ignore_override and name in self._parameter_overrides:
                value = self._parameter_overrides[name].value
            declared.append(Parameter(name, value=value))
            descriptors[name] = descriptor
        already = [p.name for p in declared if p.name in self._parameters]
        if already:
            raise ParameterAlreadyDeclaredException(already)
        for parameter in declared:  # one at a time: those before a refusal stay declared
            result = self._set_parameters_common([parameter], descriptors, declaring=True)
            if not result.successful:
                if result.reason.startswith('Wrong parameter type'):
                    raise InvalidParameterTypeException(
                        parameter, Parameter.Type(descriptors[parameter.name].type).name)
                raise InvalidParameterValueException(parameter.name, parameter.value,
                                                     result.reason)
        return [self._parameters[p.name] for p in declared]

    def undeclare_parameter(self, name: str) -> None:
        """Forget a declared parameter (no callback is called).

        Raises:
            ParameterNotDeclaredException: ``name`` is not declared.
            ParameterImmutableException: it was declared read-only.
        """
        if name not in self._parameters:
            raise ParameterNotDeclaredException(name)
        if self._descriptors[name].read_only:
            raise ParameterImmutableException(name)
        del self._parameters[name]
        del self._descriptors[name]

    def _apply_descriptor(self, parameter: Parameter, descriptor: Any,
                          check_read_only: bool = True) -> Any:
        """Check ``parameter`` against ``descriptor`` (which takes its name, and its type when
        dynamically typed): read-only, type, integer and floating-point ranges; a
        SetParametersResult."""
        descriptor.name = parameter.name
        if check_read_only and descriptor.read_only:
            return _set_parameters_result(
                False, f'Trying to set a read-only parameter: {parameter.name}.')
        if descriptor.dynamic_typing:
            descriptor.type = parameter.type_.value
        elif self.has_parameter(parameter.name) and parameter.type_ is Parameter.Type.NOT_SET:
            return _set_parameters_result(False, 'Static parameter cannot be undeclared')
        elif (parameter.type_ is not Parameter.Type.NOT_SET
              and parameter.type_.value != descriptor.type):
            return _set_parameters_result(
                False, f"Wrong parameter type, expected '{Parameter.Type(descriptor.type)}' got "
                       f"'{parameter.type_}'")
        if parameter.type_ is Parameter.Type.INTEGER and len(descriptor.integer_range):
            return _in_range(parameter, descriptor.integer_range[0], integer=True)
        if parameter.type_ is Parameter.Type.DOUBLE and len(descriptor.floating_point_range):
            return _in_range(parameter, descriptor.floating_point_range[0], integer=False)
        return _set_parameters_result(True)

    def has_parameter(self, name: str) -> bool:
        return name in self._parameters

    def get_parameter(self, name: str) -> Parameter:
        """The declared parameter ``name``.

        Raises:
            ParameterNotDeclaredException: never declared (and undeclared ones not allowed).
            ParameterUninitializedException: statically typed and without a value.
        """
        if name in self._parameters:
            parameter = self._parameters[name]
            if (parameter.type_ is not Parameter.Type.NOT_SET
                    or self._descriptors[name].dynamic_typing):
                return parameter
            raise ParameterUninitializedException(name)
        if self._allow_undeclared:
            return Parameter(name, Parameter.Type.NOT_SET, None)
        raise ParameterNotDeclaredException(name)

    def get_parameter_or(self, name: str, alternative_value: Parameter | None = None
                         ) -> Parameter:
        """The parameter, or ``alternative_value`` if undeclared or without a value."""
        if alternative_value is None:
            alternative_value = Parameter(name, Parameter.Type.NOT_SET)
        if name not in self._parameters:
            return alternative_value
        if self._parameters[name].type_ is Parameter.Type.NOT_SET:
            return alternative_value
        return self._parameters[name]

    def get_parameters(self, names: Iterable[str]) -> list[Parameter]:
        return [self.get_parameter(name) for name in names]

    def get_parameters_by_prefix(self, prefix: str) -> dict[str, Parameter]:
        dotted = prefix + '.' if prefix else ''
        return {name[len(dotted):]: p for name, p in self._parameters.items()
                if name.startswith(dotted)}

    def describe_parameter(self, name: str) -> Any:
        """The descriptor kept for ``name`` (the object that was declared with)."""
        if name in self._descriptors:
            return self._descriptors[name]
        if self._allow_undeclared:
            return parameter_descriptor()
        raise ParameterNotDeclaredException(name)

    def describe_parameters(self, names: Iterable[str]) -> list[Any]:
        return [self.describe_parameter(name) for name in names]

    def set_parameters(self, parameter_list: Sequence[Parameter]) -> list[Any]:
        """Set each parameter in turn, each through the callbacks on its own; a
        SetParametersResult each. A NOT_SET value undeclares a dynamically typed parameter.

        Raises:
            ParameterNotDeclaredException: one was never declared (undeclared not allowed);
                the ones before it stay set, the ones after are not tried.
        """
        return [self._set_parameters_atomically([parameter]) for parameter in parameter_list]

    def set_parameters_atomically(self, parameter_list: Sequence[Parameter]) -> Any:
        """Set every parameter or none: the callbacks see the whole list once; one
        SetParametersResult.

        Raises:
            ParameterNotDeclaredException: one was never declared (nothing is set).
        """
        return self._set_parameters_atomically(list(parameter_list))

    def _set_parameters_atomically(self, parameter_list: list[Parameter]) -> Any:
        if self._pre_set_parameters_callbacks:
            modified: list[Parameter] = []
            for callback in list(self._pre_set_parameters_callbacks):
                modified.extend(callback(parameter_list))
            parameter_list = modified
            if not parameter_list:
                return _set_parameters_result(
                    False, 'parameter list cannot be empty, this might be due to '
                           'pre_set_parameters_callback modifying the original parameters list.')
        if not all(isinstance(parameter, Parameter) for parameter in parameter_list):
            raise TypeError(f"parameter must be instance of type '{Parameter!r}'")
        undeclared = [p.name for p in parameter_list if p.name not in self._parameters]
        if undeclared and not self._allow_undeclared:
            raise ParameterNotDeclaredException(undeclared)
        return self._set_parameters_common(parameter_list)

    def _set_parameters_common(self, parameter_list: list[Parameter],
                               descriptors: dict[str, Any] | None = None,
                               declaring: bool = False) -> Any:
        """Descriptor checks, on-set callbacks, store, post-set callbacks: all or nothing.

        Args:
            descriptors: new descriptors of a declaration (read-only is not checked then);
                None: the stored ones.
            declaring: a NOT_SET value is stored (a declaration without a value) instead of
                undeclaring the parameter.
        """
        checking = self._descriptors if descriptors is None else descriptors
        for parameter in parameter_list:
            if parameter.name in checking:
                result = self._apply_descriptor(parameter, checking[parameter.name],
                                                check_read_only=descriptors is None)
                if not result.successful:
                    return result
        for callback in list(self._on_set_parameters_callbacks):
            result = callback(parameter_list)
            if not result.successful:
                return result
        for parameter in parameter_list:
            if not declaring and parameter.type_ is Parameter.Type.NOT_SET:
                self._parameters.pop(parameter.name, None)
                self._descriptors.pop(parameter.name, None)
                continue
            if descriptors is not None:
                self._descriptors[parameter.name] = descriptors[parameter.name]
            elif parameter.name not in self._descriptors:
                self._descriptors[parameter.name] = parameter_descriptor(dynamic_typing=True)
            self._parameters[parameter.name] = parameter
        for callback in list(self._post_set_parameters_callbacks):
            callback(parameter_list)
        return _set_parameters_result(True)

    def add_pre_set_parameters_callback(self, callback: PreSetCallback) -> None:
        """Call ``callback`` first (before the older ones) on every set_parameters* (not on
        declarations); the parameters it returns are set instead, all at once."""
        self._pre_set_parameters_callbacks.insert(0, callback)

    def add_on_set_parameters_callback(self, callback: OnSetCallback) -> None:
        """Call ``callback`` first (before the older ones) before any parameters are set or
        declared; a result with ``successful=False`` refuses them with its ``reason``."""
        self._on_set_parameters_callbacks.insert(0, callback)

    def add_post_set_parameters_callback(self, callback: PostSetCallback) -> None:
        """Call ``callback`` first (before the older ones) after parameters were set or
        declared."""
        self._post_set_parameters_callbacks.insert(0, callback)

    def remove_pre_set_parameters_callback(self, callback: PreSetCallback) -> None:
        """Raises: ValueError: ``callback`` was not added."""
        self._pre_set_parameters_callbacks.remove(callback)

    def remove_on_set_parameters_callback(self, callback: OnSetCallback) -> None:
        """Raises: ValueError: ``callback`` was not added."""
        self._on_set_parameters_callbacks.remove(callback)

    def remove_post_set_parameters_callback(self, callback: PostSetCallback) -> None:
        """Raises: ValueError: ``callback`` was not added."""
        self._post_set_parameters_callbacks.remove(callback)

    def list_parameters(self, prefixes: list[str], depth: int) -> Any:
        """The declared names under ``prefixes`` (none: all) at most ``depth`` levels below
        them (:data:`DEPTH_RECURSIVE`: any), in declaration order, and the prefixes of those
        names; an ``rcl_interfaces/msg/ListParametersResult``.

        Raises:
            TypeError: ``prefixes`` is not a list of str, or ``depth`` not an int.
            ValueError: ``depth`` < 0.
        """
        if not isinstance(prefixes, list):
            raise TypeError('The prefixes argument must be a list')
        if not all(isinstance(prefix, str) for prefix in prefixes):
            raise TypeError('All prefixes must be instances of type str')
        if not isinstance(depth, int):
            raise TypeError('The depth must be instance of type int')
        if depth < 0:
            raise ValueError('The depth must be greater than or equal to zero')

        def shallow(name: str) -> bool:
            return name.count(PARAMETER_SEPARATOR) < depth

        def under(name: str, prefix: str) -> bool:
            rest = name[len(prefix) + 1:]
            return name == prefix or (name.startswith(prefix + PARAMETER_SEPARATOR) and (
                depth == DEPTH_RECURSIVE or shallow(rest)))

        everything = not prefixes and depth == DEPTH_RECURSIVE
        names: list[str] = []
        found_prefixes: list[str] = []
        for name in self._parameters:
            if not everything and not (not prefixes and shallow(name)) and not any(
                    under(name, prefix) for prefix in prefixes):
                continue
            names.append(name)
            prefix = name.rpartition(PARAMETER_SEPARATOR)[0]
            if prefix and prefix not in found_prefixes:
                found_prefixes.append(prefix)
        return messages.get_message('rcl_interfaces/msg/ListParametersResult')(
            names=names, prefixes=found_prefixes)

    def get_parameter_type(self, name: str) -> Any:
        """The type of ``name`` as rclpy gives it: the ParameterType value (an int) of a
        declared parameter, ``Parameter.Type.NOT_SET`` of an undeclared one if allowed.

        Raises:
            ParameterNotDeclaredException: never declared (and undeclared ones not allowed).
        """
        if name in self._parameters:
            return self._parameters[name].type_.value
        if self._allow_undeclared:
            return Parameter.Type.NOT_SET
        raise ParameterNotDeclaredException(name)

    def get_parameter_types(self, names: Iterable[str]) -> list[Any]:
        names = list(names)
        if not all(isinstance(name, str) for name in names):
            raise TypeError('All names must be instances of type str')
        return [self.get_parameter_type(name) for name in names]

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
            read = self.context.read_builtin
            changed = read(reader, unread_condition, 64)  # any will do
            if changed or kind not in self._endpoint_cache:
                self._endpoint_cache[kind] = read(reader, alive_condition, 100000)
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
        is_reader = kind == TopicEndpointTypeEnum.SUBSCRIPTION
        builtin = BuiltinTopicDcpsSubscription if is_reader else BuiltinTopicDcpsPublication
        endpoints = [e for e in self._alive_endpoints((builtin,)) if e.topic_name == dds_name]
        participants = self.context.graph.participants() if endpoints else {}
        infos = []
        for e in endpoints:
            name, namespace = node_of_endpoint(
                participants=participants, participant_gid=e.participant_key.bytes,
                endpoint_gid=e.key.bytes, is_reader=is_reader)
            infos.append(TopicEndpointInfo(
                node_name=name, node_namespace=namespace,
                topic_type=messages.ros_type_name(e.type_name), endpoint_type=kind,
                endpoint_gid=list(e.key.bytes), qos_profile=from_cyclone_qos(e.qos)))
        return infos

    def get_node_names(self) -> list[str]:
        """Names of every node in the ROS graph (``ros_discovery_info``), this one included."""
        return [name for name, _ in self.get_node_names_and_namespaces()]

    def get_node_names_and_namespaces(self) -> list[tuple[str, str]]:
        """``[(name, namespace), ...]`` of every node in the ROS graph, as rclpy's."""
        return self.context.graph.node_names_and_namespaces()

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
        self.context.graph.remove_node(self._graph_node)  # its endpoints leave with it
        if self._rosout is not None:
            self._rosout.close()
        for timer in self._timers:
            timer.destroy()
        for subscription in self._subscriptions:
            self._waitset.detach(subscription._condition)
            subscription.destroy()
        for publisher in self._publishers:
            publisher.destroy()
        for endpoint in self._service_endpoints:
            self._waitset.detach(endpoint._condition)
            endpoint.destroy()
        self._service_endpoints = []
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

