"""The pictures a training run leaves: its paths over the layout, and the return per episode.

The paths' picture reports in one line where it went and the closest approach, or why it was
not drawn (a layout that changed every episode, a scene the filter parameters cannot give).
"""
from __future__ import annotations

from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from rcbf_ros.core.config import configures_barriers
from rcbf_ros.training.build import with_far_wall

TRAJECTORY_EPISODES = 200
"""The trajectory picture of an in-process run draws at most this many (the last) episodes."""


def episode_path(number: int, trace: list[tuple[np.ndarray, bool]]) -> Any:
    """The :class:`rcbf_ros.reports.plots.EpisodePath` of a
    :func:`rcbf_ros.training.episodes.run_episode` trace."""
    from rcbf_ros.reports.plots import EpisodePath
    return EpisodePath(number, np.array([state for state, _ in trace]),
                       np.array([corrected for _, corrected in trace], dtype=bool))


def draw_trajectories(paths: list[Any], *, env: Any, filter_params: Mapping[str, Any],
                      png: Path, title: str) -> str:
    """Draw episodes (:class:`rcbf_ros.reports.plots.EpisodePath`) over the env's layout into
    ``png``; one line saying where and the closest approach, or why not."""
    from rcbf_ros.core.scene import scene_geometry
    from rcbf_ros.reports.plots import plot_trajectories
    if getattr(env, 'layout_mode', 'fixed') == 'random' and getattr(env, 'layout_seed', 0) < 0:
        return 'trajectories: not drawn: every episode ran on a new random layout'
    try:
        params = filter_params if configures_barriers(filter_params) \
            else with_far_wall(filter_params)
        picture = plot_trajectories(
            paths, scene_geometry(params), png, obstacles=getattr(env, 'obstacles', None),
            goal=getattr(env, 'goal', None), dt=getattr(env, 'dt', None),
            true_gap=getattr(env, 'min_gap', None), title=f'{title}: {len(paths)} episodes')
    except ValueError as exc:
        return f'trajectories: not drawn: {exc}'
    closest = f'; closest approach {picture.closest.describe()}' if picture.closest else ''
    return f'trajectories: {picture.path}{closest}'


def draw_reward_curve(history: Sequence[Mapping[str, Any]], *, png: Path, title: str) -> None:
    """The return of every episode of ``history`` (rows of ``metrics.jsonl``) into ``png``."""
    from rcbf_ros.reports.plots import plot_reward_curve
    plot_reward_curve([row['ret'] for row in history], png, title=title)
