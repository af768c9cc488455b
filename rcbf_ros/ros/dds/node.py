"""rclpy-compatible ``Node`` over Cyclone DDS: names, endpoints, parameters, graph queries.

ROS 2 wire conventions (so stock Jazzy nodes interoperate): topic ``/a/b`` is the DDS topic
``rt/a/b`` of type ``pkg::msg::dds_::Type_`` (XCDR1, ``@final``); every endpoint carries USER_DATA
``typehash=RIHS01_<hex>;``; QoS as rmw_cyclonedds maps it (see :mod:`.qos`). The endpoints are
:mod:`.endpoints`, the parameter methods :mod:`.node_parameters`, the graph queries
:mod:`.node_graph`.
"""
from __future__ import annotations

import numbers
import threading
from typing import Any, Callable, Iterable, Sequence

from cyclonedds.topic import Topic

from rcbf_ros.parameters.arguments import (
    check_namespace,
    check_node_name,
    parse_ros_arguments,
    resolve_topic_name,
)
from rcbf_ros.parameters.arguments import (
    parameter_overrides as collect_parameter_overrides,
)
from rcbf_ros.ros.dds import messages, services
from rcbf_ros.ros.dds.clock import Clock, ClockType
from rcbf_ros.ros.dds.context import (
    Context,
    default_context,
    delete_entity,
    new_ready_queue,
    NodeWaitSet,
)
from rcbf_ros.ros.dds.endpoints import GuardCondition, Publisher, Subscription, Timer
from rcbf_ros.ros.dds.graph import gid_of
from rcbf_ros.ros.dds.log import LEVEL_NAMES, Logger
from rcbf_ros.ros.dds.node_graph import NodeGraph
from rcbf_ros.ros.dds.node_parameters import NodeParameters
from rcbf_ros.ros.dds.parameter_service import qos_profile_parameter_events
from rcbf_ros.ros.dds.parameters import (
    DEPTH_RECURSIVE,
    InvalidParameterTypeException,
    Parameter,
    parameter_descriptor,
    ParameterException,
    ParameterNotDeclaredException,
    ParameterUninitializedException,
)
from rcbf_ros.ros.dds.qos import as_profile, QoSProfile
from rcbf_ros.ros.dds.rosout import LOG_TYPE, ROSOUT_TOPIC, RosoutWriter
from rcbf_ros.ros.dds.time_source import TimeSource

__all__ = [
    'DEPTH_RECURSIVE', 'InvalidParameterTypeException', 'Node', 'Parameter',
    'ParameterException', 'ParameterNotDeclaredException', 'ParameterUninitializedException',
    'parameter_descriptor',
]
"""Node, and the parameter names that callers take from this module (defined in
:mod:`.parameters`)."""

INT64_MAX = 2 ** 63 - 1
"""The longest timer period in nanoseconds (rcl's int64)."""
_LONGEST_PERIOD_S = f'{INT64_MAX // 10 ** 9}.{INT64_MAX % 10 ** 9:09d}'


def timer_period_ns(timer_period_sec: Any) -> int:
    """``timer_period_sec`` in whole nanoseconds, as rclpy's ``create_timer`` converts it.

    rclpy refuses a negative period (rcl's "timer period must be non-negative") and raises a
    bare OverflowError, ValueError or TypeError for an infinite, NaN or too long one; here
    each is one ValueError naming the period, and a period under a nanosecond is refused
    too: a timer always due would keep the executor busy.

    Raises:
        ValueError: one line naming ``timer_period_sec``.
    """
    if isinstance(timer_period_sec, bool) or not isinstance(timer_period_sec, numbers.Real):
        raise ValueError(f'timer_period_sec: expected a number of seconds, got '
                         f'{type(timer_period_sec).__name__}')
    seconds = float(timer_period_sec)
    period_ns = round(seconds * 1e9) if 0.0 < seconds * 1e9 < INT64_MAX else 0  # NaN, inf: 0
    if not 0 < period_ns <= INT64_MAX:
        raise ValueError(f'timer_period_sec: must be in [1e-09, {_LONGEST_PERIOD_S}] s (a '
                         f'positive int64 of nanoseconds), got {seconds!r}')
    return period_ns


class Node(NodeParameters, NodeGraph):
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
        if log_level not in LEVEL_NAMES:
            raise ValueError(f'--log-level {log_level!r} is not debug|info|warn|error|fatal')
        self._logger = Logger(self.get_fully_qualified_name().lstrip('/').replace('/', '.'),
                              LEVEL_NAMES[log_level])
        overrides = {
            name: Parameter(name, value=value) for name, value in
            collect_parameter_overrides(arguments, self.get_fully_qualified_name()).items()}
        overrides.update({p.name: p for p in parameter_overrides or ()})
        self._init_parameters(overrides=overrides, allow_undeclared=allow_undeclared_parameters)
        if automatically_declare_parameters_from_overrides:  # as rclpy: static, typed by value
            self.declare_parameters('', [(name, parameter.value, parameter_descriptor())
                                         for name, parameter in self._parameter_overrides.items()],
                                    ignore_override=True)
        self._clock = Clock(clock_type=ClockType.ROS_TIME)
        self._topics: dict[tuple[str, str], Topic] = {}
        self._publishers: list[Publisher] = []
        self._subscriptions: list[Subscription] = []
        self._event_endpoints: dict[int, Publisher | Subscription] = {}
        """Endpoint by the handle of its reader or writer, which the wait set waits on for
        incompatible QoS (:class:`rcbf_ros.ros.dds.endpoints.WarnsIncompatibleQos`)."""
        self._timers: list[Timer] = []
        self._guard_conditions: list[GuardCondition] = []
        self._ready = new_ready_queue()
        self._spin_lock = threading.Lock()
        self._waitset: NodeWaitSet | None = NodeWaitSet(self.context.participant)
        self._guard = self._waitset.guard
        if self.context.graph.condition is not None:  # drained as it fills (graph.py)
            self._waitset.attach(self.context.graph.condition)
        self._init_graph_queries()
        self._service_endpoints: list[services.Service | services.Client] = []
        self._graph_node: Any = None  # set before the context holds the node: a signal
        self._rosout: RosoutWriter | None = None  # from here on leaves it destroyable
        self.context.add_node(self)
        self._graph_node = self.context.graph.add_node(name=self._name,
                                                       namespace=self._namespace)
        self._parameter_event_publisher = self.create_publisher(
            messages.get_message('rcl_interfaces/msg/ParameterEvent'), '/parameter_events',
            qos_profile_parameter_events)
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
        return self._adopt(Publisher(self, msg_type, self.resolve_topic_name(topic),
                                     as_profile(qos_profile), topic_as_given=topic),
                           self._publishers)

    def create_subscription(self, msg_type: Any, topic: str, callback: Callable[[Any], None],
                            qos_profile: QoSProfile | int, *, raw: bool = False,
                            **_ignored: Any) -> Subscription:
        return self._adopt(Subscription(self, msg_type, self.resolve_topic_name(topic),
                                        callback, as_profile(qos_profile), raw,
                                        topic_as_given=topic),
                           self._subscriptions)

    def create_timer(self, timer_period_sec: float, callback: Callable[[], None],
                     callback_group: Any = None, clock: Clock | None = None,
                     **_ignored: Any) -> Timer:
        """A timer calling ``callback`` every ``timer_period_sec`` seconds of ``clock`` (None:
        the node's, which follows ``/clock`` while ``use_sim_time`` is true; a ``STEADY_TIME``
        clock: the monotonic clock, whatever ``/clock`` does), as rclpy's.

        Raises:
            ValueError: one line naming ``timer_period_sec``: not a number, or one whose
                nanoseconds are not a positive int64 (:func:`timer_period_ns`).
        """
        timer = Timer(timer_period_ns(timer_period_sec), callback,
                      self._clock if clock is None else clock)
        self._timers.append(timer)
        self._wake()
        return timer

    def create_guard_condition(self, callback: Callable[[], None], callback_group: Any = None
                               ) -> GuardCondition:
        """A guard condition whose :meth:`~GuardCondition.trigger` (from any thread) has the
        executor call ``callback`` (rclpy's ``Node.create_guard_condition``)."""
        guard = GuardCondition(callback, self._wake)
        self._guard_conditions.append(guard)
        return guard

    def create_service(self, srv_type: Any, srv_name: str,
                       callback: Callable[[Any, Any], Any], *,
                       qos_profile: QoSProfile = services.qos_profile_services_default,
                       **_ignored: Any) -> services.Service:
        """Serve ``srv_name``: ``callback(request, response)`` returns the response."""
        return self._adopt(services.Service(self, srv_type, self.resolve_topic_name(srv_name),
                                            callback, as_profile(qos_profile)),
                           self._service_endpoints)

    def create_client(self, srv_type: Any, srv_name: str, *,
                      qos_profile: QoSProfile = services.qos_profile_services_default,
                      **_ignored: Any) -> services.Client:
        return self._adopt(services.Client(self, srv_type, self.resolve_topic_name(srv_name),
                                           as_profile(qos_profile)), self._service_endpoints)

    def destroy_publisher(self, publisher: Publisher) -> bool:
        return self._release(publisher, self._publishers)

    def destroy_subscription(self, subscription: Subscription) -> bool:
        return self._release(subscription, self._subscriptions)

    def destroy_client(self, client: services.Client) -> bool:
        return self._release(client, self._service_endpoints)

    def destroy_timer(self, timer: Timer) -> bool:
        """Stop and forget ``timer``; False if it is not this node's (rclpy's
        ``Node.destroy_timer``)."""
        if timer not in self._timers:
            return False
        self._timers.remove(timer)
        timer.destroy()
        return True

    def destroy_guard_condition(self, guard: GuardCondition) -> bool:
        """Forget ``guard`` (its triggers wake nothing any more); False if it is not this
        node's."""
        if guard not in self._guard_conditions:
            return False
        self._guard_conditions.remove(guard)
        guard.destroy()
        return True

    def _adopt(self, endpoint: Any, endpoints: list[Any]) -> Any:
        """Keep ``endpoint`` in ``endpoints``, wake the executor on its samples and on its
        incompatible-QoS status, and list its DDS reader and writer as this node's in
        ros_discovery_info (as rmw_cyclonedds does, a service's and a client's too, so ros2 node
        info lists them)."""
        for condition in _conditions_of(endpoint):
            self._waitset.attach(condition)
        events = getattr(endpoint, '_event_entity', None)
        if events is not None:
            self._event_endpoints[events._ref] = endpoint
        endpoints.append(endpoint)
        for entity, is_reader in _dds_entities(endpoint):
            self.context.graph.add_endpoint(self._graph_node, gid_of(entity),
                                            is_reader=is_reader)
        return endpoint

    def _release(self, endpoint: Any, endpoints: list[Any]) -> bool:
        """Undo :meth:`_adopt` and destroy ``endpoint``; False if it is not in ``endpoints``."""
        if endpoint not in endpoints:
            return False
        endpoints.remove(endpoint)
        self._detach(endpoint)
        for entity, is_reader in _dds_entities(endpoint):
            self.context.graph.remove_endpoint(self._graph_node, gid_of(entity),
                                               is_reader=is_reader)
        endpoint.destroy()
        return True

    def _detach(self, endpoint: Any) -> None:
        """Stop waiting on ``endpoint`` (before it is destroyed)."""
        for condition in _conditions_of(endpoint):
            self._waitset.detach(condition)
        events = getattr(endpoint, '_event_entity', None)
        if events is not None:
            self._event_endpoints.pop(events._ref, None)

    def _wake(self) -> None:
        guard = self._guard  # None once destroyed (from another thread: read once)
        if guard is not None:
            guard.set(True)

    # teardown -------------------------------------------------------------------------------
    def destroy_node(self) -> None:
        """Delete every DDS entity of this node (idempotent)."""
        if self._waitset is None:
            return
        if self._graph_node is not None:
            self.context.graph.remove_node(self._graph_node)  # its endpoints leave with it
        if self._rosout is not None:
            self._rosout.close()
        for timer in self._timers:
            timer.destroy()
        for guard in self._guard_conditions:
            guard.destroy()
        self._guard_conditions = []
        for endpoint in (*self._subscriptions, *self._publishers, *self._service_endpoints):
            self._detach(endpoint)
            endpoint.destroy()
        self._service_endpoints = []
        self._close_graph_queries()
        self._timers, self._subscriptions, self._publishers = [], [], []
        self._ready.clear()
        waitset, self._waitset, self._guard = self._waitset, None, None
        waitset.close()
        for topic in self._topics.values():
            delete_entity(topic)
        self._topics.clear()
        self.context.remove_node(self)


def _conditions_of(endpoint: Any) -> list[Any]:
    """What the node's wait set waits on for ``endpoint``: the read condition of its samples
    (none for a publisher), then its reader or writer itself for incompatible QoS (none for a
    service or client)."""
    return [condition for condition in (getattr(endpoint, '_condition', None),
                                        getattr(endpoint, '_event_entity', None))
            if condition is not None]


def _dds_entities(endpoint: Any) -> list[tuple[Any, bool]]:
    """``(entity, is_reader)`` of the DDS reader and writer ``endpoint`` has, reader first."""
    return [(entity, is_reader) for entity, is_reader in (
        (getattr(endpoint, '_reader', None), True), (getattr(endpoint, '_writer', None), False))
        if entity is not None]
