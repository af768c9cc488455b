"""The filter's observation sources: the latest points of each scan or cloud, fresh and in the
state's frame, for every decision.

Each source (``observation_sources``, ``<name>.*``; :class:`rcbf_ros.core.config.SourceConfig`)
keeps the points of its latest message, in the message's frame, as
:mod:`rcbf_ros.messages.sensor` reads them. At a decision, :meth:`ObservationSources.points`
gives every source's points in the state's frame, or why the filter must answer with the
fail-safe: a source without a message yet, with one older than its ``timeout_s``, whose latest
message was refused, or in a frame other than the state's (``odom_frame_id``) or the robot's
(``base_frame_id``: taken to the state's frame through the pose in the state). No middleware:
the node hands in bytes and times.
"""
from __future__ import annotations

from dataclasses import dataclass, field
import math
from typing import Any, Callable, Sequence

import numpy as np

from rcbf_ros.core.config import SourceConfig, SourceParameters
from rcbf_ros.messages import sensor

SENSOR_MESSAGES = {'scan': 'sensor_msgs/msg/LaserScan',
                   'pointcloud': 'sensor_msgs/msg/PointCloud2'}
"""The message type of each ``<name>.type`` of an observation source."""

COUNT_KEYS = ('messages', 'refused', 'stale')
"""Per source: messages received, messages refused (undecodable, wrong layout, too large),
decisions answered with the fail-safe because the source was stale or had no message yet."""


def topic_refusal(config: SourceConfig, own_topics: Sequence[str],
                  resolve: Callable[[str], str]) -> str:
    """Why the sources' topics cannot be used, in one line naming ``<name>.topic`` ('' when
    they can): a topic that resolves (``resolve``: the node's resolve_topic_name, remaps and
    namespace included) to one of ``own_topics`` (the node's own: its answers would come back
    as sensor data, or its inputs be read as scans), or to another source's topic, or that
    does not resolve at all. Names are compared resolved: ``scan`` and ``/scan`` are one topic
    in the root namespace."""
    def resolved(key: str, topic: str) -> str:
        try:
            return resolve(topic)
        except Exception as exc:  # the runtime's refusal of the name, in one line
            raise ValueError(f'{key}: {topic!r} is not a valid topic name '
                             f'({" ".join(str(exc).split())[:160]})') from None
    try:
        own = {}
        for topic in own_topics:
            own.setdefault(resolved(topic, topic), topic)
        taken: dict[str, str] = {}
        for name, params in config.sources:
            key = f'{name}.topic'
            topic = resolved(key, params.topic)
            if topic in own:
                return (f"{key}: {params.topic!r} resolves to {topic}, the node's own "
                        f'{own[topic]} topic')
            if topic in taken:
                return (f'{key}: {params.topic!r} resolves to {topic}, the topic of '
                        f'{taken[topic]}.topic too')
            taken[topic] = name
    except ValueError as exc:
        return str(exc)
    return ''


@dataclass
class _Source:
    """One source's parameters, latest points and counts."""

    name: str
    params: SourceParameters
    points: np.ndarray | None = None
    """(N, 2) in ``frame_id`` (None: no usable message yet)."""
    spread: float = 0.0
    frame_id: str = ''
    stamp_ns: int = 0
    received_ns: int = 0
    refusal: str = ''
    """Why the latest message was refused ('' when it was read)."""
    counts: dict[str, int] = field(default_factory=lambda: dict.fromkeys(COUNT_KEYS, 0))


class ObservationSources:
    """The latest points of every source, and the fail-safe's reason when they cannot be used
    (module docstring)."""

    def __init__(self, config: SourceConfig) -> None:
        self.config = config
        self._sources = {name: _Source(name, params) for name, params in config.sources}

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
        source.points, source.spread = out.points, out.spread
        source.frame_id, source.stamp_ns = out.frame_id, out.stamp_ns
        source.received_ns, source.refusal = received_ns, ''
        return ''

    def points(self, state: np.ndarray, *, now_ns: int, stamp_now_ns: int
               ) -> tuple[np.ndarray, np.ndarray | float] | str:
        """Every source's points in the state's frame, and their spread (one value, or one per
        point where the sources' differ), at ``state`` (n_x); else the fail-safe's reason,
        naming the source.

        A message's age is counted from its header stamp on the node's clock
        (``stamp_now_ns``, as collision_monitor counts ``source_timeout``), and never from
        later than its receipt (``now_ns`` and the message's receipt, on the monotonic clock):
        a stamp in the future does not keep a source fresh.
        """
        config = self.config
        parts: list[np.ndarray] = []
        spreads: list[tuple[float, int]] = []
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
            points = source.points
            if source.frame_id == config.base_frame_id:
                points = self._to_state_frame(points, state)
                if isinstance(points, str):
                    return f'source {name}: {points}'
            elif source.frame_id != config.odom_frame_id:
                return (f"source {name}: frame {source.frame_id!r} is neither the state's "
                        f"{config.odom_frame_id!r} nor the robot's {config.base_frame_id!r} "
                        '(no tf here)')
            parts.append(points)
            spreads.append((source.spread, len(points)))
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

    def _to_state_frame(self, points: np.ndarray, state: np.ndarray) -> np.ndarray | str:
        """Points in the robot's frame -> the state's: rotated by the heading, moved to the
        position (both from ``state``)."""
        config = self.config
        if config.heading_index is None:
            return (f'frame {config.base_frame_id!r} needs the heading in the state '
                    '(obstacles.heading_index)')
        i, j = config.position_indices
        x, y, heading = float(state[i]), float(state[j]), float(state[config.heading_index])
        if not (math.isfinite(x) and math.isfinite(y) and math.isfinite(heading)):
            return "the state's pose is not finite"
        cos, sin = math.cos(heading), math.sin(heading)
        out = np.empty_like(points)
        out[:, 0] = x + cos * points[:, 0] - sin * points[:, 1]
        out[:, 1] = y + sin * points[:, 0] + cos * points[:, 1]
        return out
