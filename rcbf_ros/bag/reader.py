"""Read bags written by :class:`rcbf_ros.bag.writer.BagWriter` (or by rosbag2 with MCAP storage).

:func:`read_bag` iterates ``(topic, type_name, cdr bytes, log_time_ns, publish_time_ns)`` in
log-time order. Every file is checked in full before the first message is returned
(:class:`rcbf_ros.bag.scan.McapScan`: framing, chunk CRCs, data and summary CRCs, footer), so
a damaged, empty or foreign file raises :class:`BagError` (one line: the file and what is wrong)
instead of yielding wrong or partial data. A file cut short (its writer killed: no summary or
footer) is refused as well, with the command that recovers it (:mod:`rcbf_ros.bag.recover`);
``allow_cut_short=True`` reads its whole chunks instead, and :func:`bag_info` does so by default
(it reports :attr:`BagInfo.complete`).

Limits. ``metadata.yaml`` is read up to :data:`MAX_METADATA_BYTES` (16 MiB), without aliases,
nested at most 64 deep (:mod:`rcbf_ros.parameters.bounded_yaml`); a chunk holds at most
:data:`rcbf_ros.bag.scan.MAX_CHUNK_BYTES` (64 MiB) once decompressed, checked before it is
decompressed (:mod:`rcbf_ros.bag.scan`). A file past a limit is a :class:`BagError`. Only
regular files are read (a FIFO would block the reader, a device never end), and
``relative_file_paths`` names each file once, inside the bag directory (:func:`mcap_files`).
"""
from __future__ import annotations

from dataclasses import dataclass
import heapq
import os
from pathlib import Path, PurePath
import stat
import struct
from typing import Any, Iterable, Iterator, NamedTuple

from mcap.exceptions import McapError
from mcap.reader import make_reader
from mcap.records import Channel, Message, Schema
import yaml

from rcbf_ros.bag.qos import parse_offered_qos_profiles, RecordedQos
from rcbf_ros.bag.scan import (
    BagError,
    BagNotFoundError,
    check_regular,
    McapScan,
    not_regular_error,
    open_regular,
)
from rcbf_ros.messages.cdr import deserialize_rosbags_message
from rcbf_ros.parameters import bounded_yaml

MAX_METADATA_BYTES = 16 * 2**20
"""Largest ``metadata.yaml`` read (16 MiB; rosbag2 writes about 1 KiB per topic and file)."""


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
    message_definition: str = ''
    """The schema text as recorded (``ros2msg``: the full definition; empty if none)."""
    schema_encoding: str = ''
    """The schema's encoding, e.g. ``ros2msg`` (empty if the channel has no schema)."""
    message_encoding: str = ''
    """The messages' encoding, e.g. ``cdr``; the topic's channels disagreeing, each of theirs
    (sorted, comma-separated)."""
    other_types: tuple[str, ...] = ()
    """The types other channels of the topic declare, sorted (none: every channel is
    ``type_name``). A topic on DDS is one type; a bag written by another tool or merged from
    two may hold one topic under several, and a reader of ``type_name`` cannot decode the
    others."""


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
    """True if every file has its summary and footer (closed cleanly); False if some file was
    cut short (then only its whole chunks are counted)."""


def mcap_files(path: str | os.PathLike[str]) -> list[Path]:
    """The MCAP files of a bag: ``path`` itself if a file; else the files that the directory's
    ``metadata.yaml`` lists, or (no metadata, e.g. after a crash) its ``*.mcap`` files sorted.

    Only regular files are taken (a FIFO would block the reader, a device never end); the
    entries of ``relative_file_paths`` must be names inside the bag directory (no absolute
    path, no ``..``), each file once.

    Raises:
        BagNotFoundError: nothing at ``path``, no ``.mcap`` file in the directory, or a file
            that ``metadata.yaml`` lists is missing (also a FileNotFoundError).
        BagError: ``metadata.yaml`` cannot be read or lists a file outside the bag or twice; a
            file of the bag (or ``path``) is not a regular file.
    """
    p = Path(path)
    try:
        mode = p.stat().st_mode
    except FileNotFoundError as exc:
        raise BagNotFoundError(f'{p}: does not exist (no bag directory or .mcap file there)'
                               ) from exc
    except OSError as exc:
        raise BagError(f'{p}: cannot be examined ({exc.strerror or exc})') from exc
    if stat.S_ISREG(mode):
        return [p]
    if not stat.S_ISDIR(mode):
        raise not_regular_error(p, mode)
    meta = p / 'metadata.yaml'
    if os.path.lexists(meta):
        files = [p / rel for rel in _listed_files(meta)]
        for file in files:
            if not file.exists():
                raise BagNotFoundError(f'{meta}: lists {file.name}, which does not exist')
            check_regular(file)
        if not files:
            raise BagNotFoundError(f'{meta}: lists no file')
    else:
        files = sorted(p.glob('*.mcap'), key=bag_file_order)
        if not files:
            raise BagNotFoundError(f'{p}: bag directory holds no .mcap file')
        for file in files:
            check_regular(file)
    _refuse_same_file(files, meta if os.path.lexists(meta) else p)
    return files


def _listed_files(meta: Path) -> list[str]:
    """``relative_file_paths`` of a bag's ``metadata.yaml``: names inside the bag directory.

    Raises:
        BagError: the file cannot be read, is not rosbag2 bag information, or lists an
            absolute path, a path through ``..`` or a name twice.
    """
    try:
        check_regular(meta)
        info = bounded_yaml.load_file(meta, max_bytes=MAX_METADATA_BYTES,
                                      what='bag metadata.yaml', allow_aliases=False)
        listed = info['rosbag2_bagfile_information']['relative_file_paths']
        if not isinstance(listed, list) or any(isinstance(rel, (list, dict)) for rel in listed):
            raise TypeError('relative_file_paths is not a list of file names')
        relative = [str(rel) for rel in listed]
    except bounded_yaml.YAMLLimitError as exc:
        raise BagError(str(exc)) from exc
    except OSError as exc:
        raise BagError(f'{meta}: cannot be read ({exc.strerror or exc})') from exc
    except (yaml.YAMLError, KeyError, TypeError, UnicodeDecodeError) as exc:
        why = ' '.join(str(exc).split())
        raise BagError(f'{meta}: not rosbag2 bag information ({type(exc).__name__}: '
                       f'{why})') from exc
    seen: set[str] = set()
    for rel in relative:
        shown = repr(rel[:200])
        if not rel or os.path.isabs(rel) or '..' in PurePath(rel).parts or '\0' in rel:
            raise BagError(f'{meta}: relative_file_paths: {shown} is not a file name inside the '
                           'bag directory')
        key = os.path.normpath(rel)
        if key in seen:
            raise BagError(f'{meta}: relative_file_paths: {shown} is listed twice')
        seen.add(key)
    return relative


def _refuse_same_file(files: list[Path], where: Path) -> None:
    """Refuse a bag that names one file twice (links, symlinks): its messages would count and
    play twice."""
    first: dict[tuple[int, int], Path] = {}
    for file in files:
        try:
            status = file.stat()
        except OSError as exc:
            raise BagError(f'{file}: cannot be examined ({exc.strerror or exc})') from exc
        key = (status.st_dev, status.st_ino)
        if key in first:
            raise BagError(f'{where}: {file.name} is the same file as {first[key].name}')
        first[key] = file


def bag_file_order(path: Path) -> tuple[int, str]:
    """Sort key of a bag's files: rosbag2's split index (``<name>_<i>.mcap``), then the name."""
    stem = path.stem
    tail = stem.rsplit('_', 1)[-1]
    return (int(tail) if tail.isdigit() else 0, stem)


def cut_short_error(scan: McapScan, bag: str | os.PathLike[str]) -> BagError:
    """The error for a file without its footer: where it ends and how to recover it."""
    return scan.error(f'cut short at byte {scan.readable_end} of {scan.size} ({scan.cut_short}); '
                      f'`rcbf_ros bag recover {bag}` rewrites it from its whole chunks')


def check_file(path: Path, *, allow_cut_short: bool, bag: str | os.PathLike[str]) -> McapScan:
    """Verify one MCAP file in full (see :class:`rcbf_ros.bag.scan.McapScan`).

    Raises:
        BagError: the file is damaged, or (unless ``allow_cut_short``) cut short.
    """
    scan = McapScan(path).verify()
    if not scan.complete and not allow_cut_short:
        raise cut_short_error(scan, bag)
    return scan


@dataclass
class _FileContents:
    schemas: dict[int, Schema]
    channels: dict[int, Channel]
    messages: list[Message]


def _read_whole_chunks(path: Path) -> _FileContents:
    """Schemas, channels and messages of a cut-short file, from its whole (checked) chunks."""
    contents = _FileContents({}, {}, [])
    for _, record in McapScan(path).records():
        if isinstance(record, Message):
            contents.messages.append(record)
        elif isinstance(record, Schema):
            contents.schemas[record.id] = record
        elif isinstance(record, Channel):
            contents.channels[record.id] = record
    contents.messages.sort(key=lambda m: m.log_time)
    return contents


def _decode_errors() -> tuple[type[BaseException], ...]:
    errors: list[type[BaseException]] = [McapError, ValueError, EOFError, struct.error, OSError]
    try:
        import zstandard
        errors.append(zstandard.ZstdError)
    except ImportError:
        pass
    return tuple(errors)


def _iter_file(scan: McapScan, topics: frozenset[str] | None) -> Iterator[BagMessage]:
    path = scan.path
    if not scan.complete:
        contents = _read_whole_chunks(path)
        for message in contents.messages:
            channel = contents.channels[message.channel_id]  # the scan checked it exists
            if topics is not None and channel.topic not in topics:
                continue
            schema = contents.schemas.get(channel.schema_id)
            yield BagMessage(channel.topic, schema.name if schema else '', message.data,
                             message.log_time, message.publish_time)
        return
    try:
        with open_regular(path) as stream:
            reader = make_reader(stream, validate_crcs=True)
            for schema, channel, message in reader.iter_messages(
                    topics=None if topics is None else list(topics), log_time_order=True):
                yield BagMessage(channel.topic, schema.name if schema else '', message.data,
                                 message.log_time, message.publish_time)
    except _decode_errors() as exc:  # the file changed after it was checked
        raise scan.error(f'{type(exc).__name__}: {exc}') from exc


def read_bag(path: str | os.PathLike[str], *, topics: Iterable[str] | None = None,
             allow_cut_short: bool = False) -> Iterator[BagMessage]:
    """Iterate a bag's messages in log-time order (across files too).

    Every file is checked in full before the first message is returned.

    Args:
        path: a bag directory or one ``.mcap`` file.
        topics: only these topic names (default: all).
        allow_cut_short: read the whole chunks of a file cut short (no footer) instead of
            refusing it.

    Raises:
        BagError: missing, empty, damaged or foreign files; a file cut short (unless allowed).
    """
    wanted = None if topics is None else frozenset(topics)
    scans = [check_file(f, allow_cut_short=allow_cut_short, bag=path) for f in mcap_files(path)]
    streams = [_iter_file(scan, wanted) for scan in scans]
    if len(streams) == 1:
        yield from streams[0]
    else:
        yield from heapq.merge(*streams, key=lambda m: m.log_time_ns)


def read_bag_messages(path: str | os.PathLike[str], *, topics: Iterable[str] | None = None,
                      allow_cut_short: bool = False) -> Iterator[tuple[BagMessage, Any]]:
    """Like :func:`read_bag`, with each message also decoded to a rosbags message object."""
    for item in read_bag(path, topics=topics, allow_cut_short=allow_cut_short):
        yield item, deserialize_rosbags_message(item.data, item.type_name)


@dataclass
class _FileCounts:
    schemas: dict[int, Schema]
    channels: dict[int, Channel]
    per_channel: dict[int, int]
    start_ns: int | None
    end_ns: int | None


def _count_file(scan: McapScan) -> _FileCounts:
    """Schemas, channels, messages per channel and time range of one checked file."""
    if scan.complete:
        with open_regular(scan.path) as stream:
            summary = make_reader(stream).get_summary()
        if summary is not None and summary.statistics is not None:
            stats = summary.statistics
            return _FileCounts(
                summary.schemas, summary.channels, dict(stats.channel_message_counts),
                stats.message_start_time if stats.message_count else None,
                stats.message_end_time if stats.message_count else None)
    counts = _FileCounts({}, {}, {}, None, None)  # counted as read: no message is kept
    for _, record in McapScan(scan.path).records():
        if isinstance(record, Message):
            counts.per_channel[record.channel_id] = counts.per_channel.get(record.channel_id,
                                                                           0) + 1
            t = record.log_time
            counts.start_ns = t if counts.start_ns is None else min(counts.start_ns, t)
            counts.end_ns = t if counts.end_ns is None else max(counts.end_ns, t)
        elif isinstance(record, Schema):
            counts.schemas[record.id] = record
        elif isinstance(record, Channel):
            counts.channels[record.id] = record
    return counts


def channel_qos(file: Path, channel: Channel) -> tuple[RecordedQos, ...]:
    """The offered QoS profiles a channel's metadata records.

    Raises:
        BagError: they cannot be read (naming the file and the topic).
    """
    try:
        return tuple(parse_offered_qos_profiles(channel.metadata.get('offered_qos_profiles',
                                                                     '')))
    except ValueError as exc:
        why = ' '.join(str(exc).split())
        raise BagError(f'{file}: channel {channel.topic!r}: {why}') from exc


def bag_info(path: str | os.PathLike[str], *, allow_cut_short: bool = True) -> BagInfo:
    """Topics, counts and time range of a bag, from its data.

    Every file is checked in full (as for :func:`read_bag`). A file cut short counts with its
    whole chunks and makes :attr:`BagInfo.complete` False (``allow_cut_short=False``: raise).

    Raises:
        BagError: missing, empty, damaged or foreign files; a file cut short (if not allowed).
    """
    files = mcap_files(path)
    counts: dict[str, int] = {}
    topic_meta: dict[str, tuple[str, tuple[RecordedQos, ...], str, str, str]] = {}
    encodings: dict[str, set[str]] = {}
    types: dict[str, set[str]] = {}
    start: int | None = None
    end: int | None = None
    total = 0
    complete = True
    for file in files:
        scan = check_file(file, allow_cut_short=allow_cut_short, bag=path)
        complete = complete and scan.complete
        one = _count_file(scan)
        if one.start_ns is not None:
            start = one.start_ns if start is None else min(start, one.start_ns)
        if one.end_ns is not None:
            end = one.end_ns if end is None else max(end, one.end_ns)
        for channel_id, channel in one.channels.items():
            schema = one.schemas.get(channel.schema_id)
            topic_meta.setdefault(channel.topic, (
                schema.name if schema else '',
                channel_qos(file, channel),
                channel.metadata.get('topic_type_hash', ''),
                schema.data.decode(errors='replace') if schema else '',
                schema.encoding if schema else ''))
            encodings.setdefault(channel.topic, set()).add(channel.message_encoding)
            types.setdefault(channel.topic, set()).add(schema.name if schema else '')
            n = one.per_channel.get(channel_id, 0)
            counts[channel.topic] = counts.get(channel.topic, 0) + n
            total += n
    topics = {name: TopicInfo(name, meta[0], counts.get(name, 0), meta[1], meta[2], meta[3],
                              meta[4], ', '.join(sorted(encodings[name])),
                              tuple(sorted(types[name] - {meta[0]})))
              for name, meta in topic_meta.items()}
    return BagInfo(tuple(files), topics, total, start or 0, end or 0, complete)
