"""The table of systems: every place that needs the list of systems, or a fact of one, reads it.

One :class:`System` per name the ``system`` parameter takes: its packaged params file and the
named entries of its state and command vectors (what the message edge and the docs show). The
classes of a system declare the name themselves and join their entry when defined: the
dynamics (``system_name`` of a :class:`rcbf_ros.core.dynamics.NamedDynamics`) and the env
(``system_name`` of a :class:`rcbf_ros.envs.base.SafetyEnv`, which also holds the nominal
controller and the torch reward model). So each layer keeps the facts it owns in the system's
own module, and this table, at the bottom of the layers, gives name -> all of them.

:func:`import_object` is the one reader of a dotted path ``package.module.Name`` (a user's own
dynamics or env named in YAML instead of a table name).
"""
from __future__ import annotations

from dataclasses import dataclass, field
import importlib
from pathlib import Path
from typing import Any, Callable, Iterator, Mapping

from rcbf_ros.parameters.rules import find_config

Layout = tuple[tuple[str, str], ...]
"""(name, unit) per vector entry, in order."""

PARTS = ('dynamics', 'env')
"""The classes that join an entry (each declares ``system_name``)."""


@dataclass(frozen=True)
class System:
    """One system of the table (its classes join :attr:`parts` when they are defined)."""

    name: str
    """The value of the ``system`` parameter (and the stem of its params file)."""
    state: Layout
    """The state vector, (name, unit) per entry, in order."""
    command: Layout
    """The command vector u, (name, unit) per entry, in order."""
    odometry: str | None = None
    """How a nav_msgs/Odometry holds the state (None: it does not)."""
    planar_position: tuple[int, int] | None = None
    """The state indices of a position in a plane (x, y), where circular obstacles and sensor
    points are placed (None: the state holds none; ``obstacles.*`` and
    ``observation_sources`` are refused)."""
    config: str = ''
    """The packaged params file (``config/<file>``; '': ``<name>.yaml``)."""
    parts: dict[str, type] = field(default_factory=dict)
    """The classes that joined: ``dynamics``, ``env`` (:data:`PARTS`)."""

    def __post_init__(self) -> None:
        if not self.name.isidentifier():
            raise ValueError(f'system: a table name is an identifier, got {self.name!r}')
        object.__setattr__(self, 'config', self.config or f'{self.name}.yaml')

    def config_path(self) -> Path:
        """The packaged params file (:func:`rcbf_ros.parameters.rules.find_config`).

        Raises:
            FileNotFoundError: naming the file and every directory searched.
        """
        return find_config(self.config)

    def part(self, kind: str) -> type:
        """The class of ``kind`` (:data:`PARTS`) that declared this system.

        Raises:
            ValueError: naming ``system`` when no such class has been defined (imported).
        """
        if kind not in self.parts:
            raise ValueError(f'system: no {kind} declares system_name {self.name!r}')
        return self.parts[kind]


_TABLE: dict[str, System] = {}


def register(system: System) -> System:
    """Add ``system`` to the table (a name once only).

    Raises:
        ValueError: naming ``system`` when the name is taken.
    """
    if system.name in _TABLE:
        raise ValueError(f'system: {system.name!r} is in the table already')
    _TABLE[system.name] = system
    return system


def unregister(name: str) -> None:
    """Take ``name`` out of the table (a system registered for a while, e.g. by a test)."""
    _TABLE.pop(name, None)


def join(cls: type, kind: str) -> None:
    """Let ``cls`` join the entry its own ``system_name`` names, as its ``kind`` part.

    A class that does not set ``system_name`` itself (a subclass of a system's class, or a
    user's class named by dotted path) joins nothing.

    Raises:
        ValueError: ``kind`` is not one of :data:`PARTS`.
    """
    if kind not in PARTS:
        raise ValueError(f'kind: one of {PARTS}, got {kind!r}')
    name = cls.__dict__.get('system_name')
    if isinstance(name, str) and name in _TABLE:
        _TABLE[name].parts[kind] = cls


def system_names() -> tuple[str, ...]:
    """Every name of the table, in its order."""
    return tuple(_TABLE)


def lookup(name: Any) -> System:
    """The entry of ``name``.

    Raises:
        ValueError: naming ``system`` when the table has no such name.
    """
    if not isinstance(name, str) or name not in _TABLE:
        raise ValueError(f'system: unknown system {name!r}; the table has {list(_TABLE)}')
    return _TABLE[name]


def import_object(path: str, explain: Callable[[ImportError], str] = str) -> Any:
    """The object a dotted path ``package.module.Name`` names.

    Args:
        explain: what an ImportError of the module says in one line (a layer above may say
            how to install what is missing).

    Raises:
        ValueError: naming ``system`` when the path has no dot, or cannot be imported.
    """
    module_name, _, attr = path.rpartition('.')
    if not module_name or not attr:
        raise ValueError(f'system: {path!r} is neither a table name {list(_TABLE)} nor a '
                         'dotted path package.module.Name')
    try:
        return getattr(importlib.import_module(module_name), attr)
    except (ImportError, AttributeError) as exc:
        reason = explain(exc) if isinstance(exc, ImportError) else exc
        raise ValueError(f'system: cannot import {path!r}: {reason}') from None


class FactView(Mapping[str, Any]):
    """name -> one fact of every system of the table, read live (a system added later shows)."""

    def __init__(self, fact: str, *, skip_none: bool = False) -> None:
        self._fact, self._skip_none = fact, skip_none

    def _items(self) -> dict[str, Any]:
        items = {name: getattr(system, self._fact) for name, system in _TABLE.items()}
        return {k: v for k, v in items.items() if not (self._skip_none and v is None)}

    def __getitem__(self, name: str) -> Any:
        return self._items()[name]

    def __iter__(self) -> Iterator[str]:
        return iter(self._items())

    def __len__(self) -> int:
        return len(self._items())

    def __repr__(self) -> str:
        return f'FactView({self._fact!r}: {self._items()!r})'


for _system in (
    System('unicycle',
           state=(('x', 'm'), ('y', 'm'), ('theta', 'rad, heading from the x axis')),
           command=(('v', 'm/s, forward speed'), ('omega', 'rad/s, turn rate')),
           odometry='[pose.position.x, pose.position.y, yaw of pose.orientation]',
           planar_position=(0, 1)),
    System('pvtol',  # the paper's normalized units: gravity 1
           state=(('x1', 'horizontal position'), ('x2', 'vertical position'),
                  ('v1', 'horizontal velocity'), ('v2', 'vertical velocity'),
                  ('theta', 'rad, tilt'), ('f', 'thrust, 1 = hover'),
                  ('x_h', "operator's horizontal position; only with_operator")),
           command=(('omega', 'rad/s, tilt rate'), ('u_f', 'thrust rate')),
           planar_position=(0, 1)),  # the vertical plane it flies in
    System('car_following',
           state=tuple(item for car in range(1, 6) for item in (
               (f'p{car}', f'm, car {car} position'), (f'v{car}', f'm/s, car {car} velocity'))),
           command=(('a4', 'm/s^2, acceleration of car 4'),)),
):
    register(_system)
