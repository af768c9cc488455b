"""The console as rcutils writes it: one line to stderr, best effort.

A node's console is output for people, never a reason to stop: stderr may be a full disk, a
pipe whose reader left (EPIPE), a closed file or no file at all (``2>&-``), and rcutils'
handler drops the line then and goes on. A log line or an exit line goes through here so that
the node goes on filtering, and a program that stops keeps its exit status.
"""
from __future__ import annotations

import sys


def console_line(line: str) -> bool:
    """Write ``line`` and a newline to stderr and flush; False (the line dropped) where stderr
    cannot take it. Never raises."""
    stream = sys.stderr
    if stream is None:  # started with stderr closed: Python has no stream
        return False
    try:
        stream.write(f'{line}\n')
        stream.flush()
    except (OSError, ValueError):  # ENOSPC, EPIPE, EIO; a closed file; an encoding refused
        return False
    return True
