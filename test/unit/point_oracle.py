"""The oracle of the sensor points' rows: the points as a static circle family, which the
filter's own point rows never take (the tests compare the two)."""
from __future__ import annotations

import numpy as np

from rcbf_ros.core.barriers import CircleObstacles
from rcbf_ros.core.filter import SafetyFilter
from rcbf_ros.core.rcbf import RCBFProblem


def point_family(config, points: np.ndarray) -> CircleObstacles:
    """``points`` (N, 2) as circles with the footprint's radius, margin and guarded point."""
    template = config.footprint
    return CircleObstacles(
        centers=tuple(map(tuple, points.tolist())), radii=(template.radii[0],) * len(points),
        margin=template.margin, position_indices=template.position_indices,
        heading_index=template.heading_index, lookahead=template.lookahead,
        speed_input=template.speed_input, name='point')


def points_filter(config, points: np.ndarray) -> SafetyFilter:
    """A filter whose problem holds ``points`` as a static circle family, after the problem's
    own barriers (row k + i is point i)."""
    problem = RCBFProblem(
        system=config.problem.system,
        families=config.problem.families + (point_family(config, points),),
        alpha=config.problem.alpha, k_c=config.problem.k_c,
        slack_weight=config.problem.slack_weight, input_weight=config.problem.input_weight)
    return SafetyFilter(problem, vector_rows=10**9)
