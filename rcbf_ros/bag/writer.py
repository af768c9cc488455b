"""Write bags: MCAP files in the layout of rosbag2's MCAP storage plugin, plus ``metadata.yaml``.

A bag is a directory ``<dir>/`` holding ``<dir>/<name>_0.mcap`` and, once closed,
``<dir>/metadata.yaml`` (rosbag2 bag information, version 9, ``storage_identifier: mcap``), so
that ``ros2 bag info/play <dir>``, Foxglove and rosbags read it.

The MCAP file follows what rosbag2_storage_mcap writes:

- header profile ``ros2``;
- one schema per message type: name ``pkg/msg/Type``, encoding ``ros2msg``, data the full
  concatenated message definition (root ``.msg`` text, then each dependency after a line of
  80 ``=`` and ``MSG: pkg/Type``);
- one channel per topic: message encoding ``cdr``, metadata ``offered_qos_profiles`` (the
  profiles dumped to a YAML string, see :mod:`rcbf_ros.bag.qos`) and ``topic_type_hash``
  (``RIHS01_...``);
- messages with ``log_time`` = receive time and ``publish_time`` = send time, in nanoseconds;
- a metadata record named ``rosbag2`` with key ``serialized_metadata`` (the bag information
  YAML, the same as ``metadata.yaml``'s: from version 9 on, each topic's
  ``offered_qos_profiles`` is a YAML sequence of profiles there, not a string) written on close,
  then the summary: schemas, channels, statistics, chunk / metadata indexes and summary
  offsets.

Integrity. Every chunk carries the CRC of its records and the data end record the CRC of the
data section; the readers (:mod:`rcbf_ros.bag.scan`) check them.

Crash safety. Messages are grouped into compressed chunks. The file is written unbuffered, so a
chunk, with its message indexes, reaches the operating system as soon as it is finished: when it
fills (``chunk_size`` bytes), when ``flush()`` is called, and at the latest on the first
``write()`` after ``flush_period_s`` has passed since the last flush. What has reached the OS
survives the writer process being killed (SIGKILL included; not a power cut unless
``fsync=True``). So after a kill at most the messages written since the last flush are lost:
with a periodic ``flush()`` (the recorder calls it every ``flush_period_s``), at most the last
``flush_period_s`` of data. The file then lacks its summary and footer, and the readers refuse
it until :func:`rcbf_ros.bag.recover.recover_bag` (``rcbf_ros bag recover <dir>``) has rewritten
it as a complete file from its whole chunks. While the writer is open it holds an exclusive
``flock`` on the file, so recovery never touches a bag that is still being written.
"""
from __future__ import annotations

from dataclasses import dataclass
from importlib.metadata import PackageNotFoundError, version
import os
from pathlib import Path
import time
from typing import Any, Iterable, Protocol, Sequence

from mcap.writer import CompressionType, IndexType, Writer
import yaml

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


class _UnbufferedFile:
    """The stream the mcap writer writes to: every ``write`` goes straight to the OS.

    The mcap writer buffers a chunk itself and writes it (then its message indexes) in one
    call each, so writing unbuffered costs a few system calls per chunk and puts every finished
    chunk on disk at once. (A raw ``FileIO`` would be wrapped in a ``BufferedWriter`` by the
    mcap writer, hence this small class.)
    """

    def __init__(self, path: Path) -> None:
        self._fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)  # never clobber
        self._position = 0

    def fileno(self) -> int:
        return self._fd

    def write(self, data: bytes | bytearray | memoryview) -> int:
        view = memoryview(data)
        while view:
            written = os.write(self._fd, view)
            view = view[written:]
        self._position += len(data)
        return len(data)

    def tell(self) -> int:
        return self._position

    def flush(self) -> None:
        """Nothing is buffered here."""

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
    crash, worse compression)."""
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
        self._file = _UnbufferedFile(self.mcap_path)
        _lock_exclusive(self._file.fileno())
        self._writer = new_mcap_writer(self._file, config)
        self._writer.start(profile='ros2', library=_library_identifier())
        self._writer.flush()
        self._last_flush = time.monotonic()
        self._closed = False

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
        if schema_id is None:
            schema_id = self._writer.register_schema(
                name=type_name, encoding='ros2msg', data=message_definition.encode())
            self._schema_ids[type_name] = schema_id
        channel_id = self._writer.register_channel(
            topic=name, message_encoding='cdr', schema_id=schema_id,
            metadata={'offered_qos_profiles': dump_offered_qos_profiles(profiles),
                      'topic_type_hash': type_hash})
        record = TopicRecord(name=name, type_name=type_name, channel_id=channel_id,
                             offered_qos=profiles, type_hash=type_hash)
        self.topics[name] = record
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
        """
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
        self._writer.add_message(
            channel_id=record.channel_id, log_time=log_time_ns, data=data,
            publish_time=log_time_ns if publish_time_ns is None else int(publish_time_ns),
            sequence=record.message_count & 0xFFFFFFFF)
        record.message_count += 1
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
        """Close the open chunk and hand everything written so far to the OS (see module doc)."""
        self._check_open()
        self._writer.flush()
        if self.config.fsync:
            os.fsync(self._file.fileno())
        self._last_flush = time.monotonic()

    # -- closing --------------------------------------------------------------------------

    @property
    def message_count(self) -> int:
        """Messages written so far, all topics."""
        return self._times.count

    def bag_metadata(self) -> dict[str, Any]:
        """rosbag2 bag information (``rosbag2_bagfile_information`` contents) as of now."""
        return bag_information(
            files=[FileSpan(self.mcap_path.name, self._times.start_ns or 0,
                            self._times.end_ns or 0, self._times.count)],
            topics=self.topics.values())

    def close(self) -> None:
        """Write the ``rosbag2`` metadata record, the summary and footer, then metadata.yaml.

        Idempotent.
        """
        if self._closed:
            return
        info = self.bag_metadata()
        self._writer.flush()  # last chunk first: the metadata record then follows all data
        self._writer.add_metadata('rosbag2', {
            'serialized_metadata': yaml.safe_dump(info, sort_keys=False).rstrip('\n')})
        self._writer.finish()
        if self.config.fsync:
            os.fsync(self._file.fileno())
        self._file.close()
        self._closed = True
        write_metadata_yaml(self.directory, info)

    def _check_open(self) -> None:
        if self._closed:
            raise RuntimeError(f'bag {str(self.directory)!r} is closed')

    def __enter__(self) -> BagWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


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
    tmp.write_text(yaml.safe_dump({'rosbag2_bagfile_information': info}, sort_keys=False))
    os.replace(tmp, path)
    return path
