"""Recover a bag whose writer was killed, and rebuild ``metadata.yaml`` (``ros2 bag reindex``).

    rcbf_ros bag recover BAG [--no-backup]      # or: python -m rcbf_ros.bag recover BAG
    rcbf_ros bag check BAG

A recorder killed by SIGKILL (or a full disk, or a power cut) leaves MCAP files without their
summary and footer. Readers that start from the footer (rosbags' AnyReader, mcap's seeking
reader and so mcap_ros2's, ``pymcap-cli``) refuse such a file, and so do ours.
:func:`recover_file` rewrites it as a complete MCAP file: its header, then the schemas,
channels, messages, metadata and attachments of every whole chunk (CRC checked; a damaged chunk
is left out and reported), re-chunked with chunk and data CRCs, a fresh ``rosbag2`` metadata
record (for the ``ros2`` profile), a data end, a summary (schemas, channels, statistics, chunk
and metadata indexes, summary offsets) and a footer. :func:`recover_bag` does so for every file
of a bag directory, then writes ``metadata.yaml`` with the recovered message counts.

The recovered file is written beside the original under a temporary name, synced to disk and
renamed over the original in one step; the original stays as ``<file>.orig`` (a hard link, so
the rename never leaves the bag without its file) unless ``keep_original=False``. A complete
file is checked and left as it is. A file still held open by a running writer (its ``flock``,
see :mod:`rcbf_ros.bag.writer`) is refused.
"""
from __future__ import annotations

import argparse
from dataclasses import dataclass
import os
from pathlib import Path
import shutil
import sys
from typing import Sequence

from mcap.data_stream import RecordBuilder
from mcap.records import Attachment, Channel, Header, Message, Metadata, Schema
import yaml

from rcbf_ros.bag.reader import bag_file_order, bag_info, BagInfo, channel_qos, TopicInfo
from rcbf_ros.bag.scan import BagError, BagNotFoundError, check_regular, McapScan, open_regular
from rcbf_ros.bag.writer import (
    bag_information,
    BagWriterConfig,
    ChunkFill,
    FileSpan,
    max_chunk_bytes,
    MESSAGE_RECORD_OVERHEAD,
    MessageTooLargeError,
    new_mcap_writer,
    write_metadata_yaml,
)

#: Suffix of the original file kept beside a recovered one.
ORIGINAL_SUFFIX = '.orig'
_PARTIAL_SUFFIX = '.recovering'


@dataclass(frozen=True)
class FileRecovery:
    """What recovering one MCAP file did."""

    path: Path
    """The file (now complete)."""
    rewritten: bool
    """False: the file was complete and is untouched."""
    message_count: int
    """Messages the file holds now."""
    dropped_bytes: int
    """Bytes of the original whose data is not in the recovered file: the damaged records
    left out and the cut-off tail past the last whole record."""
    problems: tuple[str, ...]
    """Why the original was incomplete, and each damaged record left out."""
    original: Path | None
    """Where the original is kept (None if not rewritten or not kept)."""

    def describe(self) -> str:
        """One line for the command line."""
        if not self.rewritten:
            return f'{self.path}: complete, left as it is ({self.message_count} messages)'
        kept = f'; original kept as {self.original.name}' if self.original else ''
        return (f'{self.path}: recovered {self.message_count} messages from whole chunks, '
                f'dropped {self.dropped_bytes} bytes ({"; ".join(self.problems)}){kept}')


class _FileLock:
    """A shared ``flock`` on a file, refused while a writer holds its exclusive one."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self._file = None

    def __enter__(self) -> _FileLock:
        try:
            import fcntl
        except ImportError:  # not POSIX: no lock
            return self
        self._file = open_regular(self.path)
        try:
            fcntl.flock(self._file.fileno(), fcntl.LOCK_SH | fcntl.LOCK_NB)
        except BlockingIOError as exc:
            self._file.close()
            raise BagError(f'{self.path}: is being written by a running process (stop the '
                           'recorder first)') from exc
        return self

    def __exit__(self, *exc: object) -> None:
        if self._file is not None:
            self._file.close()


def _topics_of(path: Path, channels: dict[int, Channel], schemas: dict[int, Schema],
               per_channel: dict[int, int]) -> list[TopicInfo]:
    """Per-topic counts for the ``rosbag2`` record, from the recovered channels."""
    topics: dict[str, TopicInfo] = {}
    for channel_id, channel in channels.items():
        schema = schemas.get(channel.schema_id)
        count = per_channel.get(channel_id, 0)
        known = topics.get(channel.topic)
        if known is not None:
            topics[channel.topic] = TopicInfo(known.name, known.type_name,
                                              known.message_count + count, known.offered_qos,
                                              known.type_hash)
            continue
        topics[channel.topic] = TopicInfo(
            channel.topic, schema.name if schema else '', count,
            channel_qos(path, channel),
            channel.metadata.get('topic_type_hash', ''))
    return list(topics.values())


def _rewrite(path: Path, partial: Path, problems: list[str]) -> tuple[int, McapScan, int]:
    """Write the whole records of ``path`` as a complete MCAP file ``partial``, in chunks the
    reader accepts; return the message count, the salvage scan and the bytes of the messages
    no chunk can hold (left out, each one a line in ``problems``)."""
    scan = McapScan(path, salvage=True)
    left_out = 0
    with open(partial, 'xb') as stream:
        writer = None
        fill: ChunkFill | None = None
        schema_ids: dict[int, int] = {}
        channel_ids: dict[int, int] = {}
        channels: dict[int, Channel] = {}
        schemas: dict[int, Schema] = {}
        per_channel: dict[int, int] = {}
        start: int | None = None
        end: int | None = None
        header = Header(profile='', library='')
        for _, record in scan.records():
            if isinstance(record, Header):
                header = record
                config = BagWriterConfig(chunk_size=min(BagWriterConfig.chunk_size,
                                                        max_chunk_bytes()))
                writer = new_mcap_writer(stream, config)
                fill = ChunkFill(writer, config.chunk_size)
                writer.start(profile=record.profile, library=record.library)
                continue
            assert writer is not None and fill is not None  # the scan yields the header first
            if isinstance(record, Message):
                new_id = channel_ids.get(record.channel_id)
                if new_id is None:  # its channel was left out (below)
                    left_out += MESSAGE_RECORD_OVERHEAD + len(record.data)
                    continue
                try:
                    fill.add_message(channel_id=new_id, log_time=record.log_time,
                                     data=record.data, publish_time=record.publish_time,
                                     sequence=record.sequence, topic=channels[new_id].topic)
                except MessageTooLargeError as exc:
                    problems.append(str(exc))
                    left_out += MESSAGE_RECORD_OVERHEAD + len(record.data)
                    continue
                per_channel[new_id] = per_channel.get(new_id, 0) + 1
                start = record.log_time if start is None else min(start, record.log_time)
                end = record.log_time if end is None else max(end, record.log_time)
            elif isinstance(record, Schema) and record.id not in schema_ids:
                if not fill.room(_record_size(record)):
                    left_out += _too_large(record, problems)
                    continue  # its channels have no schema
                schema_ids[record.id] = writer.register_schema(
                    name=record.name, encoding=record.encoding, data=record.data)
                fill.added(_record_size(record), message=False)
                schemas[schema_ids[record.id]] = record
            elif isinstance(record, Channel) and record.id not in channel_ids:
                if not fill.room(_record_size(record)):
                    left_out += _too_large(record, problems)
                    continue  # its messages are left out
                new_id = writer.register_channel(
                    topic=record.topic, message_encoding=record.message_encoding,
                    schema_id=schema_ids.get(record.schema_id, 0), metadata=record.metadata)
                fill.added(_record_size(record), message=False)
                channel_ids[record.id] = new_id
                channels[new_id] = Channel(new_id, record.topic, record.message_encoding,
                                           record.metadata, schema_ids.get(record.schema_id, 0))
            elif isinstance(record, Metadata) and not (record.name == 'rosbag2'
                                                        and header.profile == 'ros2'):
                writer.add_metadata(record.name, record.metadata)
            elif isinstance(record, Attachment):
                writer.add_attachment(create_time=record.create_time, log_time=record.log_time,
                                      name=record.name, media_type=record.media_type,
                                      data=record.data)
        if writer is None:
            raise scan.error('no header record: nothing to recover')
        count = sum(per_channel.values())
        if header.profile == 'ros2':
            info = bag_information(
                files=[FileSpan(path.name, start or 0, end or 0, count)],
                topics=_topics_of(path, channels, schemas, per_channel))
            writer.flush()  # the record follows all data, as the writer's close() does
            fill.closed()
            writer.add_metadata('rosbag2', {
                'serialized_metadata': yaml.safe_dump(info, sort_keys=False).rstrip('\n')})
        writer.finish()
        stream.flush()
        os.fsync(stream.fileno())
    return count, scan, left_out


def _too_large(record: Schema | Channel, problems: list[str]) -> int:
    """Say that ``record`` (only one outside any chunk can be so large) is left out; its
    size."""
    size = _record_size(record)
    problems.append(f'{type(record).__name__.lower()} {record.id} of {size} bytes left out: '
                    'larger than a chunk may be')
    return size


def _record_size(record: Schema | Channel) -> int:
    """Bytes of ``record`` serialized (what it adds to a chunk)."""
    builder = RecordBuilder()
    record.write(builder)
    return builder.count
def recover_file(path: str | os.PathLike[str], *, keep_original: bool = True) -> FileRecovery:
    """Make one MCAP file complete (see the module docstring); a complete file is untouched.

    Args:
        path: the ``.mcap`` file.
        keep_original: keep the original beside the recovered file as ``<file>.orig``.

    Raises:
        BagError: not an MCAP file, no header, still being written, or ``<file>.orig`` exists.
    """
    path = Path(path)
    check_regular(path)
    with _FileLock(path):
        scan = McapScan(path)
        damage = ''
        try:
            scan.verify()
        except BagError as exc:
            damage = str(exc).removeprefix(f'{path}: ')
        if scan.complete:
            return FileRecovery(path, False, scan.message_count, 0, (), None)
        original = path.with_name(path.name + ORIGINAL_SUFFIX) if keep_original else None
        # An original that is the file itself was linked by a recovery interrupted before its
        # rename: it is kept as it is.
        linked = original is not None and original.exists() and original.samefile(path)
        if original is not None and original.exists() and not linked:
            raise BagError(f'{original}: exists already (move it away to recover {path.name} '
                           'again)')
        partial = path.with_name(path.name + _PARTIAL_SUFFIX)
        partial.unlink(missing_ok=True)  # left by a recovery that was itself interrupted
        problems: list[str] = []
        try:
            count, salvage, left_out = _rewrite(path, partial, problems)
            if original is not None and not linked:
                _keep(path, original)
            os.replace(partial, path)
        finally:
            partial.unlink(missing_ok=True)
    sync_directory(path.parent)
    problems[:0] = salvage.skipped
    dropped = salvage.skipped_bytes + left_out
    if salvage.cut_short:
        problems.append(f'cut short at byte {salvage.readable_end}: {salvage.cut_short}')
        dropped += salvage.size - salvage.readable_end
    if damage and damage not in problems:
        problems.insert(0, damage)
    return FileRecovery(path, True, count, dropped, tuple(problems), original)


def _keep(path: Path, original: Path) -> None:
    """``original`` becomes a second name of ``path`` (a copy where links are impossible)."""
    try:
        os.link(path, original)
    except OSError:
        shutil.copy2(path, original)


def sync_directory(directory: Path) -> None:
    """Flush ``directory``'s entries (a rename) to disk where the system allows it."""
    try:
        fd = os.open(directory, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass  # some file systems refuse fsync on a directory; the rename is still done
    finally:
        os.close(fd)


def reindex_bag(directory: str | os.PathLike[str], *, keep_original: bool = True) -> Path:
    """Recover every ``*.mcap`` file of a bag directory (:func:`recover_file`), then write its
    ``metadata.yaml`` from the data (like ``ros2 bag reindex``, after a crash).

    Returns:
        The path of the metadata file written.

    Raises:
        BagError: the directory or its files cannot be recovered (the message says which).
    """
    return _recover_directory(Path(directory), keep_original=keep_original)[0]


def _recover_directory(directory: Path, *,
                       keep_original: bool) -> tuple[Path, list[FileRecovery]]:
    if not directory.is_dir():
        if os.path.lexists(directory):
            check_regular(directory)  # a FIFO, a device: refused as such
        raise BagNotFoundError(f'{directory}: bag directory does not exist')
    files = sorted(directory.glob('*.mcap'), key=bag_file_order)
    if not files:
        raise BagNotFoundError(f'{directory}: bag directory holds no .mcap file')
    for file in files:  # before anything is rewritten: a FIFO would block, a directory fail
        check_regular(file)
    recoveries = [recover_file(f, keep_original=keep_original) for f in files]
    spans: list[FileSpan] = []
    topics: dict[str, TopicInfo] = {}
    for file in files:
        one = bag_info(file, allow_cut_short=False)
        spans.append(FileSpan(file.name, one.start_time_ns, one.end_time_ns, one.message_count))
        for name, topic in one.topics.items():
            known = topics.get(name)
            topics[name] = topic if known is None else TopicInfo(
                name, known.type_name, known.message_count + topic.message_count,
                known.offered_qos, known.type_hash)
    meta = write_metadata_yaml(directory, bag_information(files=spans, topics=topics.values()))
    return meta, recoveries


def recover_bag(path: str | os.PathLike[str], *,
                keep_original: bool = True) -> list[FileRecovery]:
    """Recover a bag directory (its files and ``metadata.yaml``) or one ``.mcap`` file."""
    if Path(path).is_file():
        return [recover_file(path, keep_original=keep_original)]
    return _recover_directory(Path(path), keep_original=keep_original)[1]


def check_bag(path: str | os.PathLike[str]) -> BagInfo:
    """Check every file of a bag in full; the bag's summary if it is complete and intact.

    Raises:
        BagError: a file is missing, damaged, foreign or cut short (the message says which).
    """
    return bag_info(path, allow_cut_short=False)


# -- command line ----------------------------------------------------------------------------

def add_bag_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of ``rcbf_ros bag``."""
    verbs = parser.add_subparsers(dest='bag_command', required=True)
    recover = verbs.add_parser(
        'recover', help='rewrite a bag cut short (recorder killed) as complete MCAP files from '
                        'their whole chunks, and write its metadata.yaml')
    recover.add_argument('bag', help='bag directory or .mcap file')
    recover.add_argument('--no-backup', dest='keep_original', action='store_false',
                         help=f'do not keep the original file as <file>{ORIGINAL_SUFFIX}')
    check = verbs.add_parser('check', help='check every chunk and CRC of a bag')
    check.add_argument('bag', help='bag directory or .mcap file')


def run_bag_command(args: argparse.Namespace) -> int:
    """Run ``rcbf_ros bag <verb>``: 0, or 2 with one line on stderr if the bag is bad."""
    try:
        if args.bag_command == 'recover':
            for recovery in recover_bag(args.bag, keep_original=args.keep_original):
                print(recovery.describe())
            if Path(args.bag).is_dir():
                print(f'{Path(args.bag) / "metadata.yaml"}: written')
        else:
            info = check_bag(args.bag)
            print(f'{args.bag}: intact, {info.message_count} messages on {len(info.topics)} '
                  f'topics in {len(info.files)} file(s)')
    except (BagError, OSError) as exc:
        print(f'rcbf_ros bag {args.bag_command}: error: {exc}', file=sys.stderr)
        return 2
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m rcbf_ros.bag recover|check BAG``: as ``rcbf_ros bag``."""
    parser = argparse.ArgumentParser(prog='python -m rcbf_ros.bag',
                                     description='Check or recover an MCAP bag.')
    add_bag_arguments(parser)
    return run_bag_command(parser.parse_args(argv))
