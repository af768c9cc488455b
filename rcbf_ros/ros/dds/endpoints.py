"""rclpy's endpoints over the Cyclone runtime: ``Publisher``, ``Subscription``, ``Timer``,
``GuardCondition``, and ``TopicEndpointInfo`` (an endpoint as graph queries report it).

A node creates them (:mod:`.node`); its executor (:mod:`.context`) takes their samples, fires
their timers and, as rclpy's default QoS event callbacks do, warns once for each remote endpoint
whose QoS keeps it from matching one of them (:class:`WarnsIncompatibleQos`). Wire conventions:
a publisher or subscription of ``/a/b`` is a writer or reader of the DDS topic ``rt/a/b`` whose
USER_DATA is ``typehash=RIHS01_<hex>;``; QoS as rmw_cyclonedds maps it (:mod:`.qos`).
"""
from __future__ import annotations

from dataclasses import dataclass
import enum
import threading
import time
from typing import Any, Callable, TYPE_CHECKING

from cyclonedds._clayer import ddspy_take, ddspy_write
from cyclonedds.core import DDSStatus, InstanceState, ReadCondition, SampleState, ViewState
from cyclonedds.pub import DataWriter
from cyclonedds.sub import DataReader

from rcbf_ros.ros.dds import messages
from rcbf_ros.ros.dds.clock import Clock
from rcbf_ros.ros.dds.context import delete_entity
from rcbf_ros.ros.dds.qos import QoSProfile, to_cyclone_qos, type_user_data

if TYPE_CHECKING:
    from rcbf_ros.ros.dds.log import Logger
    from rcbf_ros.ros.dds.node import Node

_ANY_SAMPLE = SampleState.Any | ViewState.Any | InstanceState.Any
_TAKE_BATCH = 256
UNDECODABLE_WARNING_PERIOD_S = 1.0
"""Shortest interval between two warnings about undecodable samples on one endpoint."""


def take_valid(reader: DataReader, *, batch: int, name: str) -> list[tuple[bytes, Any]]:
    """Every valid sample ``reader`` holds (taken ``batch`` at a time), with its sample info.

    Raises:
        RuntimeError: DDS refused the take (the message names ``name``).
    """
    taken: list[tuple[bytes, Any]] = []
    while True:
        samples = ddspy_take(reader._ref, _ANY_SAMPLE, batch)
        if isinstance(samples, int):
            raise RuntimeError(f'DDS take on {name} failed with code {samples}')
        taken.extend((data, info) for data, info in samples if info.valid_data)
        if len(samples) < batch:
            return taken


def write_payload(writer: DataWriter, payload: bytes, *, name: str) -> None:
    """Write one DDS payload (encapsulation header and CDR) with ``writer``.

    Raises:
        RuntimeError: DDS refused the write (the message names ``name``).
    """
    ret = ddspy_write(writer._ref, payload)
    if isinstance(ret, int) and ret < 0:
        raise RuntimeError(f'DDS write on {name} failed with code {ret}')


class DropsUndecodable:
    """Base of an endpoint that drops the samples that do not decode: it counts them in
    ``undecodable_count`` and reports them by a one-line warning naming the endpoint, at most
    once per :data:`UNDECODABLE_WARNING_PERIOD_S`."""

    def _init_undecodable(self, *, logger: Logger, name: str) -> None:
        self.undecodable_count = 0
        """Samples dropped because they did not decode (since creation)."""
        self._undecodable_logger = logger
        self._undecodable_name = name
        self._last_warning_ns: int | None = None
        self._unreported = 0

    def _drop_undecodable(self, exc: Exception) -> None:
        """Count one undecodable sample and say so, throttled."""
        self.undecodable_count += 1
        self._unreported += 1
        now = time.monotonic_ns()
        period_ns = int(UNDECODABLE_WARNING_PERIOD_S * 1e9)
        if self._last_warning_ns is not None and now - self._last_warning_ns < period_ns:
            return
        self._last_warning_ns = now
        self._undecodable_logger.warning(
            f'{self._undecodable_name}: dropped {self._unreported} undecodable sample(s) '
            f'({self.undecodable_count} since start); last: {exc}')
        self._unreported = 0


QOS_POLICY_NAMES = {2: 'DURABILITY', 4: 'DEADLINE', 8: 'LIVELINESS', 11: 'RELIABILITY',
                    13: 'HISTORY', 21: 'LIFESPAN'}
"""rclpy's names (``QoSPolicyKind``) of Cyclone's QoS policy ids (``dds_qos_policy_id_t``), the
ones rmw_cyclonedds maps; any other id is ``INVALID``, as there."""


def qos_policy_name(policy_id: int) -> str:
    """The name rclpy gives the QoS policy of Cyclone's ``policy_id`` (see
    :data:`QOS_POLICY_NAMES`)."""
    return QOS_POLICY_NAMES.get(policy_id, 'INVALID')


class WarnsIncompatibleQos:
    """Base of a publisher or subscription that says when a remote endpoint on its topic cannot
    match it for its QoS (a best-effort publisher to a reliable subscription, a volatile one to
    a transient-local subscription, ...): one WARN on the node's logger naming the topic and
    the last incompatible policy, in rclpy's words (its default incompatible-QoS callbacks).

    Cyclone raises the incompatible-QoS status of the reader or writer once per remote endpoint
    it cannot match, not per sample; the node's wait set waits on it (:attr:`_event_entity`,
    its status mask only that status) and the executor reads it (:meth:`_take_incompatible_qos`),
    which resets it. As in rclpy, endpoints found between two reads of the status make one
    warning, and the warning is logged by the spinning thread, between callbacks.
    """

    _EVENT_STATUS = 0
    """The DDSStatus bit of the incompatible-QoS status of this kind of endpoint."""
    _EVENT_TEXT = ''
    """rclpy's warning, ``{topic}`` and ``{policy}`` to fill in."""

    def _init_incompatible_qos(self, entity: Any, *, logger: Logger, topic: str) -> None:
        entity.set_status_mask(self._EVENT_STATUS)
        self._event_entity: Any = entity
        """The reader or writer whose incompatible-QoS status the node's wait set waits on."""
        self._event_logger = logger
        self._event_topic = topic

    def _incompatible_qos_status(self, entity: Any) -> Any:
        """The incompatible-QoS status of ``entity`` (this endpoint's reader or writer)."""
        raise NotImplementedError

    def _take_incompatible_qos(self) -> list[Callable[[], None]]:
        """Read (and so reset) the incompatible-QoS status; one work item that warns if a remote
        endpoint was refused since the last read, else none. Never raises: the entity is read
        once (another thread may destroy the endpoint meanwhile), and a status that cannot be
        read (an entity deleted under it) gives no warning rather than ending the spin."""
        entity = self._event_entity
        if entity is None:
            return []
        try:
            status = self._incompatible_qos_status(entity)
            changed = status.total_count_change > 0
        except Exception:
            return []
        if not changed:
            return []
        message = self._EVENT_TEXT.format(topic=self._event_topic,
                                          policy=qos_policy_name(status.last_policy_id))
        return [lambda: self._event_logger.warning(message)]


class _TopicEndpoint:
    """What a publisher and a subscription share: a message type on one of the node's topics."""

    def __init__(self, node: Node, msg_type: Any, topic_name: str, qos: QoSProfile) -> None:
        self.msg_type = msg_type
        self.topic_name = topic_name
        self.qos_profile = qos
        self._type_name = messages.message_type_name(msg_type)
        self._topic = node._dds_topic(topic_name, self._type_name)
        self._dds_qos = to_cyclone_qos(qos, type_user_data(self._type_name))


class Publisher(_TopicEndpoint, WarnsIncompatibleQos):
    """rclpy.publisher.Publisher subset.

    ``topic_as_given`` is the name the node was asked for (before expansion and remapping),
    which rclpy's incompatible-QoS warning names (:class:`WarnsIncompatibleQos`).
    """

    _EVENT_STATUS = DDSStatus.OfferedIncompatibleQos
    _EVENT_TEXT = ("New subscription discovered on topic '{topic}', requesting incompatible "
                   'QoS. No messages will be sent to it. Last incompatible policy: {policy}')

    def __init__(self, node: Node, msg_type: Any, topic_name: str, qos: QoSProfile, *,
                 topic_as_given: str | None = None) -> None:
        super().__init__(node, msg_type, topic_name, qos)
        self._writer = DataWriter(node.context.participant, self._topic, qos=self._dds_qos)
        self._quoted_name = repr(topic_name)
        self._init_incompatible_qos(self._writer, logger=node.get_logger(),
                                    topic=topic_as_given or topic_name)

    def _incompatible_qos_status(self, entity: Any) -> Any:
        return entity.get_offered_incompatible_qos_status()

    def publish(self, msg: Any) -> None:
        """Publish a message instance, or already serialized CDR bytes (as rclpy allows)."""
        writer = self._writer
        if writer is None:
            raise RuntimeError(f'publisher on {self.topic_name!r} has been destroyed')
        if type(msg) is bytes:
            data = msg
        elif isinstance(msg, (bytes, bytearray, memoryview)):
            data = bytes(msg)
        else:
            if getattr(msg, '_type_name', None) != self._type_name:
                raise TypeError(f'publisher on {self.topic_name!r} expects {self._type_name}, '
                                f'got {type(msg).__name__}')
            data = messages.serialize_message(msg)
        write_payload(writer, messages.dds_payload(data), name=self._quoted_name)

    def get_subscription_count(self) -> int:
        """Matched subscriptions (any process, including this one)."""
        return self._writer.get_publication_matched_status().current_count

    def destroy(self) -> None:
        delete_entity(self._writer)
        self._writer = self._event_entity = None


class Subscription(_TopicEndpoint, DropsUndecodable, WarnsIncompatibleQos):
    """rclpy.subscription.Subscription subset; ``raw=True`` delivers CDR ``bytes``.

    A sample that does not decode as the topic's type (DDS has checked its structure, but not,
    e.g., that its strings are UTF-8) never reaches the callback nor escapes into the executor:
    it is dropped, counted in :attr:`undecodable_count`, and reported by a one-line warning
    naming the topic (:class:`DropsUndecodable`). A node that must answer such samples
    subscribes with ``raw=True`` and decodes them itself. ``topic_as_given``: as for
    :class:`Publisher`.
    """

    _EVENT_STATUS = DDSStatus.RequestedIncompatibleQos
    _EVENT_TEXT = ("New publisher discovered on topic '{topic}', offering incompatible QoS. "
                   'No messages will be received from it. Last incompatible policy: {policy}')

    def __init__(self, node: Node, msg_type: Any, topic_name: str,
                 callback: Callable[[Any], None], qos: QoSProfile, raw: bool, *,
                 topic_as_given: str | None = None) -> None:
        super().__init__(node, msg_type, topic_name, qos)
        self._init_undecodable(logger=node.get_logger(), name=topic_name)
        self.callback = callback
        self.raw = raw
        self._reader = DataReader(node.context.participant, self._topic, qos=self._dds_qos)
        self._condition = ReadCondition(self._reader, _ANY_SAMPLE)
        self._init_incompatible_qos(self._reader, logger=node.get_logger(),
                                    topic=topic_as_given or topic_name)

    def _incompatible_qos_status(self, entity: Any) -> Any:
        return entity.get_requested_incompatible_qos_status()

    def _take_ready(self) -> list[Callable[[], None]]:
        """Take every received sample now; return one work item per valid sample."""
        if self._reader is None:
            return []
        return [self._deliver_later(data) for data, _info in
                take_valid(self._reader, batch=_TAKE_BATCH, name=repr(self.topic_name))]

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

    def get_publisher_count(self) -> int:
        return self._reader.get_subscription_matched_status().current_count

    def destroy(self) -> None:
        delete_entity(self._condition)
        delete_entity(self._reader)
        self._reader = self._condition = self._event_entity = None


class Timer:
    """rclpy.timer.Timer subset; missed periods are skipped, not queued.

    It runs on the monotonic clock, or, while ``clock`` (a node's ``ROS_TIME`` clock) follows
    ``/clock`` (``use_sim_time``), on that time as rcl's ROS-time timers do: due when the
    simulated time reaches the next period; restarted one period after the time jumps back
    beyond the last call. A switch of ``use_sim_time`` restarts the period in the new time. On
    a ``STEADY_TIME`` (or ``SYSTEM_TIME``) clock it never follows ``/clock``.
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
        """Stop calling back until :meth:`reset` (rclpy's ``Timer.cancel``)."""
        self._canceled = True

    def is_canceled(self) -> bool:
        """True after :meth:`cancel` and before :meth:`reset`."""
        return self._canceled

    def reset(self) -> None:
        """Run again, the next call one period from now (rclpy's ``Timer.reset``)."""
        self._canceled = False
        self._ros_time = self._ros_time_active()
        self._next_ns = self._now() + self.timer_period_ns

    def destroy(self) -> None:
        self._canceled = True


class GuardCondition:
    """rclpy.guard_condition.GuardCondition subset: :meth:`trigger`, from any thread, has the
    node's executor call ``callback`` (in its own thread); triggers before that call make one
    call, as rcl's guard conditions do."""

    def __init__(self, callback: Callable[[], None], wake: Callable[[], None]) -> None:
        self.callback = callback
        self._wake = wake
        self._lock = threading.Lock()
        self._triggered = False

    def trigger(self) -> None:
        """Have the executor call the callback (thread-safe)."""
        with self._lock:
            self._triggered = True
        self._wake()

    def _take(self) -> bool:
        """True once per run of triggers (the executor's thread)."""
        with self._lock:
            triggered, self._triggered = self._triggered, False
        return triggered

    def destroy(self) -> None:
        self._wake = _no_wake
        with self._lock:
            self._triggered = False


def _no_wake() -> None:
    """A destroyed guard condition wakes no executor."""


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
