"""The filter's observation sources: the latest points of each scan or cloud, fresh and in the
state's frame, for every decision.

Each source (``observation_sources``, ``<name>.*``; :class:`rcbf_ros.core.config.SourceConfig`)
keeps the points of its latest message, in the message's frame, as
:mod:`rcbf_ros.messages.sensor` reads them. At a decision, :meth:`ObservationSources.points`
gives every source's points in the state's frame, or why the filter must answer with the
fail-safe: a source without a message yet, with one older than its ``timeout_s``, whose latest
message was refused, or whose frame cannot be placed in the state's.

Frames: points in ``odom_frame_id`` (the state's frame) are taken as they are. Any other frame
goes through tf (the transforms of :meth:`ObservationSources.read_tf`, kept in a
:class:`~rcbf_ros.node_logic.tf_buffer.TransformBuffer`) at the message's stamp, within
``transform_tolerance``. Where tf does not join the frame to ``odom_frame_id`` (no
odom -> base_link on tf) but the frame is ``base_frame_id`` or joined to it, the points go to
the robot's frame, then to the state's through the robot's pose at the message's stamp, from
the states (:meth:`ObservationSources.note_state`, by tf's rules: interpolated, or held within
``transform_tolerance``; none: the fail-safe). Where tf joins the
frames but has no transform at the stamp (too old, too new, a loop), the fail-safe. Once
placed, points are bounded by their distance from the robot (:data:`MAX_RANGE`), never by a
frame's origin; all sources together by :data:`MAX_POINTS`. No middleware: the node hands in
bytes and times.
"""
from __future__ import annotations

from dataclasses import dataclass, field
import math
from typing import Any, Callable, Sequence

import numpy as np

from rcbf_ros.core.config import SourceConfig, SourceParameters
from rcbf_ros.messages import sensor
from rcbf_ros.messages.tf import quoted, refusals_line, tf_transforms
from rcbf_ros.node_logic.pose_history import PoseHistory
from rcbf_ros.node_logic.tf_buffer import (
    CONNECTIVITY,
    FRAME,
    IDENTITY,
    NoTransform,
    Rigid,
    TransformBuffer,
)

SENSOR_MESSAGES = {'scan': sensor.LASER_SCAN, 'pointcloud': sensor.POINT_CLOUD2,
                   'range': sensor.RANGE}
"""The message type of each ``<name>.type`` of an observation source."""

COUNT_KEYS = ('messages', 'refused', 'stale', 'untransformed')
"""Per source: messages received, messages refused (undecodable, wrong layout, too large),
decisions answered with the fail-safe because the source was stale or had no message yet,
and because its points had no transform to the state's frame."""
MAX_POINTS = 100_000
"""The most points of all sources together a decision takes (each source's latest message, its
valid points after the z band and thinning); more gives the fail-safe naming every source and
its count. The filter answers this many in about 20 ms (benchmarks/bench_sources.py); every
source may still hold a full message (:data:`rcbf_ros.messages.sensor.MAX_POINTS`)."""
MAX_RANGE = 1.0e4
"""Points farther than this (m) from the robot's position in the state, once placed in the
state's frame, are left out of the decision: no sensor sees that far, and the row of a point
at distance d binds only where the robot's speed and the disturbance box reach about alpha d /
2 (5 km/s at alpha = 1 and this range). Counted from the robot, not from a frame's origin: a
robot far from ``odom_frame_id``'s origin keeps every point around it."""
MIDDLEWARE_TOPICS = ('/rosout', '/parameter_events', '/tf', '/tf_static',
                     '~/get_parameters', '~/set_parameters', '~/set_parameters_atomically',
                     '~/describe_parameters', '~/list_parameters', '~/get_parameter_types',
                     '~/get_type_description')
"""The middleware's own topics and the node's parameter services, which no source may take
(:func:`topic_refusal`): a log line, a parameter event or a transform is not a scan."""
MAX_WIDENING = 0.5
"""The most (m) a cloud's circles are widened for a tilted frame; more refuses the source."""
_HALF_RANGE = 0.5 * MAX_RANGE
"""Points within this (m) of the robot along each axis are within MAX_RANGE of it."""
_NEAR_REACH = 0.1 * _HALF_RANGE
"""Points placed through the robot's frame within this (m) of it pass
:meth:`ObservationSources._near`'s test for all near, which is then skipped: a sum rounded to
the nearest float lies at most twice as far from the robot's coordinate (itself a float) as
the exact sum, so each difference of the placement's two sums stays within 6 x this, wherever
the robot is."""
_largest, _least = np.maximum.reduce, np.minimum.reduce
TF_COUNT_KEYS = ('messages', 'refused', 'transforms_refused')
"""Of ``/tf`` and ``/tf_static`` together: messages received, messages refused whole
(undecodable, too many transforms), transforms refused alone (NaN, not a unit quaternion, a
frame its own parent, data older than the cache, ...)."""


def topic_refusal(config: SourceConfig | None, own_topics: Sequence[str],
                  resolve: Callable[[str], str]) -> str:
    """Why the node's topics cannot be used, in one line naming both of two that clash ('' when
    they can): every name the node uses (:data:`MIDDLEWARE_TOPICS`, then ``own_topics``, then
    each source's ``<name>.topic``) resolved by ``resolve`` (the node's resolve_topic_name:
    remaps and namespace included), and any two that resolve to one name refused, as is a name
    that does not resolve. A node topic on another (``cmd_proposed`` and ``cmd_safe`` on one
    topic: the filter would answer its own output, the controller reach the base unfiltered),
    on a middleware topic (``state`` on ``/tf``), or a source on either (its answers would come
    back as sensor data). Names are compared resolved: ``scan`` and ``/scan`` are one topic in
    the root namespace. ``config`` None: no sources."""
    def resolved(key: str, topic: str) -> str:
        try:
            return resolve(topic)
        except Exception as exc:  # the runtime's refusal of the name, in one line
            raise ValueError(f'{key}: {topic!r} is not a valid topic name '
                             f'({" ".join(str(exc).split())[:160]})') from None
    try:
        holders: dict[str, tuple[str, bool]] = {}  # resolved -> (who, one of the node's own)
        for topic in dict.fromkeys((*MIDDLEWARE_TOPICS, *own_topics)):
            full = resolved(topic, topic)
            if full in holders:
                return (f'{holders[full][0]} and {topic} both resolve to {full}; each of the '
                        "node's topics needs its own (see the remaps and namespace)")
            holders[full] = (topic, True)
        for name, params in (config.sources if config is not None else ()):
            key = f'{name}.topic'
            full = resolved(key, params.topic)
            if full in holders:
                return f'{key}: {params.topic!r} resolves to {full}, {_holder(*holders[full])}'
            holders[full] = (key, False)
    except ValueError as exc:
        return str(exc)
    return ''


def _holder(name: str, own: bool) -> str:
    """Who holds a topic, for :func:`topic_refusal`'s line."""
    if not own:
        return f'the topic of {name} too'
    kind = 'service' if name.startswith('~/') else 'topic'
    return f"the node's own {name} {kind}"


@dataclass
class _Source:
    """One source's parameters, latest points and counts."""

    name: str
    params: SourceParameters
    points: np.ndarray | None = None
    """(N, 2) in ``frame_id`` (None: no usable message yet)."""
    spread: float = 0.0
    reach: float = math.inf
    """A bound (m) on the points' distance from their frame's origin (inf: none)."""
    frame_id: str = ''
    stamp_ns: int = 0
    received_ns: int = 0
    refusal: str = ''
    """Why the latest message was refused ('' when it was read)."""
    counts: dict[str, int] = field(default_factory=lambda: dict.fromkeys(COUNT_KEYS, 0))


class ObservationSources:
    """The latest points of every source, and the fail-safe's reason when they cannot be used
    (module docstring)."""

    def __init__(self, config: SourceConfig, *, tf: Any = None) -> None:
        self.config = config
        self._sources = {name: _Source(name, params) for name, params in config.sources}
        self.tf = TransformBuffer() if tf is None else tf
        """The transforms of ``/tf`` and ``/tf_static`` (:meth:`read_tf`), or ``tf``: any
        object with TransformBuffer's ``lookup_transform`` (rcbf_ros.ros.tf2_buffer's over
        tf2_ros, which is fed by its own listener)."""
        self.tf_counts = dict.fromkeys(TF_COUNT_KEYS, 0)
        """Counts of the tf messages (:data:`TF_COUNT_KEYS`)."""
        self.poses = PoseHistory()
        """The robot's pose at each state's stamp (:meth:`note_state`): where tf does not
        join a source's frame to the state's, its points are placed with the pose at the
        message's stamp."""

    @property
    def names(self) -> list[str]:
        """The sources' names, in ``observation_sources`` order."""
        return list(self._sources)

    def params(self, name: str) -> SourceParameters:
        """The parameters of source ``name``."""
        return self._sources[name].params

    def counts(self) -> dict[str, dict[str, int]]:
        """Per source, a copy of its counts (:data:`COUNT_KEYS`)."""
        return {name: dict(source.counts) for name, source in self._sources.items()}

    def read(self, name: str, data: Any, *, received_ns: int) -> str:
        """Take one message of source ``name`` (CDR bytes): '' when read, else the one-line
        reason it was refused. A refused message replaces the source's points by its refusal:
        the fail-safe until a message is read. Never raises."""
        source = self._sources[name]
        source.counts['messages'] += 1
        try:
            params = source.params
            if params.type == 'scan':
                out = sensor.scan_points(data)
            elif params.type == 'range':
                out = sensor.range_points(data, obstacles_angle=params.obstacles_angle)
            else:
                out = sensor.cloud_points(data, min_height=params.min_height,
                                          max_height=params.max_height,
                                          voxel_size=params.voxel_size)
        except Exception as exc:  # the readers never raise; kept so that no path escapes
            out = sensor.Refused(f'internal error: {type(exc).__name__}: {exc}'[:200])
        if isinstance(out, sensor.Refused):
            source.counts['refused'] += 1
            source.refusal = ' '.join(out.reason.split())
            source.points = None
            return source.refusal
        source.points, source.spread, source.reach = out.points, out.spread, out.reach
        source.frame_id, source.stamp_ns = out.frame_id, out.stamp_ns
        source.received_ns, source.refusal = received_ns, ''
        return ''

    def read_tf(self, data: Any, *, static: bool, now_ns: int | None = None) -> str:
        """Take one ``/tf`` (``static`` False) or ``/tf_static`` message (CDR bytes): '' when
        every transform was kept, else one line saying what was refused (the message whole,
        or its first refused transform and how many more). ``now_ns``: the node's clock (the
        buffer's time: :mod:`rcbf_ros.node_logic.tf_buffer`). Never raises."""
        counts = self.tf_counts
        counts['messages'] += 1
        try:
            out = tf_transforms(data)
            if isinstance(out, sensor.Refused):
                counts['refused'] += 1
                return ' '.join(out.reason.split())
            refused = list(out.refused)
            for transform in out.transforms:
                why = self.tf.set_transform(transform, static=static, now_ns=now_ns)
                if why:
                    refused.append(why)
        except Exception as exc:  # the readers never raise; kept so that no path escapes
            counts['refused'] += 1
            return f'internal error: {type(exc).__name__}: {" ".join(str(exc).split())}'[:200]
        counts['transforms_refused'] += len(refused)
        return refusals_line(refused)

    def note_state(self, state: np.ndarray, *, stamp_ns: int, now_ns: int | None = None
                   ) -> str:
        """Keep the robot's pose in ``state`` (position and heading) at ``stamp_ns``: the
        state's header stamp, or its receipt on the clock the sources' stamps are aged on
        (``now_ns``, that clock at the receipt: its going back clears the poses kept).
        '' when kept, else why not (no heading in the state, a pose that is not finite).
        Never raises."""
        config = self.config
        if config.heading_index is None:
            return 'no heading in the state (obstacles.heading_index)'
        try:
            i, j = config.position_indices
            return self.poses.add(int(stamp_ns), float(state[i]), float(state[j]),
                                  float(state[config.heading_index]), now_ns=now_ns)
        except Exception as exc:  # a state of the wrong length: the decision says why
            return f'pose not kept: {type(exc).__name__}: {" ".join(str(exc).split())}'[:200]

    def points(self, state: np.ndarray, *, now_ns: int, stamp_now_ns: int
               ) -> tuple[np.ndarray, np.ndarray | float] | str:
        """Every source's points in the state's frame, and their spread (one value, or one per
        point where the sources' differ), at ``state`` (n_x); else the fail-safe's reason,
        naming the source.

        A message's age is counted from its header stamp on the node's clock
        (``stamp_now_ns``, as collision_monitor counts ``source_timeout``), and never from
        later than its receipt (``now_ns`` and the message's receipt, on the monotonic clock):
        a stamp in the future does not keep a source fresh. More than :data:`MAX_POINTS`
        points in all give the fail-safe (before any is placed); points farther than
        :data:`MAX_RANGE` from the robot once placed are left out.
        """
        parts: list[np.ndarray] = []
        spreads: list[tuple[float, int]] = []
        counts = {name: len(source.points) for name, source in self._sources.items()
                  if source.points is not None and not source.refusal}
        if sum(counts.values()) > MAX_POINTS:
            listed = ', '.join(f'{name} ({count} points)' for name, count in counts.items())
            return (f'sources {listed}: {sum(counts.values())} points in all, more than the '
                    f'bound {MAX_POINTS}')
        for name, source in self._sources.items():
            timeout = source.params.timeout_s
            if source.refusal:
                return f'source {name}: latest message refused: {source.refusal}'
            if source.points is None:
                source.counts['stale'] += 1
                return f'source {name}: no message yet on {source.params.topic}'
            age = max((stamp_now_ns - source.stamp_ns) * 1e-9,
                      (now_ns - source.received_ns) * 1e-9)
            if not age <= timeout:
                source.counts['stale'] += 1
                return (f'source {name}: latest message {age:.3f} s old > {name}.timeout_s '
                        f'{timeout:g}')
            placed = self._placed(source)
            if isinstance(placed, str):
                source.counts['untransformed'] += 1
                return f'source {name}: {placed}'
            points, widening, reach = placed
            # the range test where the robot's frame bounds the points' distance from it
            near = points if reach <= _NEAR_REACH else self._near(points, state)
            if isinstance(near, str):
                source.counts['untransformed'] += 1
                return f'source {name}: {near}'
            points = near
            parts.append(points)
            spreads.append((source.spread + widening, len(points)))
        if not parts:
            return np.zeros((0, 2)), 0.0
        widths = {float(spread) for spread, _ in spreads}
        if len(widths) == 1:  # one spread for every point (the common case)
            spread_out: np.ndarray | float = widths.pop()
        else:
            spread_out = np.concatenate([np.full(n, spread) for spread, n in spreads])
        return (parts[0] if len(parts) == 1 else np.concatenate(parts)), spread_out

    def sense(self, safety_filter: Any, state: np.ndarray, *, now_ns: int, stamp_now_ns: int
              ) -> str:
        """Set ``safety_filter``'s sensor points for ``state`` (:meth:`points`): '' when set,
        else the fail-safe's reason (the filter's points are then emptied)."""
        out = self.points(state, now_ns=now_ns, stamp_now_ns=stamp_now_ns)
        if isinstance(out, str):
            safety_filter.set_points(np.zeros((0, 2)))
            return out
        safety_filter.set_points(*out)
        return ''

    def _placed(self, source: _Source) -> tuple[np.ndarray, float, float] | str:
        """``source``'s points in the state's frame (module docstring: tf at the message's
        stamp, else the robot's frame and its pose at that stamp), how much wider (m) their
        circles must be (:meth:`_widening`) and a bound on their distance from the robot where
        it is known (:data:`_NEAR_REACH`; else inf), or why not (one line naming the frames)."""
        config = self.config
        points, frame = source.points, source.frame_id
        assert points is not None
        odom, base = config.odom_frame_id, config.base_frame_id
        if frame == odom:
            return points, 0.0, math.inf
        tolerance_ns = round(config.transform_tolerance * 1e9)
        to_odom = self.tf.lookup_transform(odom, frame, source.stamp_ns,
                                           tolerance_ns=tolerance_ns)
        if not isinstance(to_odom, NoTransform):
            widening = self._widening(source, to_odom, odom)
            if isinstance(widening, str):
                return widening
            return to_odom.apply_planar(points), widening, math.inf
        if to_odom.kind not in (FRAME, CONNECTIVITY):  # joined, but not at this stamp
            return to_odom.reason
        to_base = IDENTITY if frame == base else self.tf.lookup_transform(
            base, frame, source.stamp_ns, tolerance_ns=tolerance_ns)
        if isinstance(to_base, NoTransform):
            if to_base.kind not in (FRAME, CONNECTIVITY):
                return to_base.reason
            return (f"frame {quoted(frame)} is placed neither in the state's {quoted(odom)} "
                    f"nor in the robot's {quoted(base)} by tf ({to_odom.reason}; "
                    f'{to_base.reason})')
        widening = self._widening(source, to_base, base)
        if isinstance(widening, str):
            return widening
        reach = source.reach
        if to_base is not IDENTITY:
            points = to_base.apply_planar(points)
            # twice the reach: room for a rotation's rounding
            reach = 2.0 * reach + math.hypot(*to_base.translation[:2])
        placed = self._to_state_frame(points, source.stamp_ns, tolerance_ns)
        return placed if isinstance(placed, str) else (placed, widening, reach)

    @staticmethod
    def _widening(source: _Source, rigid: Rigid, target: str) -> float | str:
        """How far (m) a cloud's point may lie from where it is placed: its points are taken at
        z = 0 of their frame, so a frame tilted by t from ``target``'s vertical moves a point
        of height z by |z| sin t; the band bounds |z| (a scan's points lie at z = 0: 0)."""
        params = source.params
        if params.type != 'pointcloud':  # a scan's or a range's points lie at z = 0
            return 0.0
        x, y, z, w = rigid.rotation
        sin_tilt = math.hypot(2 * (x * z + y * w), 2 * (y * z - x * w))
        if sin_tilt < 1e-9:  # level (rounding of a yaw-only quaternion)
            return 0.0
        height = max(abs(params.min_height), abs(params.max_height))
        widening = height * sin_tilt
        if not math.isfinite(widening) or widening > MAX_WIDENING:
            tilt = math.degrees(math.acos(max(-1.0, min(1.0, 1 - 2 * (x * x + y * y)))))
            return (f'frame {quoted(source.frame_id)} is tilted {tilt:.1f} deg from '
                    f"{quoted(target)}'s vertical: its points, up to {height:g} m high "
                    f'({source.name}.min_height, .max_height), would lie up to {widening:.3g} m '
                    f'from where they are placed (at most {MAX_WIDENING:g})')
        return widening

    def _near(self, points: np.ndarray, state: np.ndarray) -> np.ndarray | str:
        """``points`` (in the state's frame) within :data:`MAX_RANGE` of the robot's position
        in ``state``, or why not (a position that is not finite)."""
        i, j = self.config.position_indices
        x, y = float(state[i]), float(state[j])
        if not (math.isfinite(x) and math.isfinite(y)):
            return "the state's position is not finite"
        px, py = points[:, 0], points[:, 1]
        if not px.size or (_largest(px) - x <= _HALF_RANGE and x - _least(px) <= _HALF_RANGE
                           and _largest(py) - y <= _HALF_RANGE
                           and y - _least(py) <= _HALF_RANGE):
            # every point within MAX_RANGE / 2 of the robot on each axis (rounding is
            # monotonic: no point's difference exceeds the extreme's): all near, no per-point
            # check (a NaN fails the comparisons and takes the per-point check)
            return points
        dx, dy = px - x, py - y
        near = (np.abs(dx) <= MAX_RANGE) & (np.abs(dy) <= MAX_RANGE)
        near &= dx * dx + dy * dy <= MAX_RANGE * MAX_RANGE
        return points if near.all() else points[near]

    def _to_state_frame(self, points: np.ndarray, stamp_ns: int,
                        tolerance_ns: int) -> np.ndarray | str:
        """Points in the robot's frame, taken at ``stamp_ns`` -> the state's: rotated by the
        heading, moved to the position, both of the robot's pose at that stamp
        (:attr:`poses`, within ``tolerance_ns``)."""
        config = self.config
        if config.heading_index is None:
            return (f'frame {config.base_frame_id!r} needs the heading in the state '
                    '(obstacles.heading_index)')
        pose = self.poses.at(stamp_ns, tolerance_ns=tolerance_ns)
        if isinstance(pose, str):
            return (f'no pose of the robot ({quoted(config.base_frame_id)} in '
                    f"{quoted(config.odom_frame_id)}) at the message's stamp from the states: "
                    f'{pose}')
        x, y, heading = pose
        cos, sin = math.cos(heading), math.sin(heading)
        # both columns at once, as (2, N): (x + cos px) + (-sin py) and (y + sin px) + cos py,
        # the sums of x + cos px - sin py and y + sin px + cos py in their order (negation is
        # exact); (N, 2) out, its columns contiguous
        factors = np.array([[cos, x, -sin], [sin, y, cos]])
        out = np.multiply(points[:, 0], factors[:, :1])
        out += factors[:, 1:2]
        out += np.multiply(points[:, 1], factors[:, 2:])
        return out.T
