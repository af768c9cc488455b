"""The times a ``/clock`` message may give a node under ``use_sim_time``.

The node clock is then whatever ``/clock`` says, from any participant of the domain, and every
stamp the node writes (a diagnostic, a TwistStamped) is that clock's time. rclpy's time
source raises on negative seconds, which ends the spin: one bad sample would stop the filter.
A time past int32 seconds leaves no stamp that can be written. Both kinds are dropped here and
said at most once a second; the clock keeps its time. Pure: no middleware.
"""
from __future__ import annotations

LATEST_STAMP_NS = 2**31 * 10**9 - 1
"""The latest time (ns) a builtin_interfaces/msg/Time holds: its seconds are an int32."""
WARN_PERIOD_NS = 10**9
"""The shortest time between two lines about refused /clock messages."""


def clock_refusal(sec: int, nanosec: int) -> str:
    """Why a ``/clock`` message of ``sec`` s and ``nanosec`` ns cannot be the node's time, or
    '' when it can. Its time is sec s + nanosec ns, as rclpy reads it (a nanosec of 1e9 or
    more counts whole seconds too)."""
    if sec < 0:
        return f'sec {sec} is negative'
    if sec * 10**9 + nanosec > LATEST_STAMP_NS:
        return (f'sec {sec} nanosec {nanosec} is later than {LATEST_STAMP_NS} ns, the latest '
                'builtin_interfaces/msg/Time (2038-01-19)')
    return ''


class ClockGuard:
    """Checks each ``/clock`` message; counts the refused ones and says so once a second."""

    def __init__(self) -> None:
        self.refused = 0
        """The messages refused so far."""
        self._said_ns: int | None = None

    def check(self, sec: int, nanosec: int, *, now_ns: int) -> tuple[bool, str]:
        """Whether the message may set the clock, and a line to log ('' for none).

        Args:
            sec, nanosec: the message's ``clock`` field.
            now_ns: a monotonic time (ns), for the once-a-second line.
        """
        refusal = clock_refusal(sec, nanosec)
        if not refusal:
            return True, ''
        self.refused += 1
        if self._said_ns is not None and now_ns - self._said_ns < WARN_PERIOD_NS:
            return False, ''
        self._said_ns = now_ns
        return False, (f'/clock: message refused, the clock keeps its time: {refusal} '
                       f'({self.refused} refused so far)')
