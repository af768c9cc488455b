"""The simulated systems as plain Python (Gymnasium API): Unicycle, Car Following, PVTOL.

No ROS, no file I/O. :func:`make_env` is the one way the package builds an env: from a
built-in system name (:data:`ENVS`) or the dotted path of a :class:`SafetyEnv` subclass, plus
flat parameters, e.g. ``make_env('unicycle', load_params(find_config('unicycle'),
'simulator'))``. The built-ins are also in Gymnasium's registry once this package is imported:
``gymnasium.make('rcbf_ros/Unicycle-v0', params=...)`` (ids in :data:`GYMNASIUM_IDS`; keyword
arguments go to the env's constructor).
"""
from __future__ import annotations

import importlib
from typing import Any, Mapping

import gymnasium

from rcbf_ros.core.torch_import import import_error_line
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


def env_class(system: str) -> type[SafetyEnv]:
    """The env class of a built-in system name or of a dotted path ``package.module.Class``.

    Raises:
        ValueError: naming ``system`` when the name is unknown, the path cannot be imported or
            does not name a :class:`SafetyEnv` subclass.
    """
    if system in ENVS:
        return ENVS[system]
    if '.' not in system:
        raise ValueError(f'system: no simulator for {system!r}; choose one of {sorted(ENVS)} '
                         'or give the dotted path of a SafetyEnv class')
    module_name, _, name = system.rpartition('.')
    try:
        found = getattr(importlib.import_module(module_name), name)
    except (ImportError, AttributeError) as exc:
        reason = import_error_line(exc) if isinstance(exc, ImportError) else exc
        raise ValueError(f'system: cannot import {system!r}: {reason}') from None
    if not (isinstance(found, type) and issubclass(found, SafetyEnv)):
        raise ValueError(f'system: {system!r} is not a subclass of '
                         'rcbf_ros.envs.base.SafetyEnv')
    return found


def make_env(system: str, params: Mapping[str, Any] | None = None, **overrides: Any) -> SafetyEnv:
    """The env of ``system`` (see :func:`env_class`) built from flat parameters and keyword
    overrides (``a__b=...`` sets ``a.b``).

    Raises:
        ValueError: naming ``system`` (see :func:`env_class`), or the parameter the env refuses.
    """
    return env_class(system)(params, **overrides)


__all__ = ['CarFollowingEnv', 'env_class', 'ENVS', 'GYMNASIUM_IDS', 'make_env', 'PVTOLEnv',
           'SafetyEnv', 'UnicycleEnv']
