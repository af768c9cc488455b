"""A transform buffer with tf2's lookup rules, in plain Python (no middleware).

The filter keeps the transforms of ``/tf`` and ``/tf_static``
(:func:`rcbf_ros.messages.tf.tf_transforms`) here and asks for sensor frames in the state's
frame at a message's stamp. The rules are tf2's ``BufferCore``: the frames form a tree (each
child one parent; a transform naming a new parent for a child replaces the child's link, as
tf2 replaces its cache); a static link holds at every time; a dynamic link keeps its samples
for :data:`DEFAULT_CACHE_S` (tf2's default) behind its newest, at most :data:`MAX_SAMPLES`;
a lookup walks from both frames to their common ancestor; time 0 asks for the latest time at
which every link of the chain is known; any other time interpolates each dynamic link between
its two neighbouring samples (translation linearly, rotation by slerp). Where tf2 refuses any
extrapolation, a lookup here may hold a link's first or last sample for up to a tolerance
beyond it (``transform_tolerance``). Every refusal is one line naming both frames. Never
raises for any input.

Time, and why no input can lock the buffer. The buffer's time is the receiver's clock when
one is handed in (``now_ns``: the node's ROS clock; ``rcbf_ros refilter`` hands each message's
time in the bag, the clock of the recording), else the newest dynamic stamp offered. Samples
older than the cache behind that time expire on every link (tf2 prunes a link only behind its
own newest, so a link that stops keeps its samples), a link left without samples goes, and
with it any frame no link names; the bounds (:data:`MAX_TOTAL_SAMPLES`, :data:`MAX_FRAMES`)
are checked after expiry, so a flood is refused only while it lasts. With a clock, a dynamic
stamp more than the cache from it, ahead or behind, is refused (one far-future stamp would
otherwise make every correct sample older than its link's cache, tf2's TF_OLD_DATA, until the
clock caught up), and the clock going back by more than :data:`JUMP_BACK_S` clears the
dynamic links and keeps the static ones, as tf2_ros clears its buffer when ROS time jumps
back (a simulator or a bag loop restarting). The clock is the reference of choice: the
filter's sources are fresh only against it (so tf stamped far from it could place no fresh
point anyway, in the node as in a replayed bag), and a stale or future sample is refused
alone, costing the other links nothing. Without a clock the data's time stands in: a sample
older than the cache behind the newest stamp offered is taken as that time going back (the
publisher restarted) and clears the dynamic links, so a far-future stamp blocks nothing
beyond the next good sample; the first clock handed in clears data stamped more than the
cache ahead of it.
"""
from __future__ import annotations

import bisect
from dataclasses import dataclass, field
import math
from typing import cast, NamedTuple, Sequence

import numpy as np

from rcbf_ros.messages.tf import quoted, StampedTransform, transform_refusal

DEFAULT_CACHE_S = 10.0
"""How long (s) behind a link's newest sample its older ones are kept (tf2's default)."""
MAX_FRAMES = 1000
"""The most frames a buffer holds (tf2 gives up walking a chain deeper than 1000); a transform
that would add one more is refused."""
MAX_SAMPLES = 10_000
"""The most samples of one dynamic link (10 s at 1 kHz); the oldest go first."""
MAX_TOTAL_SAMPLES = 100_000
"""The most samples of all links together (100 dynamic frames at 100 Hz for 10 s, some 45 MB);
a sample that would add one more is refused (after expiry: module docstring)."""
JUMP_BACK_S = 1.0
"""The clock going back by more than this (s) clears the dynamic links (tf2_ros's Buffer
clears on a jump back of ROS time by more than 1 s)."""
SWEEP_FRACTION = 100
"""Expiry over all links runs when the buffer's time has moved on by this fraction of the
cache since the last run, or when a bound is reached (each link also drops its own expired
samples when it takes one, as tf2)."""

FRAME, CONNECTIVITY, EXTRAPOLATION, LOOP = 'frame', 'connectivity', 'extrapolation', 'loop'
"""The kinds of :class:`NoTransform` (tf2's LookupException, ConnectivityException,
ExtrapolationException, and its invalid tree)."""

_S = 1_000_000_000


class Rigid(NamedTuple):
    """A rigid transform: p -> R(rotation) p + translation."""

    rotation: tuple[float, float, float, float]
    """x, y, z, w: a unit quaternion."""
    translation: tuple[float, float, float]
    """x, y, z."""

    def compose(self, other: Rigid) -> Rigid:
        """``self`` after ``other``: p -> self(other(p))."""
        return Rigid(quaternion_product(self.rotation, other.rotation),
                     _add(rotate(self.rotation, other.translation), self.translation))

    def inverse(self) -> Rigid:
        """The transform back: self.inverse().compose(self) is the identity."""
        x, y, z, w = self.rotation
        back = (-x, -y, -z, w)
        tx, ty, tz = rotate(back, self.translation)
        return Rigid(back, (-tx, -ty, -tz))

    def matrix(self) -> np.ndarray:
        """(3, 3) the rotation matrix of ``rotation``."""
        x, y, z, w = self.rotation
        return np.array([
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])

    def apply_planar(self, points: np.ndarray) -> np.ndarray:
        """(N, 2) points at z = 0 of the source frame -> (N, 2) x, y in the target frame (the
        full 3-D transform of (x, y, 0), its z dropped)."""
        m = self.matrix()
        out = points @ m[:2, :2].T
        out += self.translation[:2]
        return out


IDENTITY = Rigid((0.0, 0.0, 0.0, 1.0), (0.0, 0.0, 0.0))


class NoTransform(NamedTuple):
    """Why a lookup has no answer."""

    reason: str
    """One line naming both frames of the lookup."""
    kind: str
    """:data:`FRAME` (a frame unknown), :data:`CONNECTIVITY` (two trees),
    :data:`EXTRAPOLATION` (data too old or too new), :data:`LOOP`."""


def quaternion_product(a: Sequence[float], b: Sequence[float]) -> tuple[float, float, float,
                                                                         float]:
    """The Hamilton product a b of quaternions (x, y, z, w): rotation b, then a."""
    ax, ay, az, aw = a
    bx, by, bz, bw = b
    return (aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
            aw * bw - ax * bx - ay * by - az * bz)


def rotate(q: Sequence[float], v: Sequence[float]) -> tuple[float, float, float]:
    """Vector ``v`` rotated by the unit quaternion ``q`` (x, y, z, w)."""
    x, y, z, w = q
    vx, vy, vz = v
    # v + 2 w (u x v) + 2 u x (u x v), u = (x, y, z)
    cx, cy, cz = y * vz - z * vy, z * vx - x * vz, x * vy - y * vx
    return (vx + 2 * (w * cx + y * cz - z * cy),
            vy + 2 * (w * cy + z * cx - x * cz),
            vz + 2 * (w * cz + x * cy - y * cx))


def _add(a: Sequence[float], b: Sequence[float]) -> tuple[float, float, float]:
    return (a[0] + b[0], a[1] + b[1], a[2] + b[2])


def slerp(a: Sequence[float], b: Sequence[float], s: float) -> tuple[float, float, float,
                                                                      float]:
    """The unit quaternion ``s`` of the way from ``a`` to ``b`` along the shorter arc
    (s = 0: a, s = 1: b or -b)."""
    dot = sum(p * q for p, q in zip(a, b))
    if dot < 0.0:  # q and -q are one rotation: take the shorter way round
        b = tuple(-q for q in b)
    # the angle between a and b, exact near 0 where acos(dot) is not (|a -+ b| = 2 sin, cos)
    theta = 2.0 * math.atan2(math.sqrt(sum((p - q) ** 2 for p, q in zip(a, b))),
                             math.sqrt(sum((p + q) ** 2 for p, q in zip(a, b))))
    sin = math.sin(theta)
    if sin < 1e-12:  # equal to rounding: the linear blend is exact
        out = [p + s * (q - p) for p, q in zip(a, b)]
    else:
        wa, wb = math.sin((1.0 - s) * theta) / sin, math.sin(s * theta) / sin
        out = [wa * p + wb * q for p, q in zip(a, b)]
    norm = math.sqrt(sum(v * v for v in out))
    return (out[0] / norm, out[1] / norm, out[2] / norm, out[3] / norm)


def interpolate(a: Rigid, b: Rigid, s: float) -> Rigid:
    """``s`` of the way from ``a`` to ``b``: translation linear, rotation by :func:`slerp`."""
    ta, tb = a.translation, b.translation
    return Rigid(slerp(a.rotation, b.rotation, s),
                 (ta[0] + s * (tb[0] - ta[0]), ta[1] + s * (tb[1] - ta[1]),
                  ta[2] + s * (tb[2] - ta[2])))


def seconds_text(ns: int) -> str:
    """A duration or time in ns as the refusals write it: seconds to the millisecond."""
    return f'{ns / _S:.3f} s'


@dataclass
class _Link:
    """Where a child frame is in its parent: one sample (static) or samples by stamp."""

    parent: str
    static: bool
    stamps: list[int] = field(default_factory=list)
    poses: list[Rigid] = field(default_factory=list)


class StampRules:
    """The time rules both buffers share (module docstring): the clock or the data's newest
    stamp, a dynamic stamp refused more than the cache away from the clock, the dynamic links
    cleared when time goes back, expiry before the frame bound. A subclass holds ``cache_ns``,
    ``max_frames``, ``_named`` (frame -> links naming it), ``_clock_ns``, ``_data_ns`` and
    ``_swept_ns``, and gives ``_clear()`` and ``_expire(due=...)``."""

    cache_ns: int
    max_frames: int
    _named: dict[str, int]
    _clock_ns: int | None
    _data_ns: int | None
    _swept_ns: int | None

    def _clear(self) -> None:
        raise NotImplementedError

    def _expire(self, *, due: bool) -> bool:
        raise NotImplementedError

    def _sweep_horizon(self, due: bool) -> int | None:
        """The time below which dynamic samples expire now (the buffer's time less the cache),
        or None when none is due: no time yet, or it has moved on by less than
        1/:data:`SWEEP_FRACTION` of the cache since the last sweep (by nothing, if ``due``)."""
        time_ns = self._clock_ns if self._clock_ns is not None else self._data_ns
        if time_ns is None:
            return None
        horizon = time_ns - self.cache_ns
        swept = self._swept_ns
        if swept is not None and (horizon <= swept if due
                                  else horizon < swept + self.cache_ns // SWEEP_FRACTION):
            return None
        self._swept_ns = horizon
        return horizon

    def _admitted(self, names: str, parent: str, child: str, stamp: int, static: bool,
                  now_ns: int | None) -> str:
        """'' when a transform ``parent`` -> ``child`` stamped ``stamp`` may be taken as far
        as time and the frame bound go, else the one-line reason (``names`` begins it)."""
        now = self._tick(now_ns)
        if not static:
            if now is not None and stamp > now + self.cache_ns:
                return (f'{names}: stamp {seconds_text(stamp)} is more than the cache '
                        f'({seconds_text(self.cache_ns)}) after the clock ({seconds_text(now)})')
            if now is not None and stamp < now - self.cache_ns:
                return (f'{names}: stamp {seconds_text(stamp)} is older than the cache '
                        f'({seconds_text(self.cache_ns)} behind the clock, {seconds_text(now)})')
            if now is None and self._data_ns is not None and \
                    stamp < self._data_ns - self.cache_ns:
                self._clear()  # the data's time went back by more than the cache
            if self._data_ns is None or stamp > self._data_ns:
                self._data_ns = stamp  # offered, if not kept: the time all the same
        self._expire(due=False)
        new = {parent, child} - self._named.keys()
        if new and len(self._named) + len(new) > self.max_frames and self._expire(due=True):
            new = {parent, child} - self._named.keys()
        if len(self._named) + len(new) > self.max_frames:
            return (f'{names}: refused, the buffer holds '
                    f'{len(self._named)} frames (at most {self.max_frames})')
        return ''

    def _tick(self, now_ns: int | None) -> int | None:
        """The clock after ``now_ns`` (None: none), the dynamic links cleared when it went
        back by more than :data:`JUMP_BACK_S`."""
        if not isinstance(now_ns, int) or isinstance(now_ns, bool) or now_ns <= 0:
            return self._clock_ns  # no clock (ROS time 0: not started)
        if self._clock_ns is not None and now_ns < self._clock_ns - int(JUMP_BACK_S * _S):
            self._clear()
            self._clock_ns = now_ns
        elif self._clock_ns is None and self._data_ns is not None and \
                self._data_ns > now_ns + self.cache_ns:
            self._clear()  # a first clock, behind the data taken without one: not its time
            self._clock_ns = now_ns
        elif self._clock_ns is None or now_ns > self._clock_ns:
            self._clock_ns = now_ns
        return self._clock_ns


class TransformBuffer(StampRules):
    """The transforms received, and lookups between any two frames (module docstring)."""

    def __init__(self, *, cache_s: float = DEFAULT_CACHE_S, max_frames: int = MAX_FRAMES,
                 max_samples: int = MAX_SAMPLES,
                 max_total_samples: int = MAX_TOTAL_SAMPLES) -> None:
        if not (math.isfinite(cache_s) and cache_s > 0):
            raise ValueError(f'cache_s: {cache_s!r} is not a duration > 0')
        self.cache_ns = int(cache_s * _S)
        self.max_frames = max_frames
        self.max_samples = max_samples
        self.max_total_samples = max_total_samples
        self._links: dict[str, _Link] = {}
        self._named: dict[str, int] = {}
        """Every frame some link names (as its child or its parent): how many links do."""
        self._samples = 0
        """Samples held by all links together."""
        self._clock_ns: int | None = None
        """The newest clock handed in (None: none yet, or none since the clock jumped back)."""
        self._data_ns: int | None = None
        """The newest dynamic stamp taken since the dynamic links were last cleared."""
        self._swept_ns: int | None = None
        """The time below which every link's samples were last expired."""
        self.clears = 0
        """How often the dynamic links were cleared (the clock or the data's time went back)."""

    @property
    def frames(self) -> frozenset[str]:
        """Every frame a link names (a frame whose links all expired is forgotten)."""
        return frozenset(self._named)

    def parent(self, frame: str) -> str | None:
        """The parent of ``frame`` (None: a root or unknown)."""
        link = self._links.get(frame)
        return None if link is None else link.parent

    def set_transform(self, transform: StampedTransform, *, static: bool,
                      now_ns: int | None = None) -> str:
        """Keep ``transform``: '' when kept, else the one-line reason it was refused (a bad
        transform, a new frame beyond :data:`MAX_FRAMES`, a sample beyond
        :data:`MAX_TOTAL_SAMPLES`, data older than the cache, as tf2's TF_OLD_DATA, or
        stamped more than the cache after ``now_ns``). ``now_ns``: the receiver's clock (ns;
        None or 0, none: module docstring). Never raises."""
        try:
            return self._set(transform, static, now_ns)
        except Exception as exc:  # any value a caller hands in: a refusal, never a raise
            return f'transform refused: {type(exc).__name__}: {" ".join(str(exc).split())}'[:200]

    def _set(self, transform: StampedTransform, static: bool, now_ns: int | None) -> str:
        parent, child, stamp = transform.parent, transform.child, transform.stamp_ns
        if not (isinstance(parent, str) and isinstance(child, str)):
            return 'transform refused: frame ids are not text'
        if not isinstance(stamp, int) or isinstance(stamp, bool):
            return f'{quoted(parent)} -> {quoted(child)}: stamp {stamp!r} is not an integer'
        translation = tuple(float(v) for v in transform.translation)
        rotation = tuple(float(v) for v in transform.rotation)
        if len(translation) != 3 or len(rotation) != 4:
            return (f'{quoted(parent)} -> {quoted(child)}: needs 3 translation and 4 rotation '
                    'values')
        why = transform_refusal(parent, child, translation, rotation)
        if why:
            return why
        names = f'{quoted(parent)} -> {quoted(child)}'
        why = self._admitted(names, parent, child, stamp, static, now_ns)
        if why:
            return why
        norm = math.sqrt(math.fsum(v * v for v in rotation))
        pose = Rigid(tuple(v / norm for v in rotation),  # type: ignore[arg-type]
                     translation)  # type: ignore[arg-type]
        link = self._links.get(child)
        replaced = link is not None and (static or link.static or link.parent != parent)
        if link is not None and not replaced and stamp < link.stamps[-1] - self.cache_ns:
            return (f'{names}: stamp {seconds_text(stamp)} is older '
                    f'than the cache ({seconds_text(self.cache_ns)} behind the newest, '
                    f'{seconds_text(link.stamps[-1])})')
        freed = len(link.stamps) if replaced else 0  # type: ignore[union-attr]
        if self._samples - freed + 1 > self.max_total_samples and self._expire(due=True):
            link = self._links.get(child)  # expiry may have taken the link
            replaced = link is not None and (static or link.static or link.parent != parent)
            freed = len(link.stamps) if replaced else 0  # type: ignore[union-attr]
        if self._samples - freed + 1 > self.max_total_samples:
            return (f'{names}: refused, the buffer holds '
                    f'{self._samples} samples (at most {self.max_total_samples})')
        if link is None or replaced:  # a new link: a new child, parent or kind
            if link is not None:
                self._drop(child, link)
            link = self._links[child] = _Link(parent, static)
            for frame in (parent, child):
                self._named[frame] = self._named.get(frame, 0) + 1
        if static:
            self._samples += 1 - len(link.stamps)
            link.stamps, link.poses = [stamp], [pose]
        else:
            at = bisect.bisect_left(link.stamps, stamp)
            if at < len(link.stamps) and link.stamps[at] == stamp:
                link.poses[at] = pose  # the same instant again: the latest word counts
            else:
                link.stamps.insert(at, stamp)
                link.poses.insert(at, pose)
                self._samples += 1
            drop = bisect.bisect_left(link.stamps, link.stamps[-1] - self.cache_ns)
            drop = max(drop, len(link.stamps) - self.max_samples)
            if drop > 0:
                del link.stamps[:drop], link.poses[:drop]
                self._samples -= drop
        return ''

    def _clear(self) -> None:
        """Forget every dynamic link (the static ones stay, as in tf2's clear)."""
        for child, link in list(self._links.items()):
            if not link.static:
                self._drop(child, link)
        self._data_ns = self._swept_ns = None
        self.clears += 1

    def _drop(self, child: str, link: _Link) -> None:
        """Forget ``child``'s link, and each of its frames no other link names."""
        del self._links[child]
        self._samples -= len(link.stamps)
        for frame in (link.parent, child):
            left = self._named[frame] - 1
            if left:
                self._named[frame] = left
            else:
                del self._named[frame]

    def _expire(self, *, due: bool) -> bool:
        """Drop every dynamic sample older than the cache behind the buffer's time (module
        docstring), and every link left without one: when the time has moved on by
        1/:data:`SWEEP_FRACTION` of the cache since the last time, or at all if ``due`` (a
        bound is reached). Whether any time had passed (something may have expired)."""
        horizon = self._sweep_horizon(due)
        if horizon is None:
            return False
        for child, link in list(self._links.items()):
            if link.static or link.stamps[0] >= horizon:
                continue
            drop = bisect.bisect_left(link.stamps, horizon)
            if drop == len(link.stamps):
                self._drop(child, link)
            else:
                del link.stamps[:drop], link.poses[:drop]
                self._samples -= drop
        return True

    def lookup_transform(self, target: str, source: str, time_ns: int, *,
                         tolerance_ns: int = 0) -> Rigid | NoTransform:
        """The transform taking points in ``source`` to ``target`` at ``time_ns`` (0: the
        latest time the whole chain is known), each dynamic link interpolated at that time or
        held within ``tolerance_ns`` of its first or last sample; else :class:`NoTransform`.
        Never raises."""
        try:
            return self._lookup(target, source, int(time_ns), max(0, int(tolerance_ns)))
        except Exception as exc:  # a defect or an absurd argument: a refusal all the same
            return NoTransform(f'no transform from {quoted(str(source))} to '
                               f'{quoted(str(target))}: {type(exc).__name__}: '
                               f'{" ".join(str(exc).split())}'[:300], FRAME)

    def _lookup(self, target: str, source: str, time_ns: int,
                tolerance_ns: int) -> Rigid | NoTransform:
        names = f'no transform from {quoted(source)} to {quoted(target)}'
        for frame in (target, source):
            if not isinstance(frame, str) or not frame:
                return NoTransform(f'{names}: empty frame id', FRAME)
        if target == source:
            return IDENTITY
        for frame in (source, target):
            if frame not in self._named:
                return NoTransform(f'{names}: frame {quoted(frame)} does not exist', FRAME)
        up_source, up_target = self._path(source), self._path(target)
        for path in (up_source, up_target):
            if isinstance(path, str):
                return NoTransform(f'{names}: the tree has a loop through {path}', LOOP)
        up_source, up_target = cast(list, up_source), cast(list, up_target)
        on_target = set(up_target)
        common = next((frame for frame in up_source if frame in on_target), None)
        if common is None:
            return NoTransform(f'{names}: they are in two unconnected trees (of roots '
                               f'{quoted(up_source[-1])} and {quoted(up_target[-1])})',
                               CONNECTIVITY)
        source_links = [self._links[frame] for frame in up_source[:up_source.index(common)]]
        target_links = [self._links[frame] for frame in up_target[:up_target.index(common)]]
        if time_ns == 0:  # tf2: the latest time at which every link is known
            newest = [link.stamps[-1] for link in source_links + target_links
                      if not link.static]
            time_ns = min(newest) if newest else 0
        ups = []
        for path, links in ((up_source, source_links), (up_target, target_links)):
            up = IDENTITY  # the frame at the path's start -> the common ancestor
            for frame, link in zip(path, links):
                pose = self._sample(link, frame, time_ns, tolerance_ns)
                if isinstance(pose, str):
                    return NoTransform(f'{names} at {seconds_text(time_ns)}: {pose}',
                                       EXTRAPOLATION)
                up = pose.compose(up)
            ups.append(up)
        source_up, target_up = ups
        return target_up.inverse().compose(source_up)

    def _path(self, frame: str) -> list[str] | str:
        """``frame``, its parent, ..., its root; or the frame where the walk comes back on
        itself (quoted: a loop)."""
        path, seen = [frame], {frame}
        link = self._links.get(frame)
        while link is not None:
            frame = link.parent
            if frame in seen:
                return quoted(frame)
            path.append(frame)
            seen.add(frame)
            link = self._links.get(frame)
        return path

    @staticmethod
    def _sample(link: _Link, child: str, time_ns: int, tolerance_ns: int) -> Rigid | str:
        """``link`` at ``time_ns``: interpolated between its neighbouring samples, or its first
        or last held within ``tolerance_ns``; else why not (one line)."""
        if link.static:
            return link.poses[0]
        stamps, poses = link.stamps, link.poses
        what = f'{quoted(link.parent)} -> {quoted(child)}'
        if time_ns >= stamps[-1]:
            if time_ns - stamps[-1] <= tolerance_ns:
                return poses[-1]
            return (f'{what} too old: its newest is at {seconds_text(stamps[-1])}, '
                    f'{seconds_text(time_ns - stamps[-1])} before (tolerance '
                    f'{seconds_text(tolerance_ns)})')
        if time_ns <= stamps[0]:
            if stamps[0] - time_ns <= tolerance_ns:
                return poses[0]
            return (f'{what} too new: its oldest is at {seconds_text(stamps[0])}, '
                    f'{seconds_text(stamps[0] - time_ns)} after (tolerance '
                    f'{seconds_text(tolerance_ns)})')
        after = bisect.bisect_right(stamps, time_ns)
        before = after - 1
        if stamps[before] == time_ns:
            return poses[before]
        s = (time_ns - stamps[before]) / (stamps[after] - stamps[before])
        return interpolate(poses[before], poses[after], s)
