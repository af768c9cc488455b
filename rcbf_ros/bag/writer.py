"""Write bags: MCAP files in the layout of rosbag2's MCAP storage plugin, plus ``metadata.yaml``.

rosbag2's MCAP layout, so ``ros2 bag``, Foxglove and rosbags read the bags. The file is written
unbuffered a whole chunk at a time and closed properly even after a failed write, so a kill
loses at most the open chunk and a full disk never leaves a torn record: docs/BAGS.md has the
format, the crash safety and the write-error rules.
"""
from __future__ import annotations

import ctypes
from dataclasses import dataclass, field, replace
import errno
from importlib.metadata import PackageNotFoundError, version
import os
from pathlib import Path
import signal
import struct
import threading
import time
from typing import Any, Iterable, Protocol, Sequence
import zlib

from mcap.data_stream import RecordBuilder
from mcap.opcode import Opcode
from mcap.records import (
    Channel,
    ChunkIndex,
    DataEnd,
    Footer,
    Metadata,
    MetadataIndex,
    Schema,
    Statistics,
    SummaryOffset,
)
from mcap.writer import CompressionType, IndexType, Writer
import yaml

from rcbf_ros.bag import scan
from rcbf_ros.bag.interrupts import held
from rcbf_ros.bag.qos import dump_offered_qos_profiles, offered_qos_sequence, RecordedQos
from rcbf_ros.messages.cdr import serialize_message
from rcbf_ros.messages.typestore import (
    jazzy_typestore,
    message_definition_text,
    normalize_type_name,
    type_hash_rihs01,
)

#: rosbag2 bag information format version written (Jazzy: QoS policies as names).
BAG_FORMAT_VERSION = 9
#: The message type store (and so definitions and hashes) these bags use.
ROS_DISTRO = 'jazzy'


def _library_identifier() -> str:
    try:
        ours = version('rcbf_ros')
    except PackageNotFoundError:
        ours = '0.1.0'
    try:
        theirs = version('mcap')
    except PackageNotFoundError:
        theirs = 'unknown'
    return f'rcbf_ros-{ours}; mcap-python-{theirs}'


_MAGIC = b'\x89MCAP0\r\n'
_RECORD_HEAD = struct.Struct('<BQ')  # opcode, content length
_SUMMARY_OFFSET_SIZE = _RECORD_HEAD.size + 1 + 8 + 8  # opcode, group start and length
_FOOTER_SIZE = _RECORD_HEAD.size + 8 + 8 + 4  # summary start, offsets start, CRC
_TOPIC_SLACK = 64
"""Bytes each topic's share of the closing bound carries beyond its own measure
(:meth:`BagWriter._share`): the YAML of a list of one entry differs from an empty list's."""
_CHUNK_HEAD = struct.Struct('<QQQII')  # start and end time, uncompressed size and CRC, len(str)
_MESSAGE_INDEX_HEAD = struct.Struct('<HI')  # channel id, bytes of (time, offset) entries
_MESSAGE_HEAD = struct.Struct('<HIQQ')  # channel id, sequence, log and publish time
MESSAGE_RECORD_OVERHEAD = _RECORD_HEAD.size + _MESSAGE_HEAD.size
"""Bytes a message record adds to a chunk besides the message's own (31)."""


def max_chunk_bytes() -> int:
    """The most uncompressed bytes a chunk written here may hold: the reader's limit
    (:data:`rcbf_ros.bag.scan.MAX_CHUNK_BYTES`), read when asked, so the two never differ.

    A chunk within it is also a record within the reader's ``MAX_RECORD_BYTES`` once
    compressed: zstd and lz4 add at most about 1/255 to data they cannot compress, the
    record's limit 1/16."""
    return scan.MAX_CHUNK_BYTES


class MessageTooLargeError(ValueError):
    """A message that no chunk can hold (see :func:`max_chunk_bytes`): it is left out, the
    bag is unchanged and stays open. The text is one line naming the topic and the size."""


class BagWriteError(OSError):
    """Writing a bag file failed: disk full, file size limit, I/O error (``errno`` says which).

    Raised by the call that met the error, once the bag is closed as well as it could be (see
    the module docstring), and again by every later call but ``close()``. Its text is one line
    naming the file, the error and what the bag holds.
    """

    def __init__(self, code: int, line: str) -> None:
        super().__init__(code, line)

    def __str__(self) -> str:
        return str(self.strerror)


def _error_text(exc: OSError) -> str:
    """``ENOSPC: No space left on device`` (the code's name, then the OS's words)."""
    name = errno.errorcode.get(exc.errno or 0, 'error')
    return f'{name}: {exc.strerror or exc}'


def _file_size_limit() -> int | None:
    """The process's file size limit (``RLIMIT_FSIZE`` soft limit, bytes); None if unlimited."""
    try:
        import resource
    except ImportError:  # not POSIX
        return None
    soft = resource.getrlimit(resource.RLIMIT_FSIZE)[0]
    return None if soft == resource.RLIM_INFINITY or soft < 0 else soft


def _ignore_file_size_signal() -> None:
    """Make a write past ``RLIMIT_FSIZE`` fail with ``EFBIG`` instead of killing the process
    (``SIGXFSZ``'s default). CPython ignores the signal from the start; a program that embeds
    it, or set the default back, may not."""
    sigxfsz = getattr(signal, 'SIGXFSZ', None)
    if (sigxfsz is not None and threading.current_thread() is threading.main_thread()
            and signal.getsignal(sigxfsz) == signal.SIG_DFL):
        signal.signal(sigxfsz, signal.SIG_IGN)


_RESERVE_MARGIN = 8 * 1024
"""Bytes held beyond twice the closing records' size: metadata.yaml and file-system overhead."""
_FALLOC_FL_KEEP_SIZE = 1  # linux/falloc.h


def _fallocate_keep_size() -> Any:
    """Linux ``fallocate(fd, FALLOC_FL_KEEP_SIZE, offset, len)`` through ctypes; None where the
    C library has none (blocks are then not held ahead, see :meth:`_BagFile.reserve`)."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        function = getattr(libc, 'fallocate64', None) or libc.fallocate
    except (OSError, AttributeError):
        return None
    function.argtypes = [ctypes.c_int, ctypes.c_int, ctypes.c_int64, ctypes.c_int64]
    function.restype = ctypes.c_int
    return function


class _MemorySink:
    """The stream the mcap writer writes to: memory, handed to the file by :meth:`take`.

    :meth:`tell` is the file offset that the next byte will have once taken, so the offsets
    the mcap writer puts in its records are file offsets.
    """

    def __init__(self) -> None:
        self._pending = bytearray()
        self._taken = 0

    def write(self, data: bytes | bytearray | memoryview) -> int:
        self._pending += data
        return len(data)

    def tell(self) -> int:
        return self._taken + len(self._pending)

    def flush(self) -> None:
        """Nothing to do: :meth:`take` hands the bytes on."""

    def take(self) -> bytes:
        """Everything written since the last call (whole records)."""
        data = bytes(self._pending)
        self._pending.clear()
        self._taken += len(data)
        return data


@dataclass
class _Contents:
    """What the file holds up to :attr:`end`: the state its closing records describe."""

    end: int = 0
    """Offset just past the last whole piece written."""
    data_crc: int = 0
    """CRC-32 of the bytes before :attr:`end` (the data section's CRC)."""
    chunk_indexes: list[bytes] = field(default_factory=list)
    """One serialized chunk index record per chunk, in file order: the first
    :attr:`chunk_count` (the list is shared with the contents that follow)."""
    chunk_count: int = 0
    """Chunks in the file."""
    chunk_index_size: int = 0
    """Bytes of their chunk index records."""
    channel_counts: dict[int, int] = field(default_factory=dict)
    """Messages per channel id."""
    start_ns: int | None = None
    """Earliest message log time."""
    end_ns: int | None = None
    """Latest message log time."""

    @property
    def message_count(self) -> int:
        return sum(self.channel_counts.values())

    def plus(self, piece: bytes) -> _Contents:
        """The contents once ``piece`` (whole records) is written after :attr:`end`."""
        del self.chunk_indexes[self.chunk_count:]  # those of a piece never written
        after = _Contents(end=self.end + len(piece), data_crc=zlib.crc32(piece, self.data_crc),
                          chunk_indexes=self.chunk_indexes, chunk_count=self.chunk_count,
                          chunk_index_size=self.chunk_index_size,
                          channel_counts=dict(self.channel_counts),
                          start_ns=self.start_ns, end_ns=self.end_ns)
        view = memoryview(piece)
        chunk: ChunkIndex | None = None
        pos = len(_MAGIC) if self.end == 0 else 0  # the first piece opens with the magic
        while pos < len(view):
            opcode, length = _RECORD_HEAD.unpack_from(view, pos)
            body = pos + _RECORD_HEAD.size
            if opcode == Opcode.CHUNK:
                after._add_chunk_index(chunk)
                start, stop, size, _, name_length = _CHUNK_HEAD.unpack_from(view, body)
                name_at = body + _CHUNK_HEAD.size
                compression = bytes(view[name_at:name_at + name_length]).decode()
                (compressed,) = struct.unpack_from('<Q', view, name_at + name_length)
                chunk = ChunkIndex(
                    message_start_time=start, message_end_time=stop,
                    chunk_start_offset=self.end + pos, chunk_length=_RECORD_HEAD.size + length,
                    message_index_offsets={}, message_index_length=0, compression=compression,
                    compressed_size=compressed, uncompressed_size=size)
            elif opcode == Opcode.MESSAGE_INDEX and chunk is not None:
                channel_id, entries = _MESSAGE_INDEX_HEAD.unpack_from(view, body)
                chunk.message_index_offsets[channel_id] = self.end + pos
                chunk.message_index_length += _RECORD_HEAD.size + length
                count = entries // 16
                if count:
                    after.channel_counts[channel_id] = (
                        after.channel_counts.get(channel_id, 0) + count)
                    after._add_times(chunk.message_start_time, chunk.message_end_time)
            else:
                after._add_chunk_index(chunk)
                chunk = None
            pos = body + length
        after._add_chunk_index(chunk)
        return after

    def _add_chunk_index(self, chunk: ChunkIndex | None) -> None:
        if chunk is not None:
            record = _record_bytes(chunk)
            self.chunk_indexes.append(record)
            self.chunk_count += 1
            self.chunk_index_size += len(record)

    def _add_times(self, start: int, end: int) -> None:
        self.start_ns = start if self.start_ns is None else min(self.start_ns, start)
        self.end_ns = end if self.end_ns is None else max(self.end_ns, end)


class _BagFile:
    """The MCAP file: written unbuffered, one whole piece at a time, at known offsets."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self._fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)  # never clobber
        self.contents = _Contents()
        """What the file holds (up to its last whole piece)."""
        self._fallocate = _fallocate_keep_size()

    def reserve(self, length: int) -> None:
        """Hold disk blocks for ``length`` bytes after the contents, the file's size unchanged,
        so that they can be written when the disk is full (``FALLOC_FL_KEEP_SIZE``). Where the
        file system cannot, nothing is held (closing on a full disk may then fail).

        Raises:
            OSError: no room for them (``ENOSPC``), or an I/O error.
        """
        code = errno.EINTR
        while code == errno.EINTR:  # a signal during the call (ctypes does not retry it)
            if self._fallocate is None:
                return
            if self._fallocate(self._fd, _FALLOC_FL_KEEP_SIZE, self.contents.end, length) == 0:
                return
            code = ctypes.get_errno()
        if code in (errno.EOPNOTSUPP, errno.ENOSYS, errno.EINVAL, errno.ENODEV):
            self._fallocate = None  # not on this file system
            return
        raise OSError(code, os.strerror(code))

    def fileno(self) -> int:
        return self._fd

    def _write_at(self, offset: int, data: bytes) -> None:
        view = memoryview(data)
        while view:
            written = os.pwrite(self._fd, view, offset)
            view, offset = view[written:], offset + written

    def append(self, piece: bytes, after: _Contents) -> None:
        """Write ``piece`` after the contents; ``after`` is ``contents.plus(piece)``.

        Raises:
            OSError: the write failed; :attr:`contents` is unchanged (the file may hold part
                of the piece after it: :meth:`truncate` removes it).
        """
        self._write_at(self.contents.end, piece)
        self.contents = after

    def truncate(self, length: int = 0) -> None:
        """Cut the file ``length`` bytes after its contents, dropping a piece written in part
        and the blocks held beyond (raises OSError)."""
        os.ftruncate(self._fd, self.contents.end + length)

    def write_closing(self, closing: bytes) -> None:
        """Write the closing records after the contents, over a piece written in part, and end
        the file with them (raises OSError, see :meth:`append`)."""
        self._write_at(self.contents.end, closing)
        self.truncate(len(closing))

    def close(self) -> None:
        if self._fd >= 0:
            os.close(self._fd)
            self._fd = -1

    def __del__(self) -> None:
        self.close()  # an abandoned writer: release the descriptor and its lock


def _lock_exclusive(fd: int) -> None:
    """Hold an exclusive ``flock`` on the open file (released when it closes or the process
    dies); recovery asks for a shared one and so never rewrites a file being written."""
    try:
        import fcntl
    except ImportError:  # not POSIX: no lock
        return
    fcntl.flock(fd, fcntl.LOCK_EX)


def best_compression() -> CompressionType:
    """zstd if importable, else lz4, else none."""
    try:
        import zstandard  # noqa: F401
        return CompressionType.ZSTD
    except ImportError:
        pass
    try:
        import lz4.frame  # noqa: F401
        return CompressionType.LZ4
    except ImportError:
        return CompressionType.NONE


@dataclass(frozen=True)
class BagWriterConfig:
    """How a :class:`BagWriter` lays out and flushes its MCAP file."""

    chunk_size: int = 256 * 1024
    """Uncompressed bytes after which a chunk is closed and written (smaller: less lost on a
    crash, worse compression); at most :func:`max_chunk_bytes`. A chunk is also closed before a
    message would take it past that limit."""
    compression: str = 'auto'
    """``auto`` (zstd, else lz4, else none), ``zstd``, ``lz4`` or ``none``."""
    flush_period_s: float = 0.5
    """A ``write()`` flushes the open chunk when the last flush is older than this (seconds);
    ``0`` flushes on every write."""
    fsync: bool = False
    """Also ``os.fsync`` on every flush (survives power loss, costs a disk sync)."""

    def __post_init__(self) -> None:
        if self.chunk_size <= 0:
            raise ValueError(f'BagWriterConfig.chunk_size must be > 0, got {self.chunk_size}')
        if self.chunk_size > max_chunk_bytes():
            raise ValueError(f'BagWriterConfig.chunk_size must be <= {max_chunk_bytes()} (the '
                             f'largest chunk the reader accepts), got {self.chunk_size}')
        if self.compression not in ('auto', 'zstd', 'lz4', 'none'):
            raise ValueError("BagWriterConfig.compression must be 'auto', 'zstd', 'lz4' or "
                             f"'none', got {self.compression!r}")
        if self.flush_period_s < 0:
            raise ValueError('BagWriterConfig.flush_period_s must be >= 0')

    def compression_type(self) -> CompressionType:
        """The mcap library's compression enum for :attr:`compression`."""
        return {'auto': best_compression(), 'zstd': CompressionType.ZSTD,
                'lz4': CompressionType.LZ4, 'none': CompressionType.NONE}[self.compression]


@dataclass
class TopicRecord:
    """A topic registered in a bag and what has been written on it."""

    name: str
    type_name: str
    channel_id: int
    offered_qos: tuple[RecordedQos, ...]
    type_hash: str
    message_count: int = 0
    serialization_format: str = 'cdr'


@dataclass
class _Times:
    start_ns: int | None = None
    end_ns: int | None = None
    count: int = 0

    def add(self, t_ns: int) -> None:
        self.start_ns = t_ns if self.start_ns is None else min(self.start_ns, t_ns)
        self.end_ns = t_ns if self.end_ns is None else max(self.end_ns, t_ns)
        self.count += 1


class BagWriter:
    """Write a rosbag2-layout MCAP bag directory.

    Usage::

        with BagWriter('bags/run1') as bag:
            bag.add_topic('/state', 'std_msgs/msg/Float64MultiArray')
            bag.write_message('/state', {'data': [0.0, 1.0]}, t_ns)
            bag.write('/state', cdr_bytes, t_ns)

    Args:
        directory: the bag directory; created, and must not already contain a bag.
        name: file stem; the data goes to ``<directory>/<name>_0.mcap`` (default: the
            directory's name, as rosbag2 does).
        config: chunking, compression and flushing (see :class:`BagWriterConfig`).
    """

    def __init__(self, directory: str | os.PathLike[str], *, name: str | None = None,
                 config: BagWriterConfig = BagWriterConfig()) -> None:
        self.directory = Path(directory)
        stem = name if name is not None else self.directory.resolve().name
        if not stem or '/' in stem:
            raise ValueError(f'name {stem!r} is not a valid bag file stem')
        if (self.directory / 'metadata.yaml').exists():
            raise FileExistsError(f'directory {str(self.directory)!r} already holds a bag '
                                  '(metadata.yaml exists)')
        self.directory.mkdir(parents=True, exist_ok=True)
        self.mcap_path = self.directory / f'{stem}_0.mcap'
        if self.mcap_path.exists():
            raise FileExistsError(f'{str(self.mcap_path)!r} already exists')
        self.config = config
        self.topics: dict[str, TopicRecord] = {}
        self._schema_ids: dict[str, int] = {}
        self._typestore = jazzy_typestore()
        self._times = _Times()
        self._summary_records: list[tuple[Opcode, bytes]] = []  # schemas and channels
        self._error: BagWriteError | None = None
        self._closed = False
        # see _closing_bound: the bound without topics, what the registered topics add to it,
        # and the latest topic's own share
        self._base_bound: tuple[int, int] | None = None
        self._topics_bound = [0, 0]
        self._topic_share: tuple[TopicRecord | None, tuple[int, int]] = (None, (0, 0))
        _ignore_file_size_signal()
        self._file = _BagFile(self.mcap_path)
        _lock_exclusive(self._file.fileno())
        self._sink = _MemorySink()
        self._writer = new_mcap_writer(self._sink, config)
        self._chunk = ChunkFill(self._writer, config.chunk_size)
        self._writer.start(profile='ros2', library=_library_identifier())
        self._write_out()
        self._last_flush = time.monotonic()

    # -- topics ---------------------------------------------------------------------------

    def add_topic(self, name: str, type_name: str,
                  qos: RecordedQos | Sequence[RecordedQos] | None = None, *,
                  message_definition: str | None = None, type_hash: str | None = None,
                  ) -> TopicRecord:
        """Register topic ``name`` of ``type_name`` (a schema and a channel in the MCAP file).

        Args:
            name: absolute topic name, e.g. ``/state``.
            type_name: ``pkg/msg/Type`` (``pkg/Type`` is accepted and normalised).
            qos: the profile(s) the publishers offered (default: one default profile).
            message_definition: full ``ros2msg`` definition text, for types outside the Jazzy
                type store (then ``type_hash`` too); default: generated from the store.
            type_hash: ``RIHS01_...`` for such types.

        Returns:
            The topic's record. Registering the same name again with the same type returns
            the existing record; with another type raises ValueError.
        """
        with held:  # a signal meanwhile waits for the end (see interrupts)
            self._check_open()
            if not name.startswith('/') or name.endswith('/') and name != '/':
                raise ValueError(f'topic name {name!r} must be absolute (start with /)')
            type_name = normalize_type_name(type_name)
            if name in self.topics:
                existing = self.topics[name]
                if existing.type_name != type_name:
                    raise ValueError(f'topic {name!r} is already registered with type '
                                     f'{existing.type_name}, not {type_name}')
                return existing
            if message_definition is None:
                message_definition = message_definition_text(type_name, self._typestore)
                type_hash = type_hash_rihs01(type_name, self._typestore)
            elif type_hash is None:
                type_hash = ''
            if qos is None:
                profiles: tuple[RecordedQos, ...] = (RecordedQos(),)
            elif isinstance(qos, RecordedQos):
                profiles = (qos,)
            else:
                profiles = tuple(qos)
                if not all(isinstance(p, RecordedQos) for p in profiles):
                    raise TypeError('qos must be a RecordedQos or a sequence of them')
            schema_id = self._schema_ids.get(type_name)
            new_schema = schema_id is None
            if schema_id is None:
                schema_id = len(self._schema_ids) + 1
            schema = Schema(id=schema_id, name=type_name, encoding='ros2msg',
                            data=message_definition.encode())
            metadata = {'offered_qos_profiles': dump_offered_qos_profiles(profiles),
                        'topic_type_hash': type_hash}
            channel = Channel(id=len(self.topics) + 1, topic=name, message_encoding='cdr',
                              schema_id=schema_id, metadata=metadata)
            record = TopicRecord(name=name, type_name=type_name, channel_id=channel.id,
                                 offered_qos=profiles, type_hash=type_hash)
            added = ([(Opcode.SCHEMA, _record_bytes(schema))] if new_schema else []) + [
                (Opcode.CHANNEL, _record_bytes(channel))]
            # The schema and channel go into the open chunk as well: it must hold them.
            size = sum(len(data) for _, data in added)
            if not self._chunk.room(size):
                raise ValueError(f'topic {name}: its schema and channel records ({size} bytes) '
                                 f'do not fit a chunk of at most {max_chunk_bytes()} bytes')
            self._write_out()  # the chunk closed to make room, if any
            # The closing records list every topic: check that they still fit, then register.
            self._check_room(b'', self._file.contents, extra_topic=(record, added))
            if new_schema:
                self._schema_ids[type_name] = self._writer.register_schema(
                    name=schema.name, encoding=schema.encoding, data=schema.data)
                self._chunk.added(len(added[0][1]), message=False)
            self._writer.register_channel(topic=name, message_encoding=channel.message_encoding,
                                          schema_id=schema_id, metadata=channel.metadata)
            self._chunk.added(len(added[-1][1]), message=False)
            self._summary_records += added
            self.topics[name] = record
            share = self._share(record, added)
            self._topics_bound[0] += share[0]
            self._topics_bound[1] += share[1]
            return record

    # -- messages -------------------------------------------------------------------------

    def write(self, topic: str, cdr_bytes: bytes | bytearray | memoryview, log_time_ns: int,
              publish_time_ns: int | None = None) -> None:
        """Append one serialised message.

        Args:
            topic: a name registered with :meth:`add_topic`.
            cdr_bytes: CDR with its 4-byte encapsulation header, as received from DDS.
            log_time_ns: receive time, nanoseconds since the epoch (the bag's time axis).
            publish_time_ns: send time (default: ``log_time_ns``).

        Raises:
            MessageTooLargeError: no chunk can hold the message (:func:`max_chunk_bytes`); it
                is left out and the bag goes on.
            ValueError: not CDR, or a negative time.
            BagWriteError: the write failed; the bag is closed (see the module docstring).
        """
        with held:  # a signal meanwhile waits for the end (see interrupts)
            self._check_open()
            record = self.topics.get(topic)
            if record is None:
                raise KeyError(f'topic {topic!r} is not registered in this bag (call add_topic)')
            data = bytes(cdr_bytes)
            if len(data) < 4 or data[0] != 0 or data[1] not in (0, 1, 2, 3, 6, 7, 8, 9, 10, 11):
                raise ValueError(f'cdr_bytes for topic {topic!r} do not start with a CDR '
                                 f'encapsulation header (got {data[:4]!r})')
            log_time_ns = int(log_time_ns)
            if log_time_ns < 0:
                raise ValueError(f'log_time_ns must be >= 0, got {log_time_ns}')
            self._chunk.add_message(
                channel_id=record.channel_id, log_time=log_time_ns, data=data,
                publish_time=log_time_ns if publish_time_ns is None else int(publish_time_ns),
                sequence=record.message_count & 0xFFFFFFFF, topic=topic)
            record.message_count += 1
            self._write_out()  # a chunk, if this message filled one
            self._times.add(log_time_ns)
            if time.monotonic() - self._last_flush >= self.config.flush_period_s:
                self.flush()

    def write_message(self, topic: str, message: Any, log_time_ns: int,
                      publish_time_ns: int | None = None) -> None:
        """Serialise ``message`` (rosbags object, dict, or rclpy-like object) and :meth:`write`.

        The topic must be registered; the message is serialised as the topic's type.
        """
        record = self.topics.get(topic)
        if record is None:
            raise KeyError(f'topic {topic!r} is not registered in this bag (call add_topic)')
        self.write(topic, serialize_message(message, record.type_name, self._typestore),
                   log_time_ns, publish_time_ns)

    def flush(self) -> None:
        """Close the open chunk and hand everything written so far to the OS (see module doc).

        Raises:
            BagWriteError: the write failed; the bag is closed (see the module docstring).
        """
        with held:  # a signal meanwhile waits for the end (see interrupts)
            self._check_open()
            self._writer.flush()
            self._chunk.closed()
            self._write_out()
            if self.config.fsync:
                self._fsync()
            self._last_flush = time.monotonic()

    # -- closing --------------------------------------------------------------------------

    @property
    def message_count(self) -> int:
        """Messages written so far, all topics (after a write error: those the file holds)."""
        return self._times.count

    def bag_metadata(self) -> dict[str, Any]:
        """rosbag2 bag information (``rosbag2_bagfile_information`` contents) as of now."""
        return bag_information(
            files=[FileSpan(self.mcap_path.name, self._times.start_ns or 0,
                            self._times.end_ns or 0, self._times.count)],
            topics=self.topics.values())

    def close(self) -> None:
        """Write the ``rosbag2`` metadata record, the summary and footer, then metadata.yaml.

        Idempotent; after a :class:`BagWriteError` (the bag is closed then) it does nothing.

        Raises:
            BagWriteError: a write failed; the bag is closed as the module docstring says.
        """
        with held:  # a signal meanwhile waits for the end (see interrupts)
            if self._closed:
                return
            self._writer.flush()  # last chunk first: the metadata record then follows all data
            self._chunk.closed()
            self._write_out()
            contents = self._file.contents
            try:
                self._file.write_closing(self._closing(contents))
                if self.config.fsync:
                    os.fsync(self._file.fileno())
            except OSError as exc:
                raise self._stop(exc) from None
            self._file.close()
            self._closed = True
            try:
                write_metadata_yaml(self.directory, self._information(contents))
            except OSError as exc:
                self._error = BagWriteError(exc.errno or errno.EIO, (
                    f'cannot write {self.directory / "metadata.yaml"} ({_error_text(exc)}); '
                    f'{self.mcap_path} is complete'))
                raise self._error from None

    # -- writing out ----------------------------------------------------------------------

    def _write_out(self) -> None:
        """Hand what the mcap writer produced (whole records) to the file, or stop the bag."""
        piece = self._sink.take()
        if not piece:
            return
        before = self._file.contents
        after = before.plus(piece)
        self._check_room(piece, after)
        try:
            self._file.append(piece, after)
        except OSError as exc:
            raise self._stop(exc) from None

    def _fsync(self) -> None:
        try:
            os.fsync(self._file.fileno())
        except OSError as exc:
            raise self._stop(exc) from None

    def _check_room(self, piece: bytes, after: _Contents, *,
                    extra_topic: tuple[TopicRecord, list[tuple[Opcode, bytes]]] | None = None,
                    ) -> None:
        """Make sure that the closing records will fit after ``piece`` (or a new topic), or
        stop the bag now, while the present ones still fit.

        Under a file size limit the piece and its closing must stay within it. On disk, the
        blocks for the piece and its closing are held before the piece is written
        (:meth:`_BagFile.reserve`): a full disk then fails the reservation, not the piece,
        and the blocks held for the present closing records are still there.
        """
        closing, yaml_size = self._closing_bound(after, extra_topic=extra_topic)
        limit = _file_size_limit()
        if limit is not None and (after.end + closing > limit or yaml_size > limit):
            what = (f'{len(piece)} more bytes' if piece else
                    f'topic {extra_topic[0].name}' if extra_topic else 'the closing records')
            raise self._stop(OSError(errno.EFBIG, (
                f'{os.strerror(errno.EFBIG)}: {what} and the closing records would pass the '
                f'file size limit (RLIMIT_FSIZE) of {limit} bytes')))
        try:
            self._file.reserve(len(piece) + 2 * closing + _RESERVE_MARGIN)
        except OSError as exc:
            raise self._stop(exc) from None

    def _information(self, contents: _Contents,
                     extra: TopicRecord | None = None) -> dict[str, Any]:
        """The bag information of a file holding ``contents``."""
        topics = [replace(t, message_count=contents.channel_counts.get(t.channel_id, 0))
                  for t in (*self.topics.values(), *([extra] if extra else []))]
        return bag_information(
            files=[FileSpan(self.mcap_path.name, contents.start_ns or 0, contents.end_ns or 0,
                            contents.message_count)],
            topics=topics)

    def _closing(self, contents: _Contents, *,
                 extra_topic: tuple[TopicRecord, list[tuple[Opcode, bytes]]] | None = None,
                 ) -> bytes:
        """The records that close a file holding ``contents``: the ``rosbag2`` metadata
        record, data end, summary (schemas, channels, statistics, chunk and metadata indexes,
        summary offsets), footer and magic, laid out as the mcap writer's ``finish()``."""
        head, groups = self._closing_parts(contents, extra_topic)
        summary_start = contents.end + len(head)
        summary = bytearray()
        offsets = bytearray()
        for opcode, group in groups:
            if opcode == Opcode.CHUNK_INDEX:
                group = b''.join(contents.chunk_indexes[:contents.chunk_count])
            if group:  # no offset to an empty group (``pymcap-cli doctor`` flags one)
                offsets += _record_bytes(SummaryOffset(
                    group_opcode=opcode, group_start=summary_start + len(summary),
                    group_length=len(group)))
                summary += group
        summary_offset_start = summary_start + len(summary)
        summary += offsets
        footer_fields = struct.pack('<QQ', summary_start, summary_offset_start)
        summary_crc = zlib.crc32(_RECORD_HEAD.pack(Opcode.FOOTER, 20) + footer_fields,
                                 zlib.crc32(summary))
        footer = _record_bytes(Footer(summary_start=summary_start,
                                      summary_offset_start=summary_offset_start,
                                      summary_crc=summary_crc))
        return head + bytes(summary) + footer + _MAGIC

    def _closing_bound(self, contents: _Contents, *,
                       extra_topic: tuple[TopicRecord, list[tuple[Opcode, bytes]]] | None = None,
                       ) -> tuple[int, int]:
        """Upper bounds of ``len(self._closing(contents))`` and of metadata.yaml's size, checked
        before every chunk: without writing the bag information as YAML each time (~30 ms for
        a few topics) nor joining the chunk indexes (thousands in a long recording). Counts and
        times are taken as 20 digits wide, the most a 64-bit number has.

        The bound is the bound of a bag without topics plus each topic's share
        (:meth:`_share`), kept as running sums: registering a topic costs the same whatever
        the bag already holds (recomputing the whole bound per topic made a bag of N topics
        cost N^2 YAML dumps: minutes at a thousand)."""
        if self._base_bound is None:
            self._base_bound = self._bound_of([], [])
        fixed, yaml_size = (self._base_bound[0] + self._topics_bound[0],
                            self._base_bound[1] + self._topics_bound[1])
        if extra_topic is not None:
            share = self._share(*extra_topic)
            fixed, yaml_size = fixed + share[0], yaml_size + share[1]
        return fixed + contents.chunk_index_size, yaml_size

    def _share(self, record: TopicRecord, added: list[tuple[Opcode, bytes]]
               ) -> tuple[int, int]:
        """What one topic adds at most to the closing records and to metadata.yaml: the bound
        of a bag holding it alone less the bound without topics, plus
        :data:`_TOPIC_SLACK` (a list of one entry is written otherwise than an empty one).
        Each topic's information, schema and channel records are written apart from the
        others' (YAML anchors only shorten a repeat), so the shares' sum bounds the whole;
        a schema shared by several topics is counted for each."""
        if self._topic_share[0] is not record:
            assert self._base_bound is not None
            fixed, yaml_size = self._bound_of([record], added)
            self._topic_share = (record, (fixed - self._base_bound[0] + _TOPIC_SLACK,
                                          yaml_size - self._base_bound[1] + _TOPIC_SLACK))
        return self._topic_share[1]

    def _bound_of(self, topics: list[TopicRecord], records: list[tuple[Opcode, bytes]]
                  ) -> tuple[int, int]:
        """(the closing records' size, metadata.yaml's) of an empty file holding ``topics``
        (their schema and channel ``records``), counts and times 20 digits wide."""
        widest = _widest_counts(bag_information(
            files=[FileSpan(self.mcap_path.name, 0, 0, 0)],
            topics=[replace(t, message_count=0) for t in topics]))
        head, groups = self._closing_parts_of(_Contents(), widest, records)
        fixed = (len(head) + sum(len(group) for _, group in groups)
                 + 10 * len(topics)  # statistics: a count per channel
                 + len(groups) * _SUMMARY_OFFSET_SIZE + _FOOTER_SIZE + len(_MAGIC))
        return fixed, len(_metadata_yaml_text(widest))

    def _closing_parts(self, contents: _Contents,
                       extra_topic: tuple[TopicRecord, list[tuple[Opcode, bytes]]] | None, *,
                       info: dict[str, Any] | None = None,
                       ) -> tuple[bytes, list[tuple[Opcode, bytes]]]:
        """The ``rosbag2`` metadata record (of ``info``, default: the contents' information)
        and data end; the summary's groups in order (the chunk indexes' left empty:
        :meth:`_closing` joins them)."""
        if info is None:
            info = self._information(contents, extra_topic[0] if extra_topic else None)
        return self._closing_parts_of(
            contents, info, self._summary_records + (extra_topic[1] if extra_topic else []))

    @staticmethod
    def _closing_parts_of(contents: _Contents, info: dict[str, Any],
                          records: list[tuple[Opcode, bytes]]
                          ) -> tuple[bytes, list[tuple[Opcode, bytes]]]:
        """:meth:`_closing_parts` of the bag information ``info`` and the schema and channel
        ``records``."""
        metadata = _record_bytes(Metadata(name='rosbag2', metadata={
            'serialized_metadata': yaml.safe_dump(info, sort_keys=False).rstrip('\n')}))
        data_end = _record_bytes(DataEnd(zlib.crc32(metadata, contents.data_crc)))
        statistics = _record_bytes(Statistics(
            message_count=contents.message_count,
            schema_count=sum(opcode == Opcode.SCHEMA for opcode, _ in records),
            channel_count=sum(opcode == Opcode.CHANNEL for opcode, _ in records),
            attachment_count=0, metadata_count=1, chunk_count=contents.chunk_count,
            message_start_time=contents.start_ns or 0, message_end_time=contents.end_ns or 0,
            channel_message_counts=dict(sorted(contents.channel_counts.items()))))
        metadata_index = _record_bytes(MetadataIndex(
            offset=contents.end, length=len(metadata), name='rosbag2'))
        return metadata + data_end, [
            (Opcode.SCHEMA, b''.join(data for op, data in records if op == Opcode.SCHEMA)),
            (Opcode.CHANNEL, b''.join(data for op, data in records if op == Opcode.CHANNEL)),
            (Opcode.STATISTICS, statistics),
            (Opcode.CHUNK_INDEX, b''),
            (Opcode.METADATA_INDEX, metadata_index)]

    def _stop(self, error: OSError) -> BagWriteError:
        """Close the bag after a failed write (see the module docstring); the error to raise."""
        if self._error is not None:
            return self._error
        contents = self._file.contents
        self._closed = True
        self._times = _Times(contents.start_ns, contents.end_ns, contents.message_count)
        for topic in self.topics.values():
            topic.message_count = contents.channel_counts.get(topic.channel_id, 0)
        failed = f'cannot write {self.mcap_path} ({_error_text(error)})'
        if contents.end == 0:  # not even the header: no bag
            self._file.close()
            try:
                self.mcap_path.unlink()
            except OSError:
                pass
            self._error = BagWriteError(error.errno or errno.EIO, f'{failed}: no bag written')
            return self._error
        closed = True
        try:
            self._file.write_closing(self._closing(contents))
            if self.config.fsync:
                os.fsync(self._file.fileno())
        except OSError:
            closed = False
            try:
                self._file.truncate()  # back to the last whole chunk, as after a kill
            except OSError:
                pass
        self._file.close()
        n = contents.message_count
        if not closed:
            line = (f'{failed}: the file ends with the {n} messages of its whole chunks; '
                    f"'rcbf_ros bag recover {self.directory}' closes it")
        else:
            line = f'{failed}: bag closed with the {n} messages written before the error'
            try:
                write_metadata_yaml(self.directory, self._information(contents))
            except OSError as exc:
                line += f'; {self.directory / "metadata.yaml"} not written ({_error_text(exc)})'
        self._error = BagWriteError(error.errno or errno.EIO, line)
        return self._error

    def _check_open(self) -> None:
        if self._error is not None:
            raise self._error
        if self._closed:
            raise RuntimeError(f'bag {str(self.directory)!r} is closed')

    def __enter__(self) -> BagWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


_COUNT_KEYS = ('message_count', 'nanoseconds', 'nanoseconds_since_epoch')


def _widest_counts(info: Any) -> Any:
    """``info`` with every count and time 20 digits wide (for a size bound)."""
    if isinstance(info, dict):
        return {key: 10**19 if key in _COUNT_KEYS else _widest_counts(value)
                for key, value in info.items()}
    if isinstance(info, list):
        return [_widest_counts(value) for value in info]
    return info


def _record_bytes(record: Any) -> bytes:
    """One MCAP record (a :mod:`mcap.records` object) serialized."""
    builder = RecordBuilder()
    record.write(builder)
    return builder.end()


class ChunkFill:
    """The open chunk of an mcap ``Writer``, counted as its chunk builder counts it, so that no
    record takes a chunk past :func:`max_chunk_bytes` (the reader refuses such a chunk).

    The mcap writer closes a chunk only once it has passed ``chunk_size``, so a chunk would hold
    ``chunk_size`` plus a whole message; here the chunk is closed first when the next record
    would not fit. Schemas and channels go into the open chunk too and stay there until a
    message closes it with them.

    Args:
        writer: the mcap writer, chunked, every record of which goes through this object.
        chunk_size: the writer's ``chunk_size``.
    """

    def __init__(self, writer: Writer, chunk_size: int) -> None:
        self._writer = writer
        self._chunk_size = chunk_size
        self._limit = max_chunk_bytes()
        self.size = 0
        """Uncompressed bytes of the open chunk."""
        self.messages = 0
        """Messages in the open chunk."""

    def room(self, size: int) -> bool:
        """Make room for a record of ``size`` bytes: close the open chunk if the record would
        take it past the limit. False if the record cannot fit in any chunk (nothing changed)."""
        if self.size + size <= self._limit:
            return True
        if not self.messages or size > self._limit:
            return False  # a chunk without messages is never closed: its records stay
        self._writer.flush()
        self.closed()
        return True

    def added(self, size: int, *, message: bool) -> None:
        """A record of ``size`` bytes went into the open chunk (the mcap writer then closes the
        chunk once past ``chunk_size``, if it holds a message)."""
        self.size += size
        self.messages += message
        if self.messages and self.size > self._chunk_size:
            self.closed()

    def closed(self) -> None:
        """The mcap writer was flushed: a chunk with messages is closed (one without stays)."""
        if self.messages:
            self.size = self.messages = 0

    def add_message(self, *, channel_id: int, log_time: int, data: bytes, publish_time: int,
                    sequence: int, topic: str) -> None:
        """``writer.add_message`` of a message that fits a chunk.

        Raises:
            MessageTooLargeError: it does not (nothing is written).
        """
        size = MESSAGE_RECORD_OVERHEAD + len(data)
        if not self.room(size):
            raise MessageTooLargeError(
                f'a message of {len(data)} bytes on {topic} left out: a chunk holds at most '
                f'{self._limit} bytes, a message at most '
                f'{self._limit - self.size - MESSAGE_RECORD_OVERHEAD} of them')
        self._writer.add_message(channel_id=channel_id, log_time=log_time, data=data,
                                 publish_time=publish_time, sequence=sequence)
        self.added(size, message=True)


def new_mcap_writer(stream: Any, config: BagWriterConfig) -> Writer:
    """An mcap ``Writer`` on ``stream`` laid out as rosbag2 writes (chunk CRCs, data CRC)."""
    # No attachment index: we write no attachments, and an empty attachment-index group
    # would leave a summary offset pointing at nothing (``pymcap-cli doctor`` flags it).
    return Writer(stream, chunk_size=config.chunk_size, compression=config.compression_type(),
                  index_types=IndexType.CHUNK | IndexType.MESSAGE | IndexType.METADATA,
                  enable_crcs=True, enable_data_crcs=True)


class TopicCounts(Protocol):
    """What :func:`bag_information` needs of a topic (a :class:`TopicRecord` or a
    :class:`rcbf_ros.bag.reader.TopicInfo`)."""

    name: str
    type_name: str
    offered_qos: tuple[RecordedQos, ...]
    type_hash: str
    message_count: int


@dataclass(frozen=True)
class FileSpan:
    """One MCAP file of a bag: its name and the messages it holds."""

    path: str
    """File name relative to the bag directory."""
    start_ns: int
    """Earliest log time (0 if empty)."""
    end_ns: int
    """Latest log time (0 if empty)."""
    message_count: int
    """Messages in the file."""


def bag_information(*, files: Sequence[FileSpan],
                    topics: Iterable[TopicCounts]) -> dict[str, Any]:
    """rosbag2 bag information (``rosbag2_bagfile_information`` contents, version 9).

    The same dict goes to ``metadata.yaml`` and to the ``rosbag2`` metadata record of each file.
    Its shape is what rosbag2_storage's ``YAML::convert<BagMetadata>`` encodes and decodes for
    version 9 (``yaml.hpp``, ``qos.cpp``): ``offered_qos_profiles`` a sequence of mappings.
    """
    spans = [f for f in files if f.message_count]
    start = min((f.start_ns for f in spans), default=0)
    end = max((f.end_ns for f in spans), default=start)
    return {
        'version': BAG_FORMAT_VERSION,
        'storage_identifier': 'mcap',
        'duration': {'nanoseconds': end - start},
        'starting_time': {'nanoseconds_since_epoch': start},
        'message_count': sum(f.message_count for f in files),
        'topics_with_message_count': [
            {'topic_metadata': {
                'name': t.name,
                'type': t.type_name,
                'serialization_format': getattr(t, 'serialization_format', 'cdr'),
                'offered_qos_profiles': offered_qos_sequence(t.offered_qos),
                'type_description_hash': t.type_hash,
            }, 'message_count': t.message_count}
            for t in topics],
        'compression_format': '',
        'compression_mode': '',
        'relative_file_paths': [f.path for f in files],
        'files': [{'path': f.path,
                   'starting_time': {'nanoseconds_since_epoch': f.start_ns},
                   'duration': {'nanoseconds': f.end_ns - f.start_ns},
                   'message_count': f.message_count} for f in files],
        'custom_data': {},
        'ros_distro': ROS_DISTRO,
    }


def write_metadata_yaml(directory: str | os.PathLike[str], info: dict[str, Any]) -> Path:
    """Write ``<directory>/metadata.yaml`` (``rosbag2_bagfile_information: info``) atomically."""
    path = Path(directory) / 'metadata.yaml'
    tmp = path.with_suffix('.yaml.tmp')
    try:
        tmp.write_text(_metadata_yaml_text(info))
        os.replace(tmp, path)
    except OSError:
        tmp.unlink(missing_ok=True)  # a full disk: no half-written file left behind
        raise
    return path


def _metadata_yaml_text(info: dict[str, Any]) -> str:
    return yaml.safe_dump({'rosbag2_bagfile_information': info}, sort_keys=False)
