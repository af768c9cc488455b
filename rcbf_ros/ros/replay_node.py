"""replay: play a bag onto its topics (``ros2 run rcbf_ros replay``).

Parameters (``--ros-args -p name:=value``):

- ``bag`` (string, required): bag directory or ``.mcap`` file.
- ``rate`` (float, 1.0): speed factor; ``2.0`` plays twice as fast.
- ``loop`` (bool, false): start over after the last message, until stopped.
- ``topics`` (string list, empty: all): topics to play.
- ``wait_for_subscribers_s`` (float, 0.0): before playing, wait up to this long until every
  played topic has at least one matched subscriber (so a just-started recorder misses nothing).
- ``linger_s`` (float, 0.5): after the last message, keep the node alive this long so reliable
  retransmissions can finish.

Messages are published as the recorded CDR bytes, with the QoS of the recorded publishers
(:func:`rcbf_ros.bag.playback.replay_qos`). The bag is read and checked in full before anything
is published: a missing, empty, damaged (chunk or data CRC mismatch), foreign or cut-short file
ends the node with one line naming the file and what is wrong, exit status 2 (a bag whose
recorder was killed plays after ``rcbf_ros bag recover <bag>``). Only topics recorded as CDR
with a ROS schema (``ros2msg`` or ``ros2idl``) can be published as recorded
(:func:`rcbf_ros.bag.playback.topics_to_play`): any other is left out with one warning line
naming it and its encoding, or, named in ``topics``, refused (exit 2). A message that DDS
refuses to send all the same stops the replay with one line, exit 2. The messages are then
streamed from the bag (read again for every loop), one at a time: the node's memory does not
grow with the bag. Offline processing of a bag
(e.g. re-filtering) does not go through this node: use
:func:`rcbf_ros.bag.playback.iter_bag_messages`.
"""
from __future__ import annotations

from dataclasses import dataclass
import sys
import time
from typing import Any, Iterator, Sequence

from rcbf_ros.bag import bag_info, BagError, BagMessage
from rcbf_ros.bag.playback import (
    iter_bag_messages,
    playback_schedule,
    replay_qos,
    topics_to_play,
)
from rcbf_ros.node_logic.interface import NodeInterface, parameter_specs, TopicSpec
from rcbf_ros.parameters.reader import PERIOD_LIMITS_S, RATE_LIMITS_HZ, setting
from rcbf_ros.ros.node_main import declare_settings, run_node
from rcbf_ros.ros.runtime import (
    DurabilityPolicy,
    get_message,
    HistoryPolicy,
    Node,
    QoSProfile,
    rclpy,
    ReliabilityPolicy,
)


@dataclass(frozen=True)
class ReplayConfig:
    """What to play and how fast."""

    bag: str = setting('', description='bag directory or .mcap file (required)')
    """Bag directory or ``.mcap`` file."""
    rate: float = setting(1.0, minimum=RATE_LIMITS_HZ[0], maximum=RATE_LIMITS_HZ[1],
                         description='speed factor (2.0: twice as fast)')
    """Speed factor (> 0)."""
    loop: bool = setting(False, description='start over after the last message, until stopped')
    """Repeat until stopped."""
    topics: tuple[str, ...] = setting((), description='topics to play ([]: all)')
    """Topics to play; empty: all."""
    wait_for_subscribers_s: float = setting(
        0.0, minimum=0, maximum=PERIOD_LIMITS_S[1],
        description='longest wait (s) for a subscriber on every topic before playing')
    """Longest wait for a subscriber on every topic before playing."""
    linger_s: float = setting(0.5, minimum=0, maximum=PERIOD_LIMITS_S[1],
                              description='seconds to stay alive after the last message '
                                          '(retransmissions)')
    """Seconds to stay alive after the last message."""

    def __post_init__(self) -> None:
        if not self.bag:
            raise ValueError('bag: required (a bag directory or .mcap file)')
        if not self.rate > 0:
            raise ValueError(f'rate must be > 0, got {self.rate}')
        if self.wait_for_subscribers_s < 0 or self.linger_s < 0:
            raise ValueError('wait_for_subscribers_s and linger_s must be >= 0')


class ReplayNode(Node):
    """Publishers for a bag's topics and the playback loop."""

    def __init__(self) -> None:
        super().__init__('replay')
        self.config = self._read_config()
        info = bag_info(self.config.bag, allow_cut_short=False)
        try:
            wanted, skipped = topics_to_play(info, self.config.topics)
        except ValueError as exc:
            raise ValueError(f'bag {self.config.bag!r}: {exc}') from None
        for line in skipped:
            self.get_logger().warning(line)
        self.publishers_by_topic: dict[str, Any] = {}
        for name in wanted:
            topic = info.topics[name]
            try:
                message_type = get_message(topic.type_name)
            except (AttributeError, ImportError, TypeError) as exc:  # ValueError: run_node's
                raise ValueError(f'topic {name}: type {topic.type_name!r} unknown '
                                 f'({type(exc).__name__}: {exc})') from None
            qos = replay_qos(topic.offered_qos)
            profile = QoSProfile(
                history=HistoryPolicy.KEEP_ALL, depth=1000,
                reliability=(ReliabilityPolicy.BEST_EFFORT if qos.reliability == 'best_effort'
                             else ReliabilityPolicy.RELIABLE),
                durability=(DurabilityPolicy.TRANSIENT_LOCAL
                            if qos.durability == 'transient_local'
                            else DurabilityPolicy.VOLATILE))
            self.publishers_by_topic[name] = self.create_publisher(message_type, name, profile)
        self.failure = ''
        """Why playing stopped before the end ('' if it did not)."""
        self.wanted = frozenset(wanted)
        self.message_count = sum(info.topics[name].message_count for name in wanted)
        self.published = 0
        self.get_logger().info(
            f'replaying {self.message_count} messages on {sorted(wanted)} from '
            f'{self.config.bag} at rate {self.config.rate}{" (loop)" if self.config.loop else ""}')

    def messages(self) -> Iterator[BagMessage]:
        """The bag's messages on the played topics, read afresh: one message in memory at a
        time (a chunk's worth while it is read), whatever the bag's size."""
        return iter_bag_messages(self.config.bag, topics=self.wanted)

    def _read_config(self) -> ReplayConfig:
        """Declare and read every parameter (:func:`declare_settings`); a bad one is a
        ValueError naming it. ``topics`` unset: every topic."""
        return declare_settings(self, ReplayConfig)

    def _sleep_until(self, deadline: float) -> None:
        """Serve the executor (so signals are seen) until ``time.monotonic() >= deadline``."""
        while True:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                return
            rclpy.spin_once(self, timeout_sec=min(remaining, 0.05))

    def wait_for_subscribers(self) -> bool:
        """True once every publisher has a matched subscriber (False on timeout)."""
        deadline = time.monotonic() + self.config.wait_for_subscribers_s
        while True:
            if all(p.get_subscription_count() > 0 for p in self.publishers_by_topic.values()):
                return True
            if time.monotonic() >= deadline:
                return False
            self._sleep_until(min(deadline, time.monotonic() + 0.05))

    def play(self) -> None:
        """Publish the bag on schedule (until the end, or forever with ``loop``)."""
        if self.config.wait_for_subscribers_s > 0 and not self.wait_for_subscribers():
            self.get_logger().warning('not every topic has a subscriber; playing anyway')
        start = time.monotonic()
        try:
            for item in playback_schedule(self.messages, rate=self.config.rate,
                                          loops=0 if self.config.loop else 1):
                self._sleep_until(start + item.send_offset_s)
                topic = item.message.topic
                try:
                    self.publishers_by_topic[topic].publish(item.message.data)
                except (RuntimeError, ValueError) as exc:  # DDS refused the bytes: one line
                    self.failure = (f'{topic}: the message logged at {item.message.log_time_ns} '
                                    f'ns not published ({exc})')
                    return
                self.published += 1
        except BagError as exc:  # the bag changed after it was checked: stop, one line
            self.failure = str(exc)
            return
        self._sleep_until(time.monotonic() + self.config.linger_s)


INTERFACE = NodeInterface(
    node='replay',
    summary='Play a bag onto its topics (the bag is checked in full first).',
    topics=(TopicSpec('<every recorded topic>', 'pub', 'as recorded (CDR bytes as recorded)',
                      'all recorded topics, or `topics`, on the recorded schedule / rate',
                      "the recorded publishers' QoS, keep-all"),),
    parameters=parameter_specs(ReplayConfig),  # a test compares them with the declarations
)


def main(args: Sequence[str] | None = None) -> int:
    """Console script ``replay``."""

    failures: list[str] = []

    def report(node: ReplayNode) -> None:
        if node.failure:
            failures.append(node.failure)
            print(f'replay: {node.failure} ({node.published} messages published)',
                  file=sys.stderr)
            return
        node.get_logger().info(f'replay finished: {node.published} messages published')

    # A bad bag (BagError, a ValueError), a missing file or bad parameters: one line, exit 2;
    # so is a bag that changes while it plays (after its check).
    status = run_node('replay', ReplayNode, args, run=ReplayNode.play, on_exit=report,
                      setup_errors=(ValueError, OSError), setup_message='', interface=INTERFACE)
    return 2 if failures and status == 0 else status


if __name__ == '__main__':
    sys.exit(main())
