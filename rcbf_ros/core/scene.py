"""The geometry of a safety problem, read from the filter's own configuration.

:func:`scene_geometry` builds the filter configuration from flat parameters (the same keys and
the same checks as the safety_filter node, :func:`rcbf_ros.core.config.filter_config_from_params`)
and walks its barrier families, through any cascade, keeping what can be drawn: obstacle discs
with their margin, the look-ahead point, car gaps, bands and walls, the robot's footprint
radius, every barrier's name in row order (the ``h.<name>`` keys of the filter's
diagnostics) and, with observation sources, the frame their points and the state are in. A
filter whose only obstacles are sensor points takes its planar indices and look-ahead from
the footprint family every point takes. The scene markers
(:mod:`rcbf_ros.node_logic.scene`) and the trajectory pictures (:mod:`rcbf_ros.reports.plots`)
draw from it, so both show what the filter guards. Pure: no ROS, no I/O.
"""
from __future__ import annotations

from dataclasses import dataclass
import math
from typing import Any, Mapping, Sequence

import numpy as np

from rcbf_ros.core.barriers import BandBarrier, CircleObstacles, HalfPlane, PairGap, uncascaded
from rcbf_ros.core.config import filter_config_from_params, FootprintParameters
from rcbf_ros.core.mappings import flatten
from rcbf_ros.parameters.reader import read_parameters


@dataclass(frozen=True)
class Disc:
    """One circular obstacle as the filter sees it."""

    name: str
    """Its barrier's name (``obstacle_<i>``)."""
    x: float
    """Centre, first position coordinate [m]."""
    y: float
    """Centre, second position coordinate [m]."""
    radius: float
    """True radius r [m] (``obstacles.radius``)."""
    margin: float
    """Added by the filter: the guarded point stays outside r + margin [m]."""


@dataclass(frozen=True)
class Band:
    """A band barrier |x_index - c| <= half_width (one barrier, or its two sides)."""

    names: tuple[str, ...]
    """Its barriers' names (one, or ``<name>_upper`` and ``<name>_lower``)."""
    index: int
    """State entry kept in the band."""
    half_width: float
    """Allowed distance from the centre."""
    center: float
    """Constant centre (when ``center_index`` is None)."""
    center_index: int | None
    """State entry of a moving centre (the PVTOL operator), or None."""


@dataclass(frozen=True)
class Gap:
    """A kept distance |x_a - x_b| >= delta between two 1-D positions."""

    name: str
    """Its barrier's name (``gap_<a>_<b>``)."""
    a: int
    """State index of one position."""
    b: int
    """State index of the other."""
    delta: float
    """The distance the filter keeps [m]."""


@dataclass(frozen=True)
class Wall:
    """A half-plane n . x_S >= offset."""

    name: str
    """Its barrier's name."""
    normal: tuple[float, ...]
    """n, one entry per index."""
    offset: float
    """The offset b."""
    indices: tuple[int, ...]
    """State entries S."""


@dataclass(frozen=True)
class SceneGeometry:
    """What a picture of one system's safety problem needs (see the module docstring)."""

    system: str
    """The ``system`` parameter (``unicycle``, ``pvtol``, ``car_following`` or a dotted path)."""
    n_x: int
    """State dimension."""
    barrier_names: tuple[str, ...]
    """Every barrier's name, in the filter's row order."""
    obstacles: tuple[Disc, ...] = ()
    """Circular obstacles."""
    position_indices: tuple[int, int] = (0, 1)
    """State entries of the planar position the obstacles are measured from."""
    heading_index: int | None = None
    """State entry of the heading (look-ahead point), or None."""
    lookahead: float = 0.0
    """l_p: distance of the guarded point ahead of the position [m] (0: the position)."""
    bands: tuple[Band, ...] = ()
    """Band barriers."""
    gaps: tuple[Gap, ...] = ()
    """Gap barriers."""
    walls: tuple[Wall, ...] = ()
    """Half-plane barriers."""
    footprint_radius: float = 0.0
    """``footprint.radius``: the robot's radius as sensor points see it [m] (0: none given)."""
    odom_frame_id: str | None = None
    """With observation sources, the filter's ``odom_frame_id``: the frame of its state and of
    its sensor points (REP 105); None without sources."""

    @property
    def sensor_points(self) -> bool:
        """Whether the filter takes sensor points (has observation sources)."""
        return self.odom_frame_id is not None

    def position(self, state: Sequence[float] | np.ndarray) -> tuple[float, float]:
        """The planar position of ``state`` (n_x,)."""
        i, j = self.position_indices
        return float(state[i]), float(state[j])

    def guarded_point(self, state: Sequence[float] | np.ndarray) -> tuple[float, float] | None:
        """The look-ahead point ahead of the robot that the obstacle barriers guard for
        forward motion, or None when the barriers guard the position itself."""
        if (self.heading_index is None or self.lookahead == 0.0
                or not (self.obstacles or self.sensor_points)):
            return None
        x, y = self.position(state)
        theta = float(state[self.heading_index])
        return x + self.lookahead * math.cos(theta), y + self.lookahead * math.sin(theta)

    def band(self, name: str) -> Band | None:
        """The band whose barriers are called ``name`` or ``name_upper``/``name_lower``."""
        for band in self.bands:
            if name in band.names or f'{name}_upper' in band.names:
                return band
        return None


def scene_geometry(params: Mapping[str, Any]) -> SceneGeometry:
    """The geometry of the filter configured by flat (or nested) parameters.

    Raises:
        ValueError: a parameter the filter would refuse (the message names the key).
    """
    params = flatten(params)
    config = filter_config_from_params(params)
    problem = config.problem
    obstacles: list[Disc] = []
    bands: list[Band] = []
    gaps: list[Gap] = []
    walls: list[Wall] = []
    planar: dict[str, Any] = {}
    for family in problem.families:
        base = uncascaded(family)
        if isinstance(base, CircleObstacles):
            obstacles += [Disc(name, float(c[0]), float(c[1]), float(r), float(base.margin))
                          for name, c, r in zip(base.names, base.centers, base.radii)]
            planar = {'position_indices': tuple(base.position_indices),
                      'heading_index': base.heading_index, 'lookahead': float(base.lookahead)}
        elif isinstance(base, BandBarrier):
            bands.append(Band(tuple(base.names), base.index, float(base.half_width),
                              float(base.center), base.center_index))
        elif isinstance(base, PairGap):
            gaps += [Gap(name, a, b, float(base.delta))
                     for name, (a, b) in zip(base.names, base.pairs)]
        elif isinstance(base, HalfPlane):
            walls += [Wall(name, tuple(float(v) for v in n), float(b), tuple(base.indices))
                      for name, n, b in zip(base.names, base.normals, base.offsets)]
    footprint = uncascaded(config.footprint) if config.footprint is not None else None
    if not planar and isinstance(footprint, CircleObstacles):  # sensor points only
        planar = {'position_indices': tuple(footprint.position_indices),
                  'heading_index': footprint.heading_index,
                  'lookahead': float(footprint.lookahead)}
    if config.sources is not None:
        planar['odom_frame_id'] = config.sources.odom_frame_id
    return SceneGeometry(
        system=str(params['system']), n_x=problem.system.n_x,
        barrier_names=tuple(problem.barrier_names), obstacles=tuple(obstacles),
        bands=tuple(bands), gaps=tuple(gaps), walls=tuple(walls),
        footprint_radius=float(read_parameters(FootprintParameters, params,
                                               prefix='footprint.').radius), **planar)
