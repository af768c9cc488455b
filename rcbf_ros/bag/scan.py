"""One checked pass over an MCAP file: framing, chunk CRCs, data and summary CRCs, footer.

:class:`McapScan` reads a file front to back, record by record, and checks as it goes:

- the MCAP magic at both ends, and a header first;
- every record lies inside the file (a record that runs past the end of the file, or a file
  that ends without a footer, means the file was cut short: its writer was killed, or the copy
  is incomplete);
- every chunk decompresses to the size it states, its CRC (``uncompressed_crc``) matches, the
  records inside it are well framed, and its messages are on channels defined before them;
- the attachment CRCs, the data section CRC (``DataEnd``) and the summary CRC (``Footer``),
  wherever the writer stored them (non-zero);
- the summary's chunk indexes point at chunks of the file, and its statistics count the
  messages and chunks that the file holds.

Limits, checked before the bytes they guard are read or made: a record is at most
:data:`MAX_RECORD_BYTES` (68 MiB) and a chunk at most :data:`MAX_CHUNK_BYTES` (64 MiB) once
decompressed, whatever its compression (none, lz4, zstd); decompression streams into a buffer
of the size the chunk states and stops one byte past it, so a chunk that lies about its size
(a decompression bomb) costs at most that much memory. A scan holds one record and one
decompressed chunk at a time: about 3 x 64 MiB at most, on top of the reading program.

A problem is a :class:`BagError` whose one-line message names the file, where, and what is
wrong, e.g. ``bag_0.mcap: chunk at offset 1871: CRC mismatch (stored 0x..., computed 0x...)``.
A file cut short is not an error of the scan: :attr:`McapScan.cut_short` then says where and why
the readable part ends, and the caller decides (the bag reader refuses such a file unless asked
to read its whole chunks; recovery rewrites it). With ``salvage=True`` (recovery) a damaged
chunk is left out (:attr:`McapScan.skipped` says why) and the scan goes on with the next
record.
"""
from __future__ import annotations

import os
from pathlib import Path
import stat
import struct
from typing import Any, BinaryIO, Iterator
import zlib

from mcap.data_stream import ReadDataStream
from mcap.opcode import Opcode
from mcap.records import (
    Attachment,
    Channel,
    ChunkIndex,
    DataEnd,
    Footer,
    Header,
    McapRecord,
    Message,
    Metadata,
    Schema,
    Statistics,
)

from rcbf_ros.parameters.bounded_yaml import file_kind

#: The 8 bytes an MCAP file starts and ends with.
MAGIC = b'\x89MCAP0\r\n'
_RECORD_HEAD = struct.Struct('<BQ')
_MESSAGE_HEAD = struct.Struct('<HIQQ')
_FOOTER_CRC_FIELDS = 8 + 8  # summary_start, summary_offset_start: the CRC covers them
MAX_CHUNK_BYTES = 64 * 2**20
"""Most bytes a chunk may hold once decompressed (64 MiB). rosbag2's MCAP storage closes a chunk
once it passes ``chunk_size`` (768 KiB by default), so a chunk holds that plus one message; ours
(256 KiB by default) closes it before a message would take it past this limit
(:class:`rcbf_ros.bag.writer.ChunkFill`). 64 MiB is above any camera frame or point cloud a ROS
message carries. A chunk that states more, or decompresses to other than it states, is refused
before the excess is made: decompression streams into a buffer of the stated size and stops
one byte past it."""
MAX_RECORD_BYTES = MAX_CHUNK_BYTES + MAX_CHUNK_BYTES // 16
"""Longest record read (68 MiB: a chunk of :data:`MAX_CHUNK_BYTES` that did not compress, with
room for the compressor's overhead); a longer record is refused before it is read."""

_OPCODE_NAMES = {int(op): op.name.lower().replace('_', ' ') for op in Opcode}


class BagError(ValueError):
    """A bag or MCAP file that cannot be read as it is; the message is one line naming the file
    and what is wrong."""


class BagNotFoundError(BagError, FileNotFoundError):
    """Nothing readable at the path given."""


def not_regular_error(path: str | os.PathLike[str], mode: int) -> BagError:
    """The one-line error for a path that exists and is not a regular file."""
    return BagError(f'{os.fspath(path)}: not a regular file ({file_kind(mode)}); a bag holds '
                    'regular files only')


def check_regular(path: str | os.PathLike[str]) -> None:
    """Raise unless ``path`` is a regular file (after symlinks), without opening it (a FIFO
    would block the opener until a writer comes; a device may never end).

    Raises:
        BagNotFoundError: nothing at ``path``.
        BagError: ``path`` is a directory, FIFO, device or socket, or cannot be examined.
    """
    try:
        mode = os.stat(path).st_mode
    except FileNotFoundError as exc:
        raise BagNotFoundError(f'{os.fspath(path)}: does not exist') from exc
    except OSError as exc:
        raise BagError(f'{os.fspath(path)}: cannot be examined ({exc.strerror or exc})') from exc
    if not stat.S_ISREG(mode):
        raise not_regular_error(path, mode)


def open_regular(path: str | os.PathLike[str]) -> BinaryIO:
    """``open(path, 'rb')`` of a regular file only: opened without blocking (a FIFO put in its
    place after :func:`check_regular` cannot hang the reader) and checked on the open file.

    Raises:
        BagNotFoundError: nothing at ``path``.
        BagError: not a regular file, or it cannot be opened.
    """
    try:
        fd = os.open(path, os.O_RDONLY | getattr(os, 'O_NONBLOCK', 0))
    except FileNotFoundError as exc:
        raise BagNotFoundError(f'{os.fspath(path)}: does not exist') from exc
    except IsADirectoryError as exc:
        raise not_regular_error(path, stat.S_IFDIR) from exc
    except OSError as exc:
        raise BagError(f'{os.fspath(path)}: cannot be opened ({exc.strerror or exc})') from exc
    try:
        mode = os.fstat(fd).st_mode
        if not stat.S_ISREG(mode):
            raise not_regular_error(path, mode)
        if hasattr(os, 'set_blocking'):
            os.set_blocking(fd, True)
        return os.fdopen(fd, 'rb')
    except BaseException:
        os.close(fd)
        raise


class _Corrupt(Exception):
    """A damaged record (message without the file name; the scan adds it)."""


class _StrictBytes:
    """``read(n)`` over a record body that fails instead of returning fewer than n bytes."""

    def __init__(self, data: bytes | memoryview) -> None:
        self._view = memoryview(data)
        self._pos = 0

    def read(self, n: int) -> bytes:
        end = self._pos + n
        if end > len(self._view):
            raise _Corrupt(f'needs {end} bytes, the record holds {len(self._view)}')
        out = bytes(self._view[self._pos:end])
        self._pos = end
        return out


def _parse(record_type: Any, body: bytes | memoryview, *args: Any) -> Any:
    """``record_type.read`` over ``body``; any parse failure is :class:`_Corrupt`."""
    try:
        return record_type.read(ReadDataStream(_StrictBytes(body)), *args)  # type: ignore[arg-type]
    except (struct.error, UnicodeDecodeError, ValueError) as exc:
        raise _Corrupt(f'malformed ({exc})') from exc


def _opcode_name(opcode: int) -> str:
    return _OPCODE_NAMES.get(opcode, f'opcode 0x{opcode:02x}')


_CHUNK_HEAD = struct.Struct('<QQQI')  # start and end time, uncompressed size and CRC
_LENGTH4, _LENGTH8 = struct.Struct('<I'), struct.Struct('<Q')


class _ChunkFields:
    """A chunk record's fields, its data a view into the record (no copy)."""

    __slots__ = ('uncompressed_size', 'uncompressed_crc', 'compression', 'data')

    def __init__(self, body: memoryview) -> None:
        try:
            _, _, self.uncompressed_size, self.uncompressed_crc = _CHUNK_HEAD.unpack_from(body)
            pos = _CHUNK_HEAD.size
            (n,) = _LENGTH4.unpack_from(body, pos)
            pos += _LENGTH4.size
            if pos + n > len(body):
                raise _Corrupt(f'its compression name needs {n} bytes, the record holds '
                               f'{len(body) - pos}')
            self.compression = bytes(body[pos:pos + n]).decode()
            pos += n
            (length,) = _LENGTH8.unpack_from(body, pos)
            pos += _LENGTH8.size
        except (struct.error, UnicodeDecodeError) as exc:
            raise _Corrupt(f'malformed ({exc})') from exc
        if length > len(body) - pos:
            raise _Corrupt(f'its data needs {length} bytes, the record holds {len(body) - pos}')
        self.data = body[pos:pos + length]


def _stream_lz4(data: memoryview, size: int) -> bytes:
    """One lz4 frame decompressed into at most ``size`` + 1 bytes."""
    import lz4.frame
    decompressor = lz4.frame.LZ4FrameDecompressor()
    out = decompressor.decompress(data, max_length=size + 1)
    if len(out) > size:
        raise _Corrupt(f'decompresses to more than the {size} bytes it states')
    if not decompressor.eof:
        raise _Corrupt(f'its lz4 frame ends after {len(out)} of the {size} bytes it states')
    return out


def _stream_zstd(data: memoryview, size: int) -> bytes:
    """zstd decompressed into at most ``size`` + 1 bytes (its window is virtual memory that
    only what is decompressed touches; zstd refuses windows above 128 MiB)."""
    import zstandard
    reader = zstandard.ZstdDecompressor().stream_reader(data, read_across_frames=True)
    out = reader.read(size + 1)
    if len(out) > size:
        raise _Corrupt(f'decompresses to more than the {size} bytes it states')
    return out


def _decompress(chunk: _ChunkFields) -> bytes | memoryview:
    """The chunk's records, checked against its stated size and CRC; the stated size is checked
    against :data:`MAX_CHUNK_BYTES` before anything is decompressed, and no decompressor makes
    more than one byte past it."""
    size = chunk.uncompressed_size
    if size > MAX_CHUNK_BYTES:
        raise _Corrupt(f'states {size} uncompressed bytes, more than the {MAX_CHUNK_BYTES}-byte '
                       'limit of a chunk')
    compression = chunk.compression
    try:
        if compression == '':
            data: bytes | memoryview = chunk.data
        elif compression == 'zstd':
            data = _stream_zstd(chunk.data, size)
        elif compression == 'lz4':
            data = _stream_lz4(chunk.data, size)
        else:
            raise _Corrupt(f'unknown compression {compression!r}')
    except ImportError as exc:
        raise _Corrupt(f'compressed with {compression}, which needs the Python package '
                       f'{exc.name!r}') from exc
    except _Corrupt:
        raise
    except Exception as exc:  # noqa: BLE001 - zstandard / lz4 raise their own error types
        why = ' '.join(str(exc).split())
        raise _Corrupt(f'cannot be decompressed ({compression}: {why})') from exc
    if len(data) != size:
        raise _Corrupt(f'decompresses to {len(data)} bytes, not the {size} it states')
    if chunk.uncompressed_crc:
        computed = zlib.crc32(data)
        if computed != chunk.uncompressed_crc:
            raise _Corrupt(f'CRC mismatch (stored 0x{chunk.uncompressed_crc:08x}, computed '
                           f'0x{computed:08x})')
    return data


class McapScan:
    """A checked front-to-back pass over one MCAP file (see the module docstring).

    Usage::

        scan = McapScan(path)
        scan.verify()                 # raises BagError on damage
        if scan.complete: ...         # footer, end magic, every CRC verified
        else: print(scan.cut_short)   # where and why the readable part ends

        for offset, record in McapScan(path).records(): ...   # the checked records

    Args:
        path: the ``.mcap`` file.
        salvage: leave damaged chunks out (listed in :attr:`skipped`) instead of raising, and
            end the scan at the data section's end or at the first unreadable record.
    """

    def __init__(self, path: str | os.PathLike[str], *, salvage: bool = False) -> None:
        self.path = Path(path)
        self.salvage = salvage
        self._reset()

    def _reset(self) -> None:
        self.size = 0
        """File size in bytes."""
        self.header: Header | None = None
        """The file's header record (after a scan)."""
        self.complete = False
        """Footer and end magic found, every stored CRC verified."""
        self.readable_end = 0
        """Offset just past the last whole record read."""
        self.cut_short = ''
        """Why the file ends before its footer ('' if it does not)."""
        self.chunk_count = 0
        """Chunks read whole (and verified)."""
        self.message_count = 0
        """Messages in those chunks (and outside chunks)."""
        self.skipped: list[str] = []
        """``salvage``: the damaged chunks or records left out, one line each."""
        self.skipped_bytes = 0
        """``salvage``: bytes of those records (header included); a cut-off tail is not
        counted here (see :attr:`readable_end`)."""

    def error(self, what: str) -> BagError:
        """A :class:`BagError` about this file."""
        return BagError(f'{self.path}: {what}')

    def verify(self) -> McapScan:
        """Read the whole file, checking everything; returns ``self``.

        Raises:
            BagNotFoundError: the file does not exist.
            BagError: the file is damaged (or not MCAP at all).
        """
        for _ in self.records(emit=False):
            pass
        return self

    def records(self, *, emit: bool = True) -> Iterator[tuple[int, McapRecord]]:
        """The data records in file order, each once checked, with the offset of the record
        (for records inside a chunk: the chunk's offset).

        Yields headers, schemas, channels, messages, metadata and attachments (the summary's
        copies are not yielded). ``emit=False`` checks without building the records.
        """
        self._reset()
        stream = open_regular(self.path)
        with stream:
            try:
                yield from self._walk(stream, emit)
            except OSError as exc:
                raise self.error(f'read failed ({exc.strerror})') from exc

    # -- the pass ------------------------------------------------------------------------------

    def _cut(self, offset: int, why: str) -> None:
        self.readable_end = offset
        self.cut_short = why

    def _walk(self, stream: BinaryIO, emit: bool) -> Iterator[tuple[int, McapRecord]]:
        self.size = size = os.fstat(stream.fileno()).st_size
        if size == 0:
            raise self.error('empty file (0 bytes), not an MCAP file')
        magic = stream.read(len(MAGIC))
        if magic != MAGIC:
            if len(magic) < len(MAGIC) and MAGIC.startswith(magic):
                self._cut(0, f'the file ends after {len(magic)} bytes, inside the MCAP magic')
                return
            raise self.error('not an MCAP file (no MCAP magic at the start)')
        # A file that ends with the closing magic was closed by its writer: a record running
        # past its end has a damaged length, the file was not cut short.
        stream.seek(max(size - len(MAGIC), len(MAGIC)))
        closed = size >= 2 * len(MAGIC) and stream.read(len(MAGIC)) == MAGIC
        stream.seek(len(MAGIC))
        data_crc = zlib.crc32(magic)
        summary_crc = 0
        summary_start: int | None = None  # offset just after DataEnd
        offset = self.readable_end = len(MAGIC)
        channels: set[int] = set()
        chunks: dict[int, int] = {}  # chunk offset -> record length (opcode and length too)
        summary_chunks: list[tuple[int, ChunkIndex]] = []
        statistics: tuple[int, Statistics] | None = None
        while True:
            head = stream.read(_RECORD_HEAD.size)
            if len(head) < _RECORD_HEAD.size:
                self._cut(offset, 'no footer after the last whole record' if not head else
                          f'the file ends inside a record header at offset {offset}')
                return
            opcode, length = _RECORD_HEAD.unpack(head)
            name = _opcode_name(opcode)
            if length > size - offset - len(head):
                what = (f'the {name} record at offset {offset} needs {length} bytes, '
                        f'{size - offset - len(head)} remain')
                if closed and not self.salvage:
                    raise self.error(f'{what} (a damaged length: the file ends with the '
                                     'closing magic)')
                self._cut(offset, what)
                return
            if length > MAX_RECORD_BYTES:
                what = (f'the {name} record at offset {offset} is {length} bytes, more than '
                        f'the {MAX_RECORD_BYTES}-byte limit of a record')
                if not self.salvage:
                    raise self.error(what)
                self.skipped.append(what)
                if opcode not in (Opcode.CHUNK, Opcode.MESSAGE, Opcode.ATTACHMENT,
                                  Opcode.METADATA):
                    self._cut(offset, what)
                    return
                offset = stream.seek(length, os.SEEK_CUR)  # never read
                self.skipped_bytes += len(head) + length
                self.readable_end = offset
                continue
            body = stream.read(length)
            if len(body) < length:  # the file shrank while being read
                self._cut(offset, f'the {name} record at offset {offset} is incomplete')
                return
            record_offset, offset = offset, offset + len(head) + length
            if self.header is None and opcode != Opcode.HEADER:
                raise self.error(f'the first record (at offset {record_offset}) is a {name} '
                                 'record, not a header')
            if summary_start is None:
                if opcode != Opcode.DATA_END:
                    data_crc = zlib.crc32(body, zlib.crc32(head, data_crc))
            elif opcode == Opcode.FOOTER:
                summary_crc = zlib.crc32(body[:_FOOTER_CRC_FIELDS],
                                         zlib.crc32(head, summary_crc))
            else:
                summary_crc = zlib.crc32(body, zlib.crc32(head, summary_crc))
            try:
                if opcode == Opcode.CHUNK:
                    if summary_start is not None:
                        continue  # not part of the data: ignored, as readers do
                    records, messages = self._chunk(_ChunkFields(memoryview(body)), channels,
                                                    emit)
                    chunks[record_offset] = len(head) + length
                    self.chunk_count += 1
                    self.message_count += messages
                    if emit:
                        for record in records:
                            yield record_offset, record
                elif opcode == Opcode.MESSAGE and summary_start is None:
                    if length < _MESSAGE_HEAD.size:
                        raise _Corrupt(f'is {length} bytes, shorter than a message header')
                    channel_id = _MESSAGE_HEAD.unpack_from(body)[0]
                    if channel_id not in channels:
                        raise _Corrupt(f'is on channel {channel_id}, which no channel record '
                                       'before it defines')
                    self.message_count += 1
                    if emit:
                        yield record_offset, _parse(Message, body, length)
                elif opcode in (Opcode.SCHEMA, Opcode.CHANNEL) and summary_start is None:
                    record = _parse(Schema if opcode == Opcode.SCHEMA else Channel, body)
                    if isinstance(record, Channel):
                        channels.add(record.id)
                    if emit:
                        yield record_offset, record
                elif opcode == Opcode.HEADER:
                    if self.header is not None:
                        raise _Corrupt('is a second header')
                    self.header = _parse(Header, body)
                    if emit:
                        yield record_offset, self.header
                elif opcode == Opcode.METADATA and summary_start is None:
                    record = _parse(Metadata, body)
                    if emit:
                        yield record_offset, record
                elif opcode == Opcode.ATTACHMENT and summary_start is None:
                    record = self._attachment(body)
                    if emit:
                        yield record_offset, record
                elif opcode == Opcode.DATA_END:
                    end = _parse(DataEnd, body)
                    if (end.data_section_crc and end.data_section_crc != data_crc
                            and not self.salvage):
                        raise self.error(
                            f'data section CRC mismatch (stored 0x{end.data_section_crc:08x}, '
                            f'computed 0x{data_crc:08x})')
                    summary_start = offset
                    if self.salvage:
                        self.readable_end = offset
                        return  # every data record is read; the summary is rebuilt anyway
                elif opcode == Opcode.CHUNK_INDEX:
                    summary_chunks.append((record_offset, _parse(ChunkIndex, body)))
                elif opcode == Opcode.STATISTICS:
                    statistics = (record_offset, _parse(Statistics, body))
                elif opcode == Opcode.FOOTER:
                    footer = _parse(Footer, body)
                    self._check_summary(footer, summary_start, summary_crc, chunks,
                                        summary_chunks, statistics)
                    if self._check_end_magic(stream, offset, size):
                        self.readable_end = size
                        self.complete = True
                    return
            except _Corrupt as exc:
                what = f'{name} at offset {record_offset}: {exc}'
                if not self.salvage:
                    raise self.error(what) from None
                self.skipped.append(what)
                if opcode not in (Opcode.CHUNK, Opcode.MESSAGE, Opcode.ATTACHMENT,
                                  Opcode.METADATA):
                    self._cut(record_offset, what)
                    return
                self.skipped_bytes += offset - record_offset
            self.readable_end = offset

    def _chunk(self, chunk: _ChunkFields, channels: set[int],
               emit: bool) -> tuple[Iterator[McapRecord], int]:
        """The records of one chunk (messages only if ``emit``), made one at a time, and its
        message count.

        Everything is checked before anything is returned, so a damaged chunk adds nothing; the
        records are then built while the caller takes them, so a chunk of many small messages
        never stands in memory as that many objects.
        """
        data = memoryview(_decompress(chunk))
        new_channels: set[int] = set()
        messages = 0
        for pos, opcode, body in self._chunk_records(data):
            if opcode == Opcode.MESSAGE:
                if len(body) < _MESSAGE_HEAD.size:
                    raise _Corrupt(f'the message at byte {pos} of its data is shorter than a '
                                   'message header')
                channel_id = _MESSAGE_HEAD.unpack_from(body)[0]
                if channel_id not in channels and channel_id not in new_channels:
                    raise _Corrupt(f'the message at byte {pos} of its data is on channel '
                                   f'{channel_id}, which no channel record before it defines')
                messages += 1
            elif opcode == Opcode.CHANNEL:
                new_channels.add(_parse(Channel, body).id)
            elif opcode == Opcode.SCHEMA:
                _parse(Schema, body)
        channels |= new_channels
        return self._chunk_objects(data, emit), messages

    @staticmethod
    def _chunk_records(data: memoryview) -> Iterator[tuple[int, int, memoryview]]:
        """(byte, opcode, body) of each record in a chunk's data, framing checked."""
        pos = 0
        while pos < len(data):
            if pos + _RECORD_HEAD.size > len(data):
                raise _Corrupt(f'its data ends inside a record header at byte {pos}')
            opcode, length = _RECORD_HEAD.unpack_from(data, pos)
            start, end = pos + _RECORD_HEAD.size, pos + _RECORD_HEAD.size + length
            if end > len(data):
                raise _Corrupt(f'the {_opcode_name(opcode)} record at byte {pos} of its data '
                               f"runs past the data's end")
            yield pos, opcode, data[start:end]
            pos = end

    @classmethod
    def _chunk_objects(cls, data: memoryview, emit: bool) -> Iterator[McapRecord]:
        """The schemas and channels (and messages, if ``emit``) of checked chunk data."""
        for _, opcode, body in cls._chunk_records(data):
            if opcode == Opcode.MESSAGE and emit:
                channel_id, sequence, log_time, publish_time = _MESSAGE_HEAD.unpack_from(body)
                yield Message(channel_id=channel_id, log_time=log_time,
                              data=bytes(body[_MESSAGE_HEAD.size:]),
                              publish_time=publish_time, sequence=sequence)
            elif opcode == Opcode.CHANNEL:
                yield _parse(Channel, body)
            elif opcode == Opcode.SCHEMA:
                yield _parse(Schema, body)

    def _attachment(self, body: bytes) -> Attachment:
        record = _parse(Attachment, body)
        crc_at = len(body) - 4
        stored = struct.unpack_from('<I', body, crc_at)[0]
        if stored:
            computed = zlib.crc32(body[:crc_at])
            if computed != stored:
                raise _Corrupt(f'CRC mismatch (stored 0x{stored:08x}, computed '
                               f'0x{computed:08x})')
        return record

    def _check_summary(self, footer: Footer, summary_start: int | None, summary_crc: int,
                       chunks: dict[int, int], summary_chunks: list[tuple[int, ChunkIndex]],
                       statistics: tuple[int, Statistics] | None) -> None:
        """The footer and the summary agree with the file (raises on disagreement)."""
        if summary_start is None:
            raise self.error('no data end record before the footer')
        if footer.summary_start and footer.summary_start != summary_start:
            raise self.error(f'footer: the summary starts at offset {summary_start}, not at '
                             f'{footer.summary_start} as the footer says')
        if footer.summary_crc and footer.summary_crc != summary_crc:
            raise self.error(f'summary CRC mismatch (stored 0x{footer.summary_crc:08x}, '
                             f'computed 0x{summary_crc:08x})')
        for at, index in summary_chunks:
            if chunks.get(index.chunk_start_offset) != index.chunk_length:
                raise self.error(f'chunk index at offset {at}: no chunk of {index.chunk_length} '
                                 f'bytes starts at offset {index.chunk_start_offset}')
        if statistics is not None:
            at, stats = statistics
            if (stats.message_count, stats.chunk_count) != (self.message_count,
                                                            self.chunk_count):
                raise self.error(f'statistics at offset {at}: {stats.message_count} messages in '
                                 f'{stats.chunk_count} chunks, the file holds '
                                 f'{self.message_count} in {self.chunk_count}')

    def _check_end_magic(self, stream: BinaryIO, offset: int, size: int) -> bool:
        """True if the closing magic ends the file; False if the file is cut inside it."""
        tail = stream.read(len(MAGIC) + 1)
        if tail[:len(MAGIC)] != MAGIC:
            if len(tail) < len(MAGIC) and MAGIC.startswith(tail):
                self._cut(offset, f'the file ends at byte {size}, inside the closing MCAP magic')
                return False
            raise self.error(f'no MCAP magic after the footer (offset {offset})')
        if len(tail) > len(MAGIC):
            raise self.error(f'{size - offset - len(MAGIC)} bytes after the closing MCAP magic')
        return True
