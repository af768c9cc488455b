"""recorder: record topics into an MCAP bag in rosbag2's layout (``ros2 run rcbf_ros recorder``).

Each message is written as the CDR bytes received (less DDS's padding), never deserialised, so
the bag holds what was on the wire. A failed write stops the recording, not the node, and sets
the exit status to 1. Parameters: :data:`INTERFACE` (``recorder --help``); behaviour:
docs/NODES.md.
"""
from __future__ import annotations

from dataclasses import dataclass
from datetime import datetime, timezone
import sys
from typing import Any, Callable, Sequence

from rcbf_ros.bag import BagWriter, BagWriterConfig, RecordedQos
from rcbf_ros.bag.writer import BagWriteError, max_chunk_bytes, MessageTooLargeError
from rcbf_ros.node_logic.interface import NodeInterface, parameter_specs, TopicSpec
from rcbf_ros.parameters.reader import PERIOD_LIMITS_S, setting
from rcbf_ros.ros.console import console_line
from rcbf_ros.ros.node_main import declare_settings, run_node
from rcbf_ros.ros.runtime import (
    DurabilityPolicy,
    get_message,
    HistoryPolicy,
    Node,
    QoSProfile,
    ReliabilityPolicy,
)

MAX_CHUNK_SIZE = max_chunk_bytes()
"""The largest ``chunk_size`` (bytes): the largest chunk the bag reader accepts (an open chunk
is held in memory until it closes)."""


@dataclass(frozen=True)
class RecorderConfig:
    """What the recorder records, where, and how often it flushes."""

    topics: tuple[str, ...] = setting(
        (), description='topics to record ([]: every topic discovery finds)')
    """Topic names to record; empty: every discovered topic."""
    best_effort_topics: tuple[str, ...] = setting(
        (), description='topics to subscribe best effort (sensor-data publishers)')
    """Topics subscribed best effort (sensor-data publishers)."""
    output: str = setting('', description="the bag directory ('': bags/run_<UTC time>)")
    """Bag directory; empty: ``bags/run_<UTC time>``."""
    flush_period_s: float = setting(
        0.5, minimum=PERIOD_LIMITS_S[0], maximum=PERIOD_LIMITS_S[1],
        description='seconds between flushes of the open chunk (what a SIGKILL can lose)')
    """Seconds between flushes of the open chunk (upper bound on data lost to SIGKILL)."""
    discovery_period_s: float = setting(
        0.1, minimum=PERIOD_LIMITS_S[0], maximum=PERIOD_LIMITS_S[1],
        description='seconds between discovery checks for new topics')
    """Seconds between discovery checks for new topics (``ros2 bag record``'s default)."""
    chunk_size: int = setting(256 * 1024, minimum=1024, maximum=MAX_CHUNK_SIZE,
                              description='uncompressed MCAP chunk size (bytes)')
    """Uncompressed MCAP chunk size in bytes."""
    compression: str = setting('auto',
                               description='chunk compression: auto, zstd, lz4 or none')
    """Chunk compression: ``auto``, ``zstd``, ``lz4`` or ``none``."""

    def __post_init__(self) -> None:
        for name in (*self.topics, *self.best_effort_topics):
            if not name.startswith('/'):
                raise ValueError(f'topics / best_effort_topics: {name!r} must start with /')
        if self.flush_period_s <= 0:
            raise ValueError(f'flush_period_s must be > 0, got {self.flush_period_s}')
        if self.discovery_period_s <= 0:
            raise ValueError(f'discovery_period_s must be > 0, got {self.discovery_period_s}')
        # chunk_size and compression are checked by BagWriterConfig.

    def resolved_output(self, now: datetime | None = None) -> str:
        """The bag directory: :attr:`output`, or ``bags/run_YYYY_MM_DD-HH_MM_SS`` (UTC)."""
        if self.output:
            return self.output
        stamp = (now or datetime.now(timezone.utc)).strftime('%Y_%m_%d-%H_%M_%S')
        return f'bags/run_{stamp}'


def topics_to_subscribe(discovered: Sequence[tuple[str, Sequence[str]]],
                        wanted: Sequence[str], already: Sequence[str]) -> list[tuple[str, str]]:
    """New ``(topic, type)`` pairs to record from a discovery snapshot.

    Args:
        discovered: ``get_topic_names_and_types()`` output.
        wanted: topic names to record (empty: all).
        already: topics already recorded.

    Topics with several types take the first one listed (a warning is the caller's business).
    """
    wanted_set = set(wanted)
    done = set(already)
    new = []
    for name, types in discovered:
        if name in done or not types or (wanted_set and name not in wanted_set):
            continue
        new.append((name, types[0]))
    return new


def request_reliability(offered: Sequence[RecordedQos] | None, force_best_effort: bool) -> str:
    """``reliable`` or ``best_effort`` for a recording subscription.

    As ``ros2 bag record`` adapts its request: reliable only if every publisher offers reliable
    (a reliable reader never matches a best-effort writer). Without offer information, reliable
    unless the topic is configured best effort.
    """
    if force_best_effort:
        return 'best_effort'
    if offered:
        return 'reliable' if all(q.reliability == 'reliable' for q in offered) else 'best_effort'
    return 'reliable'


def request_durability(offered: Sequence[RecordedQos]) -> str:
    """``transient_local`` or ``volatile`` for a recording subscription.

    As ``ros2 bag record`` adapts its request: transient local only if every publisher offers
    it (a transient-local reader never matches a volatile writer); then the recorder also gets
    the samples each publisher keeps for late joiners.
    """
    if offered and all(q.durability == 'transient_local' for q in offered):
        return 'transient_local'
    return 'volatile'


_PADDING_MASK = 0x03  # the low two bits of the encapsulation options (XTypes 1.3, 7.6.3.1.2)


def cdr_payload(sample: bytes) -> bytes:
    """The CDR stream of a received serialized message, as ``serialize_message`` gives it.

    DDS carries a sample zero-padded to a multiple of 4 bytes; a writer that follows XTypes
    1.3 (7.6.3.1.2; Cyclone's serializer and this package's runtime) states the number of
    padding bytes in the low two bits of the encapsulation options. That padding is removed
    and the statement cleared, so the stored bytes are exactly the serialized message. A sample
    that states no padding (rmw_cyclonedds pads but does not say so; rosbag2 then stores the
    padding too) or is too short for what it states is returned unchanged.
    """
    if len(sample) < 4:
        return sample
    pad = sample[3] & _PADDING_MASK
    if pad == 0 or len(sample) - pad < 4:
        return sample
    return sample[:3] + bytes([sample[3] & ~_PADDING_MASK & 0xFF]) + sample[4:len(sample) - pad]


def _print_error(line: str) -> None:
    console_line(line)


class Recorder:
    """Topic bookkeeping and the bag, independent of how messages arrive.

    A write error stops the recording (:attr:`stopped`): the bag is closed then, one line goes
    to ``report`` and every later call does nothing.

    Args:
        writer: the open bag.
        clock_ns: receive-time source (nanoseconds since the epoch).
        report: where the line saying that recording stopped goes (the node's error log).
    """

    def __init__(self, writer: BagWriter, clock_ns: Callable[[], int],
                 report: Callable[[str], None] | None = None) -> None:
        self.writer = writer
        self.clock_ns = clock_ns
        self.report = report or _print_error
        self.dropped_unknown_type: set[str] = set()
        self.stopped: BagWriteError | None = None
        """The write error that stopped the recording (None while recording)."""
        self.refused_samples = 0
        """Samples the bag refused (no CDR encapsulation header): left out, counted."""
        self.oversized_samples: dict[str, int] = {}
        """Per topic, samples too large for any chunk of the bag: left out, counted."""

    def _stop(self, error: BagWriteError) -> None:
        self.stopped = error
        self.report(f'recording stopped: {error}; the recorder goes on without recording')

    def add(self, topic: str, type_name: str, offered: Sequence[RecordedQos]) -> bool:
        """Register ``topic`` in the bag; False if its type has no definition available or
        the recording has stopped."""
        if self.stopped is not None:
            return False
        try:
            self.writer.add_topic(topic, type_name, qos=list(offered) or None)
        except BagWriteError as exc:
            self._stop(exc)
            return False
        except ValueError:
            self.dropped_unknown_type.add(topic)
            return False
        return True

    def on_message(self, topic: str, sample: bytes) -> None:
        """Write one received sample's CDR stream, stamped with the receive time."""
        if self.stopped is not None:
            return
        try:
            self.writer.write(topic, cdr_payload(sample), self.clock_ns())
        except BagWriteError as exc:
            self._stop(exc)
        except MessageTooLargeError as exc:  # left out, the recording goes on
            seen = self.oversized_samples.get(topic, 0)
            self.oversized_samples[topic] = seen + 1
            if not seen:
                self.report(f'{exc} (the first on {topic}; later ones are counted, not '
                            'reported)')
        except ValueError as exc:  # not a CDR sample: left out, the recording goes on
            self.refused_samples += 1
            if self.refused_samples == 1:
                self.report(f'a sample on {topic} left out of the bag: {exc} (the first; '
                            'later ones are counted, not reported)')

    def flush(self) -> None:
        """Write the open chunk out (bounds what a SIGKILL can lose)."""
        if self.stopped is not None:
            return
        try:
            self.writer.flush()
        except BagWriteError as exc:
            self._stop(exc)

    def close(self) -> None:
        """Close the bag (summary and metadata.yaml); a write error is reported, not raised."""
        if self.stopped is not None:
            return
        try:
            self.writer.close()
        except BagWriteError as exc:
            self.stopped = exc
            self.report(f'closing the bag failed: {exc}')

    def counts(self) -> dict[str, int]:
        """Messages written per topic (after a write error: those in the bag)."""
        return {name: t.message_count for name, t in self.writer.topics.items()}


class RecorderNode(Node):
    """The ROS face of :class:`Recorder`: parameters, discovery, raw subscriptions, timers."""

    def __init__(self) -> None:
        super().__init__('recorder')
        self.config = self._read_config()
        self.bag_directory = self.config.resolved_output()
        writer = BagWriter(self.bag_directory, config=BagWriterConfig(
            chunk_size=self.config.chunk_size, compression=self.config.compression,
            flush_period_s=self.config.flush_period_s))
        self.recorder = Recorder(writer, lambda: self.get_clock().now().nanoseconds,
                                 report=lambda line: self.get_logger().error(line))
        self._subscriptions_by_topic: dict[str, Any] = {}
        self._warned: set[str] = set()
        try:
            self.discover()
            self.create_timer(self.config.discovery_period_s, self.discover)
            self.create_timer(self.config.flush_period_s, self.flush)
        except BaseException:
            # Ctrl-C (or a failure) while the node is still being built, before it can take
            # its exit path: the bag opened above is closed complete all the same.
            self.recorder.close()
            raise
        # Said once the node is built: from here on Ctrl-C closes the bag and reports it.
        self.get_logger().info(
            f'recording {list(self.config.topics) or "all topics"} into {self.bag_directory}')

    def _read_config(self) -> RecorderConfig:
        """Declare and read every parameter (:func:`declare_settings`); a bad one is a
        ValueError naming it. A topic list unset is empty."""
        return declare_settings(self, RecorderConfig)

    def _offered_qos(self, topic: str) -> list[RecordedQos] | None:
        """The publishers' offered QoS ([] while there is none); None where the runtime does
        not report offers."""
        info = getattr(self, 'get_publishers_info_by_topic', None)
        if info is None:
            return None
        try:
            return [RecordedQos.from_profile(e.qos_profile) for e in info(topic)]
        except (AttributeError, TypeError, ValueError):
            return None

    def discover(self) -> None:
        """Subscribe to topics that discovery shows and that are not recorded yet."""
        if self.recorder.stopped is not None:
            return
        discovered = [(name, list(types)) for name, types in self.get_topic_names_and_types()]
        for name, types in discovered:
            if len(types) > 1 and name not in self._warned:
                self._warned.add(name)
                self.get_logger().warning(f'topic {name} has several types {types}; '
                                          f'recording {types[0]}')
        already = [*self._subscriptions_by_topic, *self.recorder.dropped_unknown_type]
        for topic, type_name in topics_to_subscribe(discovered, self.config.topics, already):
            self._subscribe(topic, type_name)

    def _subscribe(self, topic: str, type_name: str) -> None:
        offered = self._offered_qos(topic)
        if offered == []:
            return  # no publisher yet: the next discovery check subscribes with its offer
        offered = offered or []
        reliability = request_reliability(offered, topic in self.config.best_effort_topics)
        durability = request_durability(offered)
        recorded_offer = offered or [RecordedQos(reliability=reliability)]
        if not self.recorder.add(topic, type_name, recorded_offer):
            if self.recorder.stopped is None:
                self.get_logger().warning(f'not recording {topic}: type {type_name} unknown')
            return
        try:
            msg_type = get_message(type_name)
        except (ValueError, AttributeError, ModuleNotFoundError) as exc:
            self.get_logger().warning(f'not recording {topic}: {exc}')
            self.recorder.dropped_unknown_type.add(topic)
            return
        qos = QoSProfile(
            history=HistoryPolicy.KEEP_ALL, depth=1000,
            reliability=(ReliabilityPolicy.RELIABLE if reliability == 'reliable'
                         else ReliabilityPolicy.BEST_EFFORT),
            durability=(DurabilityPolicy.TRANSIENT_LOCAL if durability == 'transient_local'
                        else DurabilityPolicy.VOLATILE))
        self._subscriptions_by_topic[topic] = self.create_subscription(
            msg_type, topic, lambda data, name=topic: self.recorder.on_message(name, data),
            qos, raw=True)
        self.get_logger().info(f'recording {topic} [{type_name}] ({reliability}, {durability})')

    def flush(self) -> None:
        """Write the open chunk out (bounds what a SIGKILL can lose)."""
        self.recorder.flush()

    def close(self) -> dict[str, int]:
        """Close the bag (summary and metadata.yaml); return per-topic counts in it."""
        self.recorder.close()
        return self.recorder.counts()


INTERFACE = NodeInterface(
    node='recorder',
    summary="Record topics into an MCAP bag in rosbag2's layout (Ctrl-C closes it).",
    topics=(TopicSpec('<every topic>', 'sub', 'as discovered (recorded as CDR bytes)',
                      'all topics, or `topics`; re-checked every discovery_period_s',
                      'keep-all; reliable unless a publisher offers best effort, or '
                      'best_effort_topics'),),
    parameters=parameter_specs(RecorderConfig),  # a test compares them with the declarations
)


WRITE_ERROR_EXIT = 1
"""Exit status of a recorder whose recording a write error stopped (the bag is short)."""


def main(args: Sequence[str] | None = None) -> int:
    """Console script ``recorder``: 0; 2 for bad parameters or a bag it cannot start;
    :data:`WRITE_ERROR_EXIT` if a write error stopped the recording."""
    stopped: list[BagWriteError] = []

    def close_bag(node: RecorderNode) -> None:
        counts = node.close()
        total = sum(counts.values())
        per_topic = ', '.join(f'{name}: {n}' for name, n in counts.items()) or 'no topics'
        if node.recorder.stopped is not None:
            stopped.append(node.recorder.stopped)
        oversized = node.recorder.oversized_samples
        node.get_logger().info(
            f'bag {node.bag_directory} closed: {total} messages ({per_topic})'
            + (f'; left out, too large for a chunk: {sum(oversized.values())} '
               f'({", ".join(f"{name}: {n}" for name, n in oversized.items())})'
               if oversized else '')
            + ('; recording had stopped on a write error' if stopped else ''))

    status = run_node('recorder', RecorderNode, args, on_exit=close_bag,
                      setup_errors=(OSError, ValueError), setup_message='cannot record: ',
                      interface=INTERFACE)
    return WRITE_ERROR_EXIT if status == 0 and stopped else status


if __name__ == '__main__':
    sys.exit(main())
