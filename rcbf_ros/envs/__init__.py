"""The simulated systems as plain Python (Gymnasium API): Unicycle, Car Following, PVTOL.

No ROS, no file I/O: build an env from flat parameters, e.g.
``UnicycleEnv(load_params(find_config('unicycle'), 'simulator'))``, or through Gymnasium's
registry once this package is imported: ``gymnasium.make('rcbf_ros/Unicycle-v0', params=...)``
(ids in :data:`GYMNASIUM_IDS`; keyword arguments go to the env's constructor).
"""
from __future__ import annotations

from typing import Any, Mapping

import gymnasium

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


GYMNASIUM_IDS: dict[str, str] = {
    'unicycle': 'rcbf_ros/Unicycle-v0',
    'car_following': 'rcbf_ros/CarFollowing-v0',
    'pvtol': 'rcbf_ros/PVTOL-v0',
}
"""Gymnasium id of each built-in system (registered on import)."""

for _system, _id in GYMNASIUM_IDS.items():
    if _id not in gymnasium.registry:
        gymnasium.register(_id, entry_point=ENVS[_system])


def make_env(system: str, params: Mapping[str, Any] | None = None, **overrides: Any) -> SafetyEnv:
    """The env of ``system`` built from flat parameters and keyword overrides.

    Raises:
        ValueError: naming ``system`` when it is not one of :data:`ENVS`.
    """
    if system not in ENVS:
        raise ValueError(f'system: no simulator for {system!r}; choose one of {sorted(ENVS)}')
    return ENVS[system](params, **overrides)


__all__ = ['CarFollowingEnv', 'ENVS', 'GYMNASIUM_IDS', 'make_env', 'PVTOLEnv', 'SafetyEnv',
           'UnicycleEnv']
