"""The robot's planar pose at each state's stamp, for placing a sensor message at its own time.

Where tf does not join a source's frame to the state's (no odom -> base_link on ``/tf``), the
points of a message in the robot's frame reach the state's frame through the robot's pose. The
pose to use is the one at the message's stamp, not the latest: a scan taken 0.1 s ago by a
robot turning at 1.9 rad/s would otherwise be turned by 0.19 rad with it, and every point
ahead moved sideways by a fifth of its range. :class:`PoseHistory` keeps the poses of the
recent states and answers a stamp by tf's rules (:mod:`rcbf_ros.node_logic.tf_buffer`):
interpolated between the neighbouring states (the position linearly, the heading along the
shorter arc), held within ``tolerance_ns`` of the first or last, else refused with the reason.
It keeps at most :data:`MAX_POSES` poses and none older than ``cache_s`` before the newest. A
state that arrives out of order (stamps jitter) goes in its place. The receiver's clock going
back (a simulation or a bag restarted), or a stamp more than ``cache_s`` before the newest,
clears it first, as tf2 clears its buffer when the clock jumps back.
"""
from __future__ import annotations

import bisect
from collections import deque
import math

from rcbf_ros.node_logic.tf_buffer import DEFAULT_CACHE_S, seconds_text

MAX_POSES = 4096
"""The most poses kept: 10 s of states at 400 Hz."""

_S = 1_000_000_000


class PoseHistory:
    """Poses (x, y, heading) of the robot in the state's frame, by stamp (module docstring)."""

    def __init__(self, *, cache_s: float = DEFAULT_CACHE_S, max_poses: int = MAX_POSES) -> None:
        if not (math.isfinite(cache_s) and cache_s > 0):
            raise ValueError(f'cache_s: {cache_s!r} is not a duration > 0')
        if not (isinstance(max_poses, int) and max_poses >= 1):
            raise ValueError(f'max_poses: {max_poses!r} is not an integer >= 1')
        self.cache_ns = int(cache_s * _S)
        self._stamps: deque[int] = deque(maxlen=max_poses)
        self._poses: deque[tuple[float, float, float]] = deque(maxlen=max_poses)
        self.clears = 0
        """How often the clock going back cleared the history."""
        self._clock_ns: int | None = None
        """The receiver's clock handed in last (:meth:`add`)."""

    def __len__(self) -> int:
        return len(self._stamps)

    def add(self, stamp_ns: int, x: float, y: float, heading: float, *,
            now_ns: int | None = None) -> str:
        """Keep the pose at ``stamp_ns``: '' when kept, else why not (one line). A stamp
        kept already has its pose replaced; an earlier one than the newest goes in its place;
        one more than the cache before the newest, or a receiver's clock ``now_ns`` earlier
        than the one handed in before (a simulation or a bag restarted), clears the history
        first."""
        if not isinstance(stamp_ns, int) or isinstance(stamp_ns, bool):
            return f'pose stamp {stamp_ns!r} is not an integer'
        if not all(math.isfinite(v) for v in (x, y, heading)):
            return "the state's pose is not finite"
        stamps, poses, pose = self._stamps, self._poses, (x, y, heading)
        went_back = now_ns is not None and self._clock_ns is not None and now_ns < self._clock_ns
        if now_ns is not None:
            self._clock_ns = now_ns
        if stamps and (went_back or stamp_ns < stamps[-1] - self.cache_ns):
            stamps.clear()
            poses.clear()
            self.clears += 1
        # the common case: the newest (a full history drops its oldest: the deques' maxlen)
        if not stamps or stamp_ns > stamps[-1]:
            stamps.append(stamp_ns)
            poses.append(pose)
            horizon = stamp_ns - self.cache_ns
            while stamps[0] < horizon:
                stamps.popleft()
                poses.popleft()
            return ''
        at = bisect.bisect_left(stamps, stamp_ns)
        if stamps[at] == stamp_ns:
            poses[at] = pose
            return ''
        if len(stamps) == stamps.maxlen:  # full: the oldest makes room, unless this is older
            if at == 0:
                return ''
            stamps.popleft()
            poses.popleft()
            at -= 1
        stamps.insert(at, stamp_ns)
        poses.insert(at, pose)
        return ''

    def at(self, stamp_ns: int, *, tolerance_ns: int) -> tuple[float, float, float] | str:
        """The pose (x, y, heading) at ``stamp_ns`` (module docstring), or why there is none
        (one line naming the stamps)."""
        stamps, poses = self._stamps, self._poses
        if not stamps:
            return 'no state yet'
        tolerance_ns = max(0, tolerance_ns)
        if stamp_ns >= stamps[-1]:
            if stamp_ns - stamps[-1] <= tolerance_ns:
                return poses[-1]
            return (f'the newest state is {seconds_text(stamp_ns - stamps[-1])} older than the '
                    f'message (tolerance {seconds_text(tolerance_ns)})')
        if stamp_ns <= stamps[0]:
            if stamps[0] - stamp_ns <= tolerance_ns:
                return poses[0]
            return (f'the oldest state kept is {seconds_text(stamps[0] - stamp_ns)} newer than '
                    f'the message (tolerance {seconds_text(tolerance_ns)})')
        after = bisect.bisect_right(stamps, stamp_ns)
        t0, t1 = stamps[after - 1], stamps[after]
        (x0, y0, h0), (x1, y1, h1) = poses[after - 1], poses[after]
        s = (stamp_ns - t0) / (t1 - t0)
        turn = math.remainder(h1 - h0, math.tau)  # the shorter arc
        return x0 + s * (x1 - x0), y0 + s * (y1 - y0), h0 + s * turn
