"""Test helpers: crafted hostile inputs, small on disk, that expand into far more than they hold
(MCAP chunks that are decompression bombs or lie about their size, YAML alias bombs, deep
nests, params files of any size), and a way to run a command and see its peak memory."""
from __future__ import annotations

import json
from pathlib import Path
import struct
import subprocess
import sys
from typing import Sequence

import lz4.frame

MAGIC = b'\x89MCAP0\r\n'
_HEADER, _CHUNK, _DATA_END, _FOOTER = 0x01, 0x06, 0x0F, 0x02
MIB = 2**20


def _record(opcode: int, body: bytes) -> bytes:
    return struct.pack('<BQ', opcode, len(body)) + body


def _string(text: str) -> bytes:
    raw = text.encode()
    return struct.pack('<I', len(raw)) + raw


def chunk_record(data: bytes, *, compression: str, uncompressed_size: int,
                 uncompressed_crc: int = 0) -> bytes:
    """An MCAP chunk record holding ``data`` (already compressed), stating the given size."""
    body = (struct.pack('<QQQI', 0, 0, uncompressed_size, uncompressed_crc)
            + _string(compression) + struct.pack('<Q', len(data)) + data)
    return _record(_CHUNK, body)


def mcap_with_chunk(path: Path, chunk: bytes) -> Path:
    """A closed MCAP file: magic, header, ``chunk``, data end, footer, magic.

    The chunk comes right after the header, at offset :data:`CHUNK_OFFSET`.
    """
    header = _record(_HEADER, _string('ros2') + _string('hostile'))
    tail = (_record(_DATA_END, struct.pack('<I', 0))
            + _record(_FOOTER, struct.pack('<QQI', 0, 0, 0)))
    path.write_bytes(MAGIC + header + chunk + tail + MAGIC)
    return path


#: Offset of the chunk in a file of :func:`mcap_with_chunk`.
CHUNK_OFFSET = len(MAGIC) + 9 + 4 + len('ros2') + 4 + len('hostile')


def lz4_zeros(n_mib: int) -> bytes:
    """One lz4 frame that decompresses to ``n_mib`` MiB of zeros (about 4 KiB per MiB): the
    compressed 4 MiB block of zeros repeated, so building it costs nothing."""
    block_mib = 4
    frame = lz4.frame.compress(bytes(block_mib * MIB), block_size=lz4.frame.BLOCKSIZE_MAX4MB,
                               block_linked=False, content_checksum=False, store_size=False)
    header, end_mark = frame[:7], frame[-4:]
    block = frame[7:-4]
    assert end_mark == b'\0\0\0\0' and len(block) < block_mib * MIB
    return header + block * (n_mib // block_mib) + end_mark


def zstd_zeros(n_mib: int) -> bytes:
    """One zstd frame of RLE blocks that decompresses to ``n_mib`` MiB of zeros (4 bytes per
    128 KiB): no content size in its header, a 128 KiB window."""
    frame = struct.pack('<IBB', 0xFD2FB528, 0x00, (17 - 10) << 3)
    blocks = n_mib * 8
    for i in range(blocks):
        last = 1 if i == blocks - 1 else 0
        frame += (last | (1 << 1) | (128 * 1024) << 3).to_bytes(3, 'little') + b'\0'
    return frame


def alias_bomb(levels: int = 9, width: int = 9) -> str:
    """A YAML document of ``width ** levels`` leaves in a few hundred bytes (billion laughs),
    under the rosbag2 ``metadata.yaml`` key."""
    lines = ['a0: &a0 ["lol"]']
    for i in range(1, levels + 1):
        lines.append(f'a{i}: &a{i} [' + ', '.join([f'*a{i - 1}'] * width) + ']')
    lines.append('rosbag2_bagfile_information:')
    lines.append('  version: 9')
    lines.append(f'  relative_file_paths: *a{levels}')
    return '\n'.join(lines) + '\n'


def deep_params(depth: int) -> str:
    """A params file whose one value nests ``depth`` flow sequences."""
    return ('/**:\n  ros__parameters:\n    system: unicycle\n    x: '
            + '[' * depth + ']' * depth + '\n')


def huge_params(path: Path, size: int) -> Path:
    """A params file of ``size`` bytes: a real header, then a hole (sparse where the file system
    allows, so it costs no disk)."""
    head = b'/**:\n  ros__parameters:\n    system: unicycle\n    comment: "'
    with open(path, 'wb') as stream:
        stream.write(head)
        stream.truncate(size)
    return path


_PEAK = """
import resource, subprocess, sys, json
limit = int(sys.argv[1])
def cap():
    if limit:
        resource.setrlimit(resource.RLIMIT_AS, (limit, limit))
run = subprocess.run(sys.argv[2:], capture_output=True, preexec_fn=cap)
peak = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss * 1024
print(json.dumps([run.returncode, run.stdout.decode(errors='replace'),
                  run.stderr.decode(errors='replace'), peak]))
"""


def run_measured(argv: Sequence[str], *, address_space: int = 0, timeout: float = 300,
                 env: dict[str, str] | None = None) -> tuple[int, str, str, int]:
    """Run ``argv`` in a child of a fresh interpreter: (exit status, stdout, stderr, the
    child's peak RSS in bytes). ``address_space``: the child's RLIMIT_AS (0: none), so that a
    reader that would take more fails with MemoryError instead of taking the machine."""
    done = subprocess.run([sys.executable, '-c', _PEAK, str(address_space), *argv],
                          capture_output=True, text=True, timeout=timeout, env=env, check=True)
    status, out, err, peak = json.loads(done.stdout)
    return status, out, err, peak
