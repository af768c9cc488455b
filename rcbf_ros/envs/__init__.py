"""The simulated systems as plain Python (Gymnasium API): Unicycle, Car Following, PVTOL.

No ROS, no file I/O: build an env from flat parameters, e.g.
``UnicycleEnv(load_params(find_config('unicycle'), 'simulator'))``.
"""
from __future__ import annotations

from typing import Any, Mapping

from rcbf_ros.envs.base import SafetyEnv
from rcbf_ros.envs.car_following import CarFollowingEnv
from rcbf_ros.envs.pvtol import PVTOLEnv
from rcbf_ros.envs.unicycle import UnicycleEnv

ENVS: dict[str, type[SafetyEnv]] = {
    'unicycle': UnicycleEnv,
    'car_following': CarFollowingEnv,
    'pvtol': PVTOLEnv,
}
"""Env class of each built-in system name."""


def make_env(system: str, params: Mapping[str, Any] | None = None, **overrides: Any) -> SafetyEnv:
    """The env of ``system`` built from flat parameters and keyword overrides.

    Raises:
        ValueError: naming ``system`` when it is not one of :data:`ENVS`.
    """
    if system not in ENVS:
        raise ValueError(f'system: no simulator for {system!r}; choose one of {sorted(ENVS)}')
    return ENVS[system](params, **overrides)


__all__ = ['CarFollowingEnv', 'ENVS', 'make_env', 'PVTOLEnv', 'SafetyEnv', 'UnicycleEnv']
