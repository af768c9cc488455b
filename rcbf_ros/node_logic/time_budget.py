"""A share of a node's one executor thread that an input stream may take.

A node answers on one thread, so a stream whose messages cost much to read (a ``/tf`` message
of 1,024 transforms takes some 15-30 ms in Python) can hold every answer back for as long as
its queue lasts: a reliable keep-last-100 ``/tf`` reader full of such messages stalls the
filter for seconds. A :class:`TimeBudget` bounds that: the time the stream took (the executor
thread's CPU time: a reading descheduled meanwhile is not charged the wait) is charged to
it, and while it is in debt a message is refused unread (a microsecond), so the stream takes
at most ``share`` of the time, and at once at most ``burst_s`` plus one message.
"""
from __future__ import annotations

import math
import time
from typing import Callable


class TimeBudget:
    """A token bucket of executor time (ns): refilled at ``share`` of the time that passes,
    up to ``burst_s``; each message's reading time charged to it; a message admitted while
    anything is left (so the debt is at most one message's time)."""

    def __init__(self, *, share: float, burst_s: float,
                 clock: Callable[[], int] = time.monotonic_ns,
                 work_clock: Callable[[], int] | None = None) -> None:
        """Args:
            share: the part of the time the stream may take on average, in (0, 1].
            burst_s: the most it may take at once, after a quiet while (s, > 0).
            clock: monotonic time in ns (the node's; a test's own): the refill's.
            work_clock: what a reading is charged on: the executor thread's CPU time by
                default (a reading descheduled or held by a garbage collection is not
                charged the time it waited, which would refuse the robot's own tf after
                one hiccup); ``clock`` when only that is given.

        Raises:
            ValueError: naming ``share`` or ``burst_s``.
        """
        if not (isinstance(share, (int, float)) and 0.0 < share <= 1.0):
            raise ValueError(f'share: {share!r} is not in (0, 1]')
        if not (isinstance(burst_s, (int, float)) and math.isfinite(burst_s) and burst_s > 0):
            raise ValueError(f'burst_s: {burst_s!r} is not a duration > 0')
        self.share = float(share)
        self.burst_ns = int(burst_s * 1e9)
        self.clock = clock
        self.work_clock = work_clock if work_clock is not None else (
            time.thread_time_ns if clock is time.monotonic_ns else clock)
        self._left_ns = float(self.burst_ns)
        self._at_ns: int | None = None
        self.refused = 0
        """Messages refused since the last one admitted (for a log line's count)."""

    def admit(self) -> int | None:
        """The start of a message's reading on :attr:`work_clock` (ns) when the budget has
        time left, else None (the message is to be refused unread; counted in
        :attr:`refused`)."""
        now = self.clock()
        if self._at_ns is not None and now > self._at_ns:
            self._left_ns = min(float(self.burst_ns),
                                self._left_ns + self.share * (now - self._at_ns))
        self._at_ns = now if self._at_ns is None else max(self._at_ns, now)
        if self._left_ns <= 0.0:
            self.refused += 1
            return None
        self.refused = 0
        return self.work_clock()

    def charge(self, started_ns: int) -> None:
        """Charge the work since ``started_ns`` (:meth:`admit`'s answer, or
        :attr:`work_clock` read by a caller that is never refused) to the budget."""
        self._left_ns -= max(0, self.work_clock() - started_ns)
        now = self.clock()
        if self._at_ns is not None and now > self._at_ns:  # the reading's time is no refill
            self._at_ns = now

    def read(self, reading: Callable[[], str], counts: dict[str, int]) -> str:
        """``reading()`` (a message read: '' or why its content was refused) charged to the
        budget; or, while the budget is spent, nothing read: counted in ``counts``
        (``messages`` and ``refused``) and why (one line)."""
        started = self.admit()
        if started is None:
            counts['messages'] += 1
            counts['refused'] += 1
            return f'unread, {self.refusal()}'
        try:
            return reading()
        finally:
            self.charge(started)

    def refusal(self) -> str:
        """Why a message is refused: one line naming the share and the burst."""
        return (f'the stream took more than its share of the executor '
                f'({self.share:.0%} of the time, {self.burst_ns / 1e6:g} ms at once), so that '
                'the answers are not held back')
