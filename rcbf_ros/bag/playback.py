"""Replay logic without middleware: which messages, when, and with what QoS.

The replay node (:mod:`rcbf_ros.ros.replay_node`) publishes what :func:`playback_schedule`
yields; an offline consumer (e.g. re-filtering recorded proposals through the safety filter)
iterates :func:`iter_bag_messages` instead and never touches DDS.
"""
from __future__ import annotations

from dataclasses import dataclass
import os
from typing import Callable, Iterable, Iterator, Sequence

from rcbf_ros.bag.qos import RecordedQos
from rcbf_ros.bag.reader import BagInfo, BagMessage, read_bag, TopicInfo

PLAYABLE_MESSAGE_ENCODING = 'cdr'
"""The message encoding a DDS publisher takes as it is (the recorded CDR bytes)."""
PLAYABLE_SCHEMA_ENCODINGS = ('ros2msg', 'ros2idl')
"""Schema encodings whose schema name is a ROS type (``pkg/msg/Type``) to publish as."""


def iter_bag_messages(path: str | os.PathLike[str], *,
                      topics: Iterable[str] | None = None) -> Iterator[BagMessage]:
    """The bag's messages in log-time order, CDR undecoded (the offline-processing entry point).

    Args:
        path: bag directory or ``.mcap`` file.
        topics: only these topic names (default: all).

    Raises:
        rcbf_ros.bag.BagError: a missing, empty, damaged, foreign or cut-short file (checked in
            full before the first message; see :func:`rcbf_ros.bag.reader.read_bag`).
    """
    yield from read_bag(path, topics=topics)


@dataclass(frozen=True)
class ScheduledMessage:
    """A message and when to send it."""

    send_offset_s: float
    """Seconds after playback start (``(log_time - first log_time) / rate``, plus loops)."""
    message: BagMessage
    """The recorded message."""


def playback_schedule(messages: Sequence[BagMessage] | Callable[[], Iterable[BagMessage]], *,
                      rate: float = 1.0, loops: int = 1) -> Iterator[ScheduledMessage]:
    """Send times that reproduce the recorded spacing scaled by ``1 / rate``.

    .. math:: t_k^{(j)} = j \\, T + (\\tau_k - \\tau_0) / r,
              \\qquad T = (\\tau_{n-1} - \\tau_0) / r + \\Delta

    for loop ``j``, recorded log times :math:`\\tau_k` (sorted) and rate :math:`r`; a loop
    restarts one mean inter-message gap :math:`\\Delta` after the previous one ended.

    The messages are taken one at a time: pass ``j = 0`` needs only :math:`\\tau_0`, and by
    the time a second pass needs :math:`T`, the first has counted them. So a bag streamed from
    disk (``messages`` a callable that reads it afresh for every pass, e.g.
    ``lambda: iter_bag_messages(path)``) is played in the memory of one message.

    Args:
        messages: recorded messages, sorted by log time; or a callable returning them anew for
            each pass.
        rate: speed factor (> 0; 2.0 plays twice as fast).
        loops: number of passes (>= 1); ``0`` repeats forever.
    """
    if not rate > 0:
        raise ValueError(f'rate must be > 0, got {rate}')
    if loops < 0:
        raise ValueError(f'loops must be >= 0 (0: forever), got {loops}')
    stream = messages if callable(messages) else (lambda: messages)
    t0: int | None = None
    last, count = 0, 0
    for message in stream():
        if t0 is None:
            t0 = message.log_time_ns
        last, count = message.log_time_ns, count + 1
        yield ScheduledMessage((message.log_time_ns - t0) / 1e9 / rate, message)
    if t0 is None:
        return
    span_s = (last - t0) / 1e9 / rate
    gap_s = span_s / (count - 1) if count > 1 else 0.0
    period_s = span_s + gap_s
    j = 1
    while loops == 0 or j < loops:
        for message in stream():
            yield ScheduledMessage(j * period_s + (message.log_time_ns - t0) / 1e9 / rate,
                                   message)
        j += 1


def unplayable_reason(topic: TopicInfo) -> str:
    """Why a recorded topic cannot be published onto DDS as recorded ('' if it can): one line
    naming the topic and its encoding."""
    if topic.message_encoding != PLAYABLE_MESSAGE_ENCODING:
        return (f'topic {topic.name}: message encoding {topic.message_encoding!r}, not '
                f'{PLAYABLE_MESSAGE_ENCODING!r}')
    if topic.schema_encoding not in PLAYABLE_SCHEMA_ENCODINGS:
        return (f'topic {topic.name}: schema encoding {topic.schema_encoding!r}, not '
                f'{" or ".join(map(repr, PLAYABLE_SCHEMA_ENCODINGS))}')
    if topic.other_types:
        return f'topic {topic.name}: {several_types(topic)}, where a subscriber takes one'
    return ''


def several_types(topic: TopicInfo) -> str:
    """A topic recorded under several types, as a refusal says it ('' for one type)."""
    if not topic.other_types:
        return ''
    types = [topic.type_name, *topic.other_types]
    shown = ', '.join(repr(name[:100]) for name in types[:4]) + (', ...' if len(types) > 4 else '')
    return f'recorded as {len(types)} types ({shown})'


def topics_to_play(info: BagInfo, requested: Iterable[str] = ()) -> tuple[list[str], list[str]]:
    """The topics to publish, sorted, and one line for each recorded topic left out because it
    cannot be published as recorded (:func:`unplayable_reason`).

    Args:
        info: the checked bag.
        requested: the topics asked for (empty: every topic of the bag that can be played).

    Raises:
        ValueError: a requested topic is not in the bag or cannot be played, or no topic can
            (one line naming it).
    """
    requested = list(requested)
    missing = sorted(set(requested) - set(info.topics))
    if missing:
        raise ValueError(f'topics {missing} are not in the bag')
    for name in sorted(set(requested)):
        why = unplayable_reason(info.topics[name])
        if why:
            raise ValueError(f'{why}: it cannot be played')
    if requested:
        return sorted(set(requested)), []
    playable, reasons = [], []
    for name in sorted(info.topics):
        why = unplayable_reason(info.topics[name])
        if why:
            reasons.append(why)
        else:
            playable.append(name)
    if reasons and not playable:
        more = f' (and {len(reasons) - 1} more topics)' if len(reasons) > 1 else ''
        raise ValueError(f'no topic of the bag can be played: {reasons[0]}{more}')
    return playable, [f'{why}: not played' for why in reasons]


def replay_qos(offered: Sequence[RecordedQos]) -> RecordedQos:
    """The profile to publish a recorded topic with.

    As ``ros2 bag play``: the recorded publishers' profile if they all agree on the policies
    that matter for matching (reliability, durability, deadline, liveliness), else the default.
    History is keep-all (so a fast replay to a reliable subscriber drops nothing).
    """
    if not offered:
        return RecordedQos(history='keep_all', depth=0)
    first = offered[0]
    same = all((q.reliability, q.durability, q.deadline_ns, q.liveliness,
                q.liveliness_lease_duration_ns)
               == (first.reliability, first.durability, first.deadline_ns, first.liveliness,
                   first.liveliness_lease_duration_ns) for q in offered)
    if not same:
        return RecordedQos(history='keep_all', depth=0)
    return RecordedQos(history='keep_all', depth=0, reliability=first.reliability,
                       durability=first.durability)
