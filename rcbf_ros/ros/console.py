"""The console as rcutils writes it: one line to stderr, best effort.

A node's console is output for people, never a reason to stop: stderr may be a full disk, a
pipe whose reader left (EPIPE), a closed file or no file at all (``2>&-``), and rcutils'
handler drops the line then and goes on. A log line or an exit line goes through here so that
the node goes on filtering, and a program that stops keeps its exit status. A command's stdout
is guarded likewise (:func:`run_writing_stdout`).
"""
from __future__ import annotations

import io
import os
import sys
from typing import Callable, TextIO


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


class _Stdout(io.TextIOBase):
    """``sys.stdout`` while a command runs: once the stream fails (its reader left, a full
    disk), what follows is dropped and the command goes on with its work."""

    def __init__(self, stream: TextIO) -> None:
        self.stream = stream
        self.error: OSError | None = None
        """The first error of the stream, None while it takes everything."""

    def _failed(self, error: OSError) -> None:
        self.error = error
        try:  # the buffered rest goes nowhere, also at the interpreter's last flush
            descriptor = self.stream.fileno()
        except (OSError, ValueError):  # no descriptor (a stream of the caller's)
            return
        null = os.open(os.devnull, os.O_WRONLY)
        try:
            os.dup2(null, descriptor)
        finally:
            os.close(null)

    def write(self, text: str) -> int:
        if self.error is None:
            try:
                self.stream.write(text)
            except OSError as exc:
                self._failed(exc)
        return len(text)

    def flush(self) -> None:
        if self.error is None:
            try:
                self.stream.flush()
            except OSError as exc:
                self._failed(exc)

    def writable(self) -> bool:
        return True

    @property
    def encoding(self) -> str:  # type: ignore[override]
        return getattr(self.stream, 'encoding', 'utf-8')


def run_writing_stdout(program: str, command: Callable[[], int]) -> int:
    """``command()``'s exit status, its stdout guarded: a reader that leaves (``| head``, a
    closed pipe) costs the rest of the output, never the work nor a traceback; a stdout that
    fails otherwise (a full disk) is said in one line on stderr and makes the status 1 where
    the command would have returned 0 (what stdout holds is incomplete). A SystemExit of the
    command (argparse's ``--help``) leaves as one, its status changed alike."""
    stream = sys.stdout
    if stream is None:  # started with stdout closed: print() writes nothing already
        return command()
    guarded = _Stdout(stream)
    sys.stdout = guarded
    try:
        status = command()
    except SystemExit as exc:
        _restore(guarded, stream)
        if isinstance(exc.code, int) and _said_incomplete(program, guarded):
            raise SystemExit(exc.code or 1) from None
        raise
    except BaseException:
        _restore(guarded, stream)
        raise
    _restore(guarded, stream)
    return (status or 1) if _said_incomplete(program, guarded) else status


def _restore(guarded: _Stdout, stream: TextIO) -> None:
    """What ``guarded`` holds written out; ``stream`` sys.stdout again."""
    guarded.flush()
    sys.stdout = stream


def _said_incomplete(program: str, guarded: _Stdout) -> bool:
    """Whether stdout failed other than by its reader leaving; then said in one line."""
    error = guarded.error
    if error is None or isinstance(error, BrokenPipeError):
        return False
    console_line(f'{program}: stdout: {error.strerror or error}; what it holds is incomplete')
    return True
