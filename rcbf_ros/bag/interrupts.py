"""Ctrl-C and SIGTERM that wait for a bag write to finish.

Python's own SIGINT handler raises ``KeyboardInterrupt`` between any two bytecodes, so a
program that records a bag in the main thread (``rcbf_ros train``) can be interrupted halfway
through a chunk: the mcap writer's chunk was taken apart but not yet written, and closing the
bag then lost it. A process that installs :func:`on_interrupt` (see :func:`interrupts_raise`)
gets the same ``KeyboardInterrupt``, except inside :data:`held` (the bag writer's sections that
change the file): there the signal is recorded and raised as the outermost section ends, with
the write complete. Sections are short (one message, one chunk), so Ctrl-C is still prompt.

Where the write itself fails (a full disk) while a signal waits, the write's error goes on
out of the section, so that the program reports the failure it cannot recover from (the user's
stop then ends nothing more than the error does); the signal is raised as ``interrupts_raise``
ends, should the program have handled the error and gone on.

Only the main thread's sections hold a signal: the handler runs in the main thread, and a
write in another thread is not what it interrupts.
"""
from __future__ import annotations

from collections.abc import Iterator
import contextlib
import signal
import threading
from typing import Any

_MAIN = threading.main_thread().ident
_get_ident = threading.get_ident


class _Held:
    """``with held:`` a signal arriving meanwhile in the main thread waits for the end."""

    def __init__(self) -> None:
        self.depth = 0
        """Sections the main thread is inside."""
        self.pending: int | None = None
        """The signal that arrived inside them, raised at the end of the outermost."""
        self.owed: int | None = None
        """A signal held while an error left the outermost section: raised as
        :func:`interrupts_raise` ends without an error."""

    def __enter__(self) -> None:
        if _get_ident() == _MAIN:
            self.depth += 1

    def __exit__(self, exc_type: type[BaseException] | None, *exc: object) -> None:
        if _get_ident() != _MAIN:
            return
        self.depth -= 1
        if self.depth == 0 and self.pending is not None:
            signum, self.pending = self.pending, None
            if exc_type is None:
                raise KeyboardInterrupt
            if not issubclass(exc_type, KeyboardInterrupt):
                self.owed = signum  # the write's error goes on: it says what failed


held = _Held()
"""The sections that a signal does not cut in half (the bag writer enters them)."""


def on_interrupt(signum: int, frame: Any) -> None:
    """Signal handler: ``KeyboardInterrupt`` now, or at the end of the :data:`held` section the
    main thread is in."""
    if held.depth > 0:
        held.pending = signum
        return
    raise KeyboardInterrupt


@contextlib.contextmanager
def interrupts_raise(*signums: int) -> Iterator[None]:
    """Within the block, ``signums`` (default SIGINT and SIGTERM) raise ``KeyboardInterrupt``
    through :func:`on_interrupt`; the previous handlers come back afterwards. A SIGINT the
    process was started ignoring (a background job of a script) stays ignored, as Python
    leaves it. Outside the main thread (where handlers cannot be set) nothing changes."""
    if _get_ident() != _MAIN:
        yield
        return
    # No section is open here; a count left behind by an interrupt that cut one short under
    # Python's own handler (outside this block) would hold every signal back.
    held.depth, held.pending, held.owed = 0, None, None
    previous = {signum: signal.signal(signum, on_interrupt)
                for signum in signums or (signal.SIGINT, signal.SIGTERM)
                if not (signum == signal.SIGINT and signal.getsignal(signum) == signal.SIG_IGN)}
    try:
        yield
    except BaseException:
        held.owed = None  # the block's own error or interrupt is what it ends with
        raise
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)
    if held.owed is not None:  # held behind a write's error that the block then handled
        held.owed = None
        raise KeyboardInterrupt
