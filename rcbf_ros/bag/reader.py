"""Read bags written by :class:`rcbf_ros.bag.writer.BagWriter` (or by rosbag2 with MCAP storage).

:func:`read_bag` iterates ``(topic, type_name, cdr bytes, log_time_ns, publish_time_ns)`` in
log-time order. A file that was cut short (its writer killed) has no summary or footer; it is
then read front to back with mcap's streaming reader up to the last complete record, so the
chunks flushed before the kill are all returned (see the writer's crash-safety note).
:func:`reindex_bag` rebuilds ``metadata.yaml`` for such a bag, like ``ros2 bag reindex``.
"""
from __future__ import annotations

from dataclasses import dataclass
import heapq
import os
from pathlib import Path
from typing import Any, Iterable, Iterator, NamedTuple

from mcap.exceptions import McapError
from mcap.reader import make_reader
from mcap.records import Channel, Message, Schema
from mcap.stream_reader import StreamReader
import yaml

from rcbf_ros.bag.messages import deserialize_message
from rcbf_ros.bag.qos import parse_offered_qos_profiles, RecordedQos


class BagMessage(NamedTuple):
    """One recorded message."""

    topic: str
    """Topic name, e.g. ``/state``."""
    type_name: str
    """``pkg/msg/Type`` (the MCAP schema name)."""
    data: bytes
    """CDR bytes with encapsulation header."""
    log_time_ns: int
    """Receive time, nanoseconds since the epoch."""
    publish_time_ns: int
    """Send time, nanoseconds since the epoch."""


@dataclass(frozen=True)
class TopicInfo:
    """A topic found in a bag."""

    name: str
    """Topic name."""
    type_name: str
    """``pkg/msg/Type``."""
    message_count: int
    """Messages on the topic that can be read."""
    offered_qos: tuple[RecordedQos, ...]
    """QoS profiles the recorded publishers offered."""
    type_hash: str
    """``RIHS01_...`` (empty if the bag does not carry one)."""


@dataclass(frozen=True)
class BagInfo:
    """Summary of a bag as it can be read now."""

    files: tuple[Path, ...]
    """The MCAP files, in order."""
    topics: dict[str, TopicInfo]
    """Per topic name."""
    message_count: int
    """All readable messages."""
    start_time_ns: int
    """Earliest log time (0 if empty)."""
    end_time_ns: int
    """Latest log time (0 if empty)."""
    complete: bool
    """True if every file has its summary and footer (closed cleanly)."""


def mcap_files(path: str | os.PathLike[str]) -> list[Path]:
    """The MCAP files of a bag: ``path`` itself if a file; else the files that the directory's
    ``metadata.yaml`` lists, or (no metadata, e.g. after a crash) its ``*.mcap`` files sorted.

    Raises:
        FileNotFoundError: nothing readable at ``path``.
    """
    p = Path(path)
    if p.is_file():
        return [p]
    if not p.is_dir():
        raise FileNotFoundError(f'bag path {str(p)!r} does not exist')
    meta = p / 'metadata.yaml'
    if meta.is_file():
        info = yaml.safe_load(meta.read_text())['rosbag2_bagfile_information']
        return [p / rel for rel in info['relative_file_paths']]
    files = sorted(p.glob('*.mcap'), key=_split_index)
    if not files:
        raise FileNotFoundError(f'bag directory {str(p)!r} holds no .mcap file')
    return files


def _split_index(path: Path) -> tuple[int, str]:
    stem = path.stem
    tail = stem.rsplit('_', 1)[-1]
    return (int(tail) if tail.isdigit() else 0, stem)


@dataclass
class _FileScan:
    schemas: dict[int, Schema]
    channels: dict[int, Channel]
    messages: list[Message]
    complete: bool


def _scan_streaming(stream: Any) -> _FileScan:
    """Read records front to back, stopping quietly at a truncated or corrupt tail."""
    schemas: dict[int, Schema] = {}
    channels: dict[int, Channel] = {}
    messages: list[Message] = []
    complete = False
    try:
        for record in StreamReader(stream, skip_magic=False).records:
            if isinstance(record, Schema):
                schemas[record.id] = record
            elif isinstance(record, Channel):
                channels[record.id] = record
            elif isinstance(record, Message):
                messages.append(record)
        complete = True
    except (McapError, EOFError, ValueError, OSError, RuntimeError):
        # A cut-short file ends inside a record; everything before it is good.
        pass
    return _FileScan(schemas, channels, messages, complete)


def _read_summary(stream: Any) -> Any:
    """The file's summary section, or None for a cut-short file; rewinds ``stream``."""
    try:
        summary = make_reader(stream).get_summary()
    except (McapError, EOFError, ValueError, OSError):
        summary = None
    stream.seek(0)
    return summary


def _iter_file(path: Path, topics: frozenset[str] | None) -> Iterator[BagMessage]:
    with open(path, 'rb') as stream:
        summary = _read_summary(stream)
        if summary is not None:
            reader = make_reader(stream)
            for schema, channel, message in reader.iter_messages(
                    topics=None if topics is None else list(topics), log_time_order=True):
                yield BagMessage(channel.topic, schema.name if schema else '', message.data,
                                 message.log_time, message.publish_time)
            return
        scan = _scan_streaming(stream)
    scan.messages.sort(key=lambda m: m.log_time)
    for message in scan.messages:
        channel = scan.channels.get(message.channel_id)
        if channel is None or (topics is not None and channel.topic not in topics):
            continue
        schema = scan.schemas.get(channel.schema_id)
        yield BagMessage(channel.topic, schema.name if schema else '', message.data,
                         message.log_time, message.publish_time)


def read_bag(path: str | os.PathLike[str], *,
             topics: Iterable[str] | None = None) -> Iterator[BagMessage]:
    """Iterate a bag's messages in log-time order (across files too).

    Args:
        path: a bag directory or one ``.mcap`` file.
        topics: only these topic names (default: all).
    """
    wanted = None if topics is None else frozenset(topics)
    streams = [_iter_file(f, wanted) for f in mcap_files(path)]
    if len(streams) == 1:
        yield from streams[0]
    else:
        yield from heapq.merge(*streams, key=lambda m: m.log_time_ns)


def read_bag_messages(path: str | os.PathLike[str], *,
                      topics: Iterable[str] | None = None) -> Iterator[tuple[BagMessage, Any]]:
    """Like :func:`read_bag`, with each message also decoded to a rosbags message object."""
    for item in read_bag(path, topics=topics):
        yield item, deserialize_message(item.data, item.type_name)


def bag_info(path: str | os.PathLike[str]) -> BagInfo:
    """Topics, counts and time range of a bag, from its data (works on a cut-short bag)."""
    files = mcap_files(path)
    counts: dict[str, int] = {}
    topic_meta: dict[str, tuple[str, tuple[RecordedQos, ...], str]] = {}
    start: int | None = None
    end: int | None = None
    total = 0
    complete = True
    for file in files:
        with open(file, 'rb') as stream:
            summary = _read_summary(stream)
            if summary is None or summary.statistics is None:
                complete = False
                scan = _scan_streaming(stream)
                channels, schemas = scan.channels, scan.schemas
                per_channel: dict[int, int] = {}
                for m in scan.messages:
                    per_channel[m.channel_id] = per_channel.get(m.channel_id, 0) + 1
                    start = m.log_time if start is None else min(start, m.log_time)
                    end = m.log_time if end is None else max(end, m.log_time)
            else:
                channels, schemas = summary.channels, summary.schemas
                per_channel = dict(summary.statistics.channel_message_counts)
                if summary.statistics.message_count:
                    s, e = (summary.statistics.message_start_time,
                            summary.statistics.message_end_time)
                    start = s if start is None else min(start, s)
                    end = e if end is None else max(end, e)
        for channel_id, channel in channels.items():
            schema = schemas.get(channel.schema_id)
            topic_meta.setdefault(channel.topic, (
                schema.name if schema else '',
                tuple(parse_offered_qos_profiles(
                    channel.metadata.get('offered_qos_profiles', ''))),
                channel.metadata.get('topic_type_hash', '')))
            n = per_channel.get(channel_id, 0)
            counts[channel.topic] = counts.get(channel.topic, 0) + n
            total += n
    topics = {name: TopicInfo(name, meta[0], counts.get(name, 0), meta[1], meta[2])
              for name, meta in topic_meta.items()}
    return BagInfo(tuple(files), topics, total, start or 0, end or 0, complete)


def reindex_bag(directory: str | os.PathLike[str]) -> Path:
    """Write ``metadata.yaml`` for a bag directory from its data (e.g. after a crash).

    Returns:
        The path of the metadata file written.
    """
    from rcbf_ros.bag.qos import dump_offered_qos_profiles
    from rcbf_ros.bag.writer import BAG_FORMAT_VERSION, ROS_DISTRO, write_metadata_yaml

    directory = Path(directory)
    if not directory.is_dir():
        raise NotADirectoryError(f'bag directory {str(directory)!r} does not exist')
    files = sorted(directory.glob('*.mcap'), key=_split_index)
    if not files:
        raise FileNotFoundError(f'bag directory {str(directory)!r} holds no .mcap file')
    meta = directory / 'metadata.yaml'
    if meta.exists():
        meta.unlink()
    file_entries = []
    for file in files:
        one = bag_info(file)
        file_entries.append({
            'path': file.name,
            'starting_time': {'nanoseconds_since_epoch': one.start_time_ns},
            'duration': {'nanoseconds': one.end_time_ns - one.start_time_ns},
            'message_count': one.message_count})
    info = bag_info(directory)
    data = {
        'version': BAG_FORMAT_VERSION,
        'storage_identifier': 'mcap',
        'duration': {'nanoseconds': info.end_time_ns - info.start_time_ns},
        'starting_time': {'nanoseconds_since_epoch': info.start_time_ns},
        'message_count': info.message_count,
        'topics_with_message_count': [
            {'topic_metadata': {
                'name': t.name, 'type': t.type_name, 'serialization_format': 'cdr',
                'offered_qos_profiles': dump_offered_qos_profiles(t.offered_qos),
                'type_description_hash': t.type_hash},
             'message_count': t.message_count}
            for t in info.topics.values()],
        'compression_format': '',
        'compression_mode': '',
        'relative_file_paths': [f.name for f in files],
        'files': file_entries,
        'custom_data': {},
        'ros_distro': ROS_DISTRO,
    }
    return write_metadata_yaml(directory, data)
