"""Parameters given to a node that it does not read, and params-file sections of no node.

rclpy ignores an override no declaration takes, so ``input_limit:`` for ``input_limits:`` in a
params file, or ``-p alpah:=3.0``, leaves the default in force without a word. Every node of
the package runs :func:`unknown_parameter_lines` on its command line as it starts (through
:func:`rcbf_ros.ros.node_main.run_node`) and logs each line as a WARN. Pure: no ROS, no DDS.

A key given under the node's own name must be one of the node's parameters; one given to every
node (``/**``, a bare ``-p``) one of the node's or of the shared problem's (the filter's keys,
which the packaged files give every node under ``/**``). A map where a value belongs
(``alpha: {x: 1}``) reaches the node as ``alpha.x`` (rcl joins nested keys with dots) and is
named as such.
"""
from __future__ import annotations

import difflib
from typing import Callable, Iterable, Mapping, Sequence

from rcbf_ros.parameters.rules import node_key_level

NODE_NAMES = ('safety_filter', 'simulator', 'nominal_controller', 'unicycle_lidar', 'recorder',
              'replay', 'learner', 'policy', 'scene_markers')
"""The names of the package's nodes (their console scripts): a params-file section for
another name is for no node of the package."""
IGNORED = ('use_sim_time', 'start_type_description_service', 'qos_overrides')
"""Parameters (and prefixes) the runtime itself reads for every node."""
MOST_SHOWN = 12
"""Most unknown names one line lists (then how many more)."""
_CUTOFF = 0.7
"""difflib similarity from which a known name is offered as the one meant."""


def _nearest(name: str, candidates: Sequence[str]) -> str | None:
    found = difflib.get_close_matches(name, candidates, n=1, cutoff=_CUTOFF)
    return found[0] if found else None


def _ignored(name: str) -> bool:
    return any(name == word or name.startswith(word + '.') for word in IGNORED)


def unknown_parameter_lines(*, sections: Mapping[str, Mapping[str, object]], node_name: str,
                            fully_qualified: str, own: Callable[[str], bool],
                            shared: Callable[[str], bool], own_names: Sequence[str],
                            shared_names: Sequence[str]) -> list[str]:
    """The WARN lines for a node's command-line parameters (none when all are known).

    Args:
        sections: the command line's params table: node key (as written) -> {name: value}
            (:meth:`rcbf_ros.parameters.rules.ParamRules.sections`).
        node_name: the node's name (after remapping).
        fully_qualified: its fully qualified name (``/ns/name``).
        own: whether the node reads a parameter of this name.
        shared: whether it is a key of the shared problem (read by some node of the package).
        own_names, shared_names: the names offered as the one meant.

    Returns:
        One line naming every unknown parameter given to this node (with the nearest known
        name where one is close), and one per section that names no node of the package.
    """
    unknown: dict[str, str] = {}
    lines = []
    for key, values in sections.items():
        level = node_key_level(key, node_name, fully_qualified)
        if level == 0:
            line = _stray_section_line(key, node_name)
            if line:
                lines.append(line)
            continue
        candidates = own_names if level == 2 else (*own_names, *shared_names)
        for name in values:
            if name in unknown or _ignored(name) or own(name) or (level == 1 and shared(name)):
                continue
            unknown[name] = _shown(name, candidates)
    if unknown:
        shown = list(unknown.values())
        more = f' and {len(shown) - MOST_SHOWN} more' if len(shown) > MOST_SHOWN else ''
        lines.insert(0, f'unknown parameter{"s" if len(shown) > 1 else ""} ignored (this node '
                        f'reads no such key): {", ".join(shown[:MOST_SHOWN])}{more}')
    return lines


def _shown(name: str, candidates: Sequence[str]) -> str:
    """``'name'`` with what was probably meant."""
    parent = name.rsplit('.', 1)[0]
    if parent != name and parent in candidates:
        return f'{name!r} ({parent!r} takes a value, not a map)'
    nearest = _nearest(name, candidates)
    return f'{name!r} (did you mean {nearest!r}?)' if nearest else repr(name)


def _stray_section_line(key: str, node_name: str) -> str:
    """The WARN line of a section whose node is none of the package's ('' for a wildcard key,
    or one naming a node of the package in another namespace)."""
    last = key.rstrip('/').rsplit('/', 1)[-1]
    if last in ('*', '**') or last in NODE_NAMES or last == node_name:
        return ''
    nearest = _nearest(last, (*NODE_NAMES, node_name))
    meant = f' (did you mean {key[:len(key) - len(last)] + nearest!r}?)' if nearest else ''
    return f'params section {key!r} names no node of rcbf_ros{meant}; its keys reach no node'


def names_of(specs: Iterable[object]) -> list[str]:
    """The concrete names of parameter specs (patterns such as ``bands.<name>.index`` left
    out): the names offered as the one meant."""
    return [spec.name for spec in specs  # type: ignore[attr-defined]
            if not getattr(spec, 'pattern', False)]
