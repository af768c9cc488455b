"""The simulated systems (Unicycle, Car Following, PVTOL) as Gymnasium envs, for training and
the simulator node; :func:`make_env` builds one from a system's name or a dotted path."""
from __future__ import annotations

from typing import Any, Mapping

import gymnasium

from rcbf_ros.core.torch_import import import_error_line
from rcbf_ros.envs.base import SafetyEnv
from rcbf_ros.envs.car_following import CarFollowingEnv
from rcbf_ros.envs.pvtol import PVTOLEnv
from rcbf_ros.envs.unicycle import UnicycleEnv
from rcbf_ros.messages import systems


def env_class(system: str) -> type[SafetyEnv]:
    """The env class of a name of the table or of a dotted path ``package.module.Class``.

    Raises:
        ValueError: naming ``system`` when the name is unknown, the path cannot be imported or
            does not name a :class:`SafetyEnv` subclass.
    """
    if system in systems.system_names():
        return systems.lookup(system).part('env')
    if '.' not in system:
        raise ValueError(f'system: no simulator for {system!r}; choose one of '
                         f'{sorted(systems.system_names())} or give the dotted path of a '
                         'SafetyEnv class')
    found = systems.import_object(system, explain=import_error_line)
    if not (isinstance(found, type) and issubclass(found, SafetyEnv)):
        raise ValueError(f'system: {system!r} is not a subclass of '
                         'rcbf_ros.envs.base.SafetyEnv')
    return found


def gymnasium_id(system: str) -> str:
    """The Gymnasium id of a name of the table (registered on import).

    Raises:
        ValueError: naming ``system`` when it has no env, or its env no id.
    """
    found = env_class(system).gymnasium_id
    if not found:
        raise ValueError(f'system: the env of {system!r} has no gymnasium_id')
    return found


def register_gymnasium_ids() -> None:
    """Put the env of every system of the table into Gymnasium's registry (once)."""
    for name in systems.system_names():
        cls = systems.lookup(name).parts.get('env')
        if cls is not None and cls.gymnasium_id and cls.gymnasium_id not in gymnasium.registry:
            gymnasium.register(cls.gymnasium_id, entry_point=cls)


register_gymnasium_ids()


def make_env(system: str, params: Mapping[str, Any] | None = None, **overrides: Any) -> SafetyEnv:
    """The env of ``system`` (see :func:`env_class`) built from flat parameters and keyword
    overrides (``a__b=...`` sets ``a.b``).

    Raises:
        ValueError: naming ``system`` (see :func:`env_class`), or the parameter the env refuses.
    """
    return env_class(system)(params, **overrides)


__all__ = ['CarFollowingEnv', 'env_class', 'gymnasium_id', 'make_env', 'PVTOLEnv',
           'register_gymnasium_ids', 'SafetyEnv', 'UnicycleEnv']
