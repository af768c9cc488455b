"""tf through tf2_ros under real rclpy: its Buffer and TransformListener behind the lookup of
:class:`~rcbf_ros.node_logic.tf_buffer.TransformBuffer`.

On rclpy with tf2_ros importable the filter keeps no transforms of its own: tf2_ros's
``Buffer`` holds them, fed by a ``TransformListener`` (its own ``/tf`` and ``/tf_static``
subscriptions), and :class:`Tf2Lookup` answers the sources' lookups from it with the rules of
our buffer: the message's stamp, each link interpolated; time 0 the latest; a lookup tf2
refuses as extrapolation answered by the chain's newest (or oldest) transform when that is
within ``transform_tolerance`` of the stamp, else the fail-safe naming both frames.
:class:`Tf2Feed` checks and counts each transform before tf2 sees it, as
:meth:`~rcbf_ros.node_logic.sources.ObservationSources.read_tf` does on our runtime. The
lookup and the feed use only the methods of the buffer handed in (no import of ROS here):
tests give them a fake; :func:`start_tf2` imports tf2_ros.
"""
from __future__ import annotations

import bisect
import math
import re
from typing import Any, Callable, NamedTuple

from rcbf_ros.messages.sensor import MAX_FRAME_ID
from rcbf_ros.messages.tf import (
    MAX_TRANSFORMS,
    quoted,
    refusals_line,
    TF_MESSAGE,
    transform_refusal,
)
from rcbf_ros.node_logic.tf_buffer import (
    CONNECTIVITY,
    DEFAULT_CACHE_S,
    EXTRAPOLATION,
    FRAME,
    IDENTITY,
    MAX_FRAMES,
    MAX_SAMPLES,
    MAX_TOTAL_SAMPLES,
    NoTransform,
    Rigid,
    seconds_text,
    StampRules,
)
from rcbf_ros.node_logic.time_budget import TimeBudget

_S = 1_000_000_000
_KINDS = {'LookupException': FRAME, 'ConnectivityException': CONNECTIVITY,
          'ExtrapolationException': EXTRAPOLATION}
"""tf2's exception (by class name) -> the kind of :class:`NoTransform`; any other: FRAME."""
_EARLIEST = re.compile(r'(?:earliest data is at time|but only time) (-?\d+(?:\.\d+)?)')
"""The oldest time of a link in tf2's text of a lookup before its samples (cache.cpp:
'... into the past.  Requested time t but the earliest data is at time T', or with one
sample: '... at time t, but only time T is in the buffer'), in seconds to the microsecond."""
_MICROSECOND_MARGIN_NS = 2_000
"""tf2 prints that time to the microsecond from a double (~0.3 us apart at 2e9 s): where the
printed time falls just before the link's oldest sample, the lookup asks this much later."""
STALE_FRACTION = 10
"""tf2's dynamic data are cleared when a sample meets the total bound and at least 1/this of
the samples tf2 holds are older than the cache behind the buffer's time (:class:`Tf2Feed`)."""
MAX_RETRIES = 8
"""The most lookups moved to a later link's oldest time for one stamp (one per link of a
chain that starts after the stamp; a robot's chain to odom has two or three)."""


class Nanoseconds(NamedTuple):
    """A time as tf2_py reads one (an object with ``nanoseconds``): no rclpy Time needed."""

    nanoseconds: int


def _text(exc: BaseException) -> str:
    return ' '.join(str(exc).split())[:300]


class _Refused(NamedTuple):
    kind: str
    text: str


class Tf2Lookup:
    """Lookups between two frames in a tf2_ros Buffer with the interface and rules of
    :meth:`rcbf_ros.node_logic.tf_buffer.TransformBuffer.lookup_transform` (module docstring).

    Where tf2 refuses a stamp as extrapolation: after the chain's newest common time (tf2's
    lookup at time 0) by at most ``tolerance_ns``, that transform; before a link's oldest
    sample by at most ``tolerance_ns``, the chain at that oldest time (to the microsecond tf2
    reports). Unlike our buffer, which holds only the link whose samples end and
    interpolates the others at the stamp, the whole chain is then taken at the held time.
    """

    backend = 'tf2_ros'
    """Which buffer answers (our buffer has none: an introspection hook for tests and logs)."""

    def __init__(self, buffer: Any) -> None:
        """``buffer``: a tf2_ros Buffer, or any object with its ``lookup_transform_core(target,
        source, time)`` (time: an object with ``nanoseconds``; returns a TransformStamped;
        raises tf2's exceptions)."""
        self.buffer = buffer

    def lookup_transform(self, target: str, source: str, time_ns: int, *,
                         tolerance_ns: int = 0) -> Rigid | NoTransform:
        """The transform taking points in ``source`` to ``target`` at ``time_ns`` (0: the
        latest), held within ``tolerance_ns`` of the chain's newest or oldest time; else
        :class:`NoTransform` naming both frames. Never raises."""
        try:
            return self._lookup(target, source, int(time_ns), max(0, int(tolerance_ns)))
        except Exception as exc:  # a defect or an absurd argument: a refusal all the same
            return NoTransform(f'no transform from {quoted(str(source))} to '
                               f'{quoted(str(target))}: {type(exc).__name__}: {_text(exc)}',
                               FRAME)

    def _lookup(self, target: str, source: str, time_ns: int,
                tolerance_ns: int) -> Rigid | NoTransform:
        names = f'no transform from {quoted(source)} to {quoted(target)}'
        for frame in (target, source):
            if not isinstance(frame, str) or not frame:
                return NoTransform(f'{names}: empty frame id', FRAME)
        if target == source:
            return IDENTITY
        found = self._at(target, source, time_ns)
        if not isinstance(found, _Refused):
            return found[0]
        if found.kind != EXTRAPOLATION or time_ns == 0:
            return NoTransform(f'{names}: tf2: {found.text}', found.kind)
        latest = self._at(target, source, 0)
        if isinstance(latest, _Refused):  # two trees (tf2 named a link's data first), ...
            return NoTransform(f'{names}: tf2: {latest.text}', latest.kind)
        pose, newest_ns = latest
        at = f'{names} at {seconds_text(time_ns)}'
        tolerance = f'(transform_tolerance {seconds_text(tolerance_ns)})'
        if time_ns > newest_ns:
            if time_ns - newest_ns <= tolerance_ns:
                return pose
            return NoTransform(f'{at}: too old: the newest is at {seconds_text(newest_ns)}, '
                               f'{seconds_text(time_ns - newest_ns)} before {tolerance}',
                               EXTRAPOLATION)
        asked = None
        for _ in range(MAX_RETRIES):  # before a link's oldest sample: hold it, if near enough
            match = _EARLIEST.search(found.text)
            if match is None:
                break
            oldest_ns = round(float(match.group(1)) * 1e6) * 1000
            if not oldest_ns - time_ns <= tolerance_ns:
                return NoTransform(f'{at}: too new: a link starts at {seconds_text(oldest_ns)}, '
                                   f'{seconds_text(oldest_ns - time_ns)} after {tolerance} '
                                   f'(tf2: {found.text})', EXTRAPOLATION)
            # the printed time, or just after it when that one is refused again (rounded)
            ask = min(oldest_ns if asked is None or oldest_ns > asked
                      else asked + _MICROSECOND_MARGIN_NS, newest_ns)
            if ask == asked:
                break
            asked = ask
            held = self._at(target, source, ask)
            if not isinstance(held, _Refused):
                return held[0]
            if held.kind != EXTRAPOLATION:
                return NoTransform(f'{names}: tf2: {held.text}', held.kind)
            found = held
        return NoTransform(f'{at}: tf2: {found.text} {tolerance}', EXTRAPOLATION)

    def _at(self, target: str, source: str, time_ns: int) -> tuple[Rigid, int] | _Refused:
        """tf2's transform at ``time_ns`` and its stamp (ns), or why not (the kind by tf2's
        exception, its text in one line)."""
        try:
            found = self.buffer.lookup_transform_core(target, source, Nanoseconds(time_ns))
        except Exception as exc:  # tf2's exceptions, or TypeError/ValueError of a bad time
            return _Refused(_KINDS.get(type(exc).__name__, FRAME), _text(exc))
        tr, q = found.transform.translation, found.transform.rotation
        stamp = found.header.stamp
        rotation = (float(q.x), float(q.y), float(q.z), float(q.w))
        norm = math.sqrt(math.fsum(v * v for v in rotation))
        if not (math.isfinite(norm) and norm > 0.5):
            return _Refused(FRAME, f'tf2 gave the rotation {rotation}, not a unit quaternion')
        pose = Rigid(tuple(v / norm for v in rotation),  # type: ignore[arg-type]
                     (float(tr.x), float(tr.y), float(tr.z)))
        return pose, int(stamp.sec) * _S + int(stamp.nanosec)


class Tf2Feed(StampRules):
    """The transforms of ``/tf`` and ``/tf_static`` (TFMessage objects, as the listener
    receives them) checked as on our runtime, then handed to tf2_ros's buffer.

    The same checks and counts as :meth:`ObservationSources.read_tf`
    (:data:`~rcbf_ros.node_logic.sources.TF_COUNT_KEYS`): a message of more than
    :data:`~rcbf_ros.messages.tf.MAX_TRANSFORMS` transforms, or with a frame id longer than
    :data:`~rcbf_ros.messages.sensor.MAX_FRAME_ID`, is refused whole; a transform that
    :func:`~rcbf_ros.messages.tf.transform_refusal` refuses, one naming a new frame beyond
    ``max_frames``, one older than its link's cache (tf2's TF_OLD_DATA), one stamped more than
    the cache from the clock, or one more sample of a link holding ``max_samples`` within its
    cache or of ``max_total_samples`` in all, is refused alone, in our buffer's words (where
    our buffer drops a full link's oldest sample, the new one is refused here: tf2 cannot be
    told to drop one). tf2 bounds a link's samples by its cache's time alone (and keeps
    several of one stamp): these bounds are kept here, from the stamps handed to tf2, pruned
    as tf2 prunes its cache (behind the link's newest).

    Time as in our buffer (:mod:`rcbf_ros.node_logic.tf_buffer`): the clock (``now_ns``) or
    the data's newest stamp; its going back clears tf2's dynamic data (``clear()``, which keeps
    the static transforms). tf2 drops nothing else by itself: a link that stops keeps its last
    cache's samples, and a frame's name stays for good. So a link whose samples all lie older
    than the cache behind the buffer's time no longer counts among the frames, and when a
    sample meets the total bound while at least :data:`STALE_FRACTION` of it is such expired
    data, tf2's dynamic data are cleared; when a new frame would make tf2 hold more than
    ``max_frames`` names, ``renew`` (if given) makes a new buffer and the static transforms are
    handed to it again. Each costs the live links their samples up to their next ones, and
    happens only after a flood: the bounds refuse while it lasts, never after.
    """

    def __init__(self, buffer: Any, counts: dict[str, int], *, cache_s: float = DEFAULT_CACHE_S,
                 max_frames: int = MAX_FRAMES, max_samples: int = MAX_SAMPLES,
                 max_total_samples: int = MAX_TOTAL_SAMPLES,
                 renew: Callable[[], Any] | None = None) -> None:
        """``buffer``: a tf2_ros Buffer (``set_transform``, ``set_transform_static``,
        ``clear``) whose cache is ``cache_s``; ``counts``: the counts to keep (``messages``,
        ``refused``, ``transforms_refused``); ``renew``: a new, empty buffer of the same kind
        (the lookup's buffer too), or None (then a frame beyond tf2's ``max_frames`` names is
        refused)."""
        self.buffer = buffer
        self.counts = counts
        self.cache_ns = int(cache_s * _S)
        self.max_frames = max_frames
        self.max_samples = max_samples
        self.max_total_samples = max_total_samples
        self.renew = renew
        self.clears = 0
        """How often tf2's dynamic data were cleared (time going back, expired data)."""
        self.renewals = 0
        """How often a new buffer replaced tf2's (too many frame names)."""
        self._links: dict[str, tuple[str, bool]] = {}
        """Per live child frame, its parent and whether it is static."""
        self._named: dict[str, int] = {}
        """Every frame a live link names: how many do."""
        self._handed: set[str] = set()
        """Every frame handed to the buffer since it was made (tf2 never forgets one)."""
        self._static: dict[str, Any] = {}
        """Per static child frame, its latest transform (handed again to a new buffer)."""
        self._stamps: dict[str, list[int]] = {}
        """Per dynamic child frame, the stamps tf2 holds (sorted), pruned as tf2 prunes."""
        self._samples = 0
        """The stamps of all children together."""
        self._clock_ns: int | None = None
        self._data_ns: int | None = None
        self._swept_ns: int | None = None
        self._stale_ns: int | None = None
        """The horizon at which the expired samples were last counted (at the total bound)."""

    @property
    def frames(self) -> frozenset[str]:
        """Every frame a live link names (a frame whose links all expired is forgotten)."""
        return frozenset(self._named)

    def take(self, message: Any, *, static: bool, now_ns: int | None = None) -> str:
        """Check ``message`` (a tf2_msgs TFMessage) and hand its good transforms to tf2: ''
        when every transform was kept, else one line saying what was refused, as
        :meth:`ObservationSources.read_tf` says it. ``now_ns``: the node's clock (ns). Never
        raises."""
        counts = self.counts
        counts['messages'] += 1
        refused: list[str] = []
        try:
            transforms = message.transforms
            if len(transforms) > MAX_TRANSFORMS:
                counts['refused'] += 1
                return (f'{TF_MESSAGE}: transforms has {len(transforms)} entries, more than '
                        f'the bound {MAX_TRANSFORMS}')
            for k, transform in enumerate(transforms):
                for field, frame in (('header.frame_id', transform.header.frame_id),
                                     ('child_frame_id', transform.child_frame_id)):
                    if len(frame) > MAX_FRAME_ID:
                        counts['refused'] += 1
                        return (f'{TF_MESSAGE}: transforms[{k}].{field}: {len(frame)} '
                                f'characters, more than the bound {MAX_FRAME_ID}')
            for k, transform in enumerate(transforms):
                why = self._take(k, transform, static, now_ns)
                if why:
                    refused.append(why)
        except Exception as exc:  # not a TFMessage: refused whole, in one line
            counts['refused'] += 1
            return f'{TF_MESSAGE}: {type(exc).__name__}: {_text(exc)}'[:200]
        counts['transforms_refused'] += len(refused)
        return refusals_line(refused)

    def _take(self, k: int, transform: Any, static: bool, now_ns: int | None) -> str:
        """Transform ``k`` of a message to tf2, or why not (a bad value naming its index, a
        bound or tf2 naming its frames, as read_tf names them)."""
        parent, child = transform.header.frame_id, transform.child_frame_id
        parent, child = parent[parent.startswith('/'):], child[child.startswith('/'):]
        tr, q = transform.transform.translation, transform.transform.rotation
        why = transform_refusal(parent, child, (float(tr.x), float(tr.y), float(tr.z)),
                                (float(q.x), float(q.y), float(q.z), float(q.w)))
        if why:
            return f'transforms[{k}] {why}'
        names = f'{quoted(parent)} -> {quoted(child)}'
        stamp = int(transform.header.stamp.sec) * _S + int(transform.header.stamp.nanosec)
        why = self._admitted(names, parent, child, stamp, static, now_ns)
        if why:
            return why
        unknown = {parent, child} - self._handed
        if len(self._handed) + len(unknown) > self.max_frames:
            if self.renew is None or not self._renew(parent, child):
                return (f'{names}: refused, tf2 holds {len(self._handed)} frame names (at '
                        f'most {self.max_frames})')
        if not static:
            why = self._room(names, child, stamp)
            if why:
                return why
        try:
            if static:
                self.buffer.set_transform_static(transform, 'default_authority')
            else:
                self.buffer.set_transform(transform, 'default_authority')
        except Exception as exc:  # tf2's refusal of a value our checks let through
            return f'{names}: tf2: {type(exc).__name__}: {_text(exc)}'
        self._handed.update((parent, child))
        self._link(child, parent, static)
        if static:
            self._static[child] = transform
        else:
            self._static.pop(child, None)
            stamps = self._stamps.setdefault(child, [])
            if stamps:  # tf2 drops the link's samples older than the cache behind its newest
                drop = bisect.bisect_left(stamps, stamps[-1] - self.cache_ns)
                del stamps[:drop]
                self._samples -= drop
            bisect.insort(stamps, stamp)
            self._samples += 1
        return ''

    def _link(self, child: str, parent: str, static: bool) -> None:
        """``child``'s link is to ``parent`` (static or not): the live frames follow."""
        if self._links.get(child) == (parent, static):
            return
        self._unlink(child)
        self._links[child] = (parent, static)
        for frame in (parent, child):
            self._named[frame] = self._named.get(frame, 0) + 1

    def _unlink(self, child: str) -> None:
        """``child``'s link no longer live, nor its frames no other live link names."""
        link = self._links.pop(child, None)
        if link is None:
            return
        for frame in (link[0], child):
            left = self._named[frame] - 1
            if left:
                self._named[frame] = left
            else:
                del self._named[frame]

    def _clear(self) -> None:
        """tf2's dynamic data cleared (its static transforms stay), and our books of them."""
        self.buffer.clear()
        self._forget_dynamic()
        self.clears += 1

    def _forget_dynamic(self) -> None:
        for child, (_, static) in list(self._links.items()):
            if not static:
                self._unlink(child)
        self._stamps.clear()
        self._samples = 0
        self._data_ns = self._swept_ns = None

    def _renew(self, parent: str, child: str) -> bool:
        """A new buffer for tf2, the static transforms handed to it again, when that leaves
        room for ``parent`` and ``child``'s names; whether it did."""
        names = {link[0] for link in self._links.values() if link[1]} | {
            frame for frame, link in self._links.items() if link[1]}
        if len(names | {parent, child}) > self.max_frames:
            return False
        buffer = self.renew()  # type: ignore[misc]
        for transform in self._static.values():
            buffer.set_transform_static(transform, 'default_authority')
        self.buffer, self._handed = buffer, names
        self._forget_dynamic()
        self.renewals += 1
        return True

    def _expire(self, *, due: bool) -> bool:
        """Links whose samples all lie older than the cache behind the buffer's time are no
        longer live: when that time has moved on by 1/SWEEP_FRACTION of the cache since the
        last time, or at all if ``due`` (a bound is reached). Whether any time had passed."""
        horizon = self._sweep_horizon(due)
        if horizon is None:
            return False
        for child, (_, static) in list(self._links.items()):
            stamps = self._stamps.get(child)
            if not static and (not stamps or stamps[-1] < horizon):
                self._unlink(child)
        return True

    def _room(self, names: str, child: str, stamp: int) -> str:
        """Why link ``child`` has no room for a sample at ``stamp`` ('' when it has). The books
        follow tf2's cache (cache.cpp): before it inserts, a link drops its samples older than
        the cache behind its newest, so those older than the cache behind ``stamp`` stay in
        tf2 until the link's next sample. They count in all, not in the link's bound (else a
        full link could never move on)."""
        stamps = self._stamps.get(child, [])
        if stamps:
            if stamp < stamps[-1] - self.cache_ns:
                return (f'{names}: stamp {seconds_text(stamp)} is older than the cache '
                        f'({seconds_text(self.cache_ns)} behind the newest, '
                        f'{seconds_text(stamps[-1])})')
        kept = len(stamps) - bisect.bisect_left(stamps, stamp - self.cache_ns)
        if kept >= self.max_samples:
            return (f'{names}: refused, the link holds {kept} samples within '
                    f'{seconds_text(self.cache_ns)} (at most {self.max_samples})')
        def freed() -> int:  # what tf2 drops of the link as it takes the sample
            held = self._stamps.get(child)
            return bisect.bisect_left(held, held[-1] - self.cache_ns) if held else 0

        if self._samples - freed() >= self.max_total_samples:
            self._expire(due=True)
            horizon = self._swept_ns
            if horizon is not None and horizon != self._stale_ns:  # once per horizon
                self._stale_ns = horizon
                expired = sum(bisect.bisect_left(held, horizon)
                              for held in self._stamps.values())
                if expired * STALE_FRACTION >= self._samples:
                    self._clear()  # tf2 keeps a stopped link's samples: clear them all
        if self._samples - freed() >= self.max_total_samples:
            return (f'{names}: refused, the buffer holds {self._samples} samples (at most '
                    f'{self.max_total_samples})')
        return ''


class Tf2(NamedTuple):
    """tf2_ros at work for a node (:func:`start_tf2`)."""

    lookup: Tf2Lookup
    """The sources' lookups (``ObservationSources(config, tf=lookup)``)."""
    feed: Tf2Feed
    """Checks and counts each message (point ``feed.counts`` at the sources' tf counts)."""
    listener: Any
    """The tf2_ros TransformListener (its subscriptions live as long as it does)."""


def start_tf2(node: Any, on_message: Callable[[str, str], None], *, qos: Any,
              static_qos: Any, budget: TimeBudget | None = None) -> Tf2 | str:
    """On ``node`` (an rclpy Node): a tf2_ros Buffer (cache :data:`DEFAULT_CACHE_S`) and a
    TransformListener (``qos`` on ``/tf``, ``static_qos`` on ``/tf_static``) whose messages
    go through a :class:`Tf2Feed`; ``on_message(topic, reason)`` after each message (reason
    '' when all was kept). A ``/tf`` message that comes while ``budget`` is spent is refused
    unread (counted in ``refused``). Or why tf2_ros cannot be used (one line: not
    importable)."""
    try:
        from rclpy.duration import Duration
        import tf2_ros
    except ImportError as exc:
        return f'tf2_ros is not importable ({_text(exc)})'
    def new_buffer() -> Any:
        return tf2_ros.Buffer(cache_time=Duration(nanoseconds=int(DEFAULT_CACHE_S * _S)))

    def renew() -> Any:  # the feed's new buffer is the lookup's too
        lookup.buffer = new_buffer()
        return lookup.buffer

    lookup = Tf2Lookup(new_buffer())
    feed = Tf2Feed(lookup.buffer, dict.fromkeys(('messages', 'refused', 'transforms_refused'), 0),
                   renew=renew)
    clock = node.get_clock()

    class _Listener(tf2_ros.TransformListener):
        """tf2_ros's listener, each message through the feed (at the node's clock)."""

        def callback(self, data: Any) -> None:
            def reading() -> str:
                return feed.take(data, static=False, now_ns=clock.now().nanoseconds)
            on_message('/tf', reading() if budget is None else budget.read(reading, feed.counts))

        def static_callback(self, data: Any) -> None:
            on_message('/tf_static', feed.take(data, static=True,
                                               now_ns=clock.now().nanoseconds))

    listener = _Listener(lookup.buffer, node, qos=qos, static_qos=static_qos)
    return Tf2(lookup, feed, listener)
