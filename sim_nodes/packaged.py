"""Parameters the simulated-system nodes take from the packaged ``config/<system>.yaml``.

The simulator and the nominal controller declare ``system`` and every key of their section
(with ``/**``) of the packaged params file of that system, with the file's values as defaults;
overrides (``--params-file``, ``-p``) win. :func:`packaged_parameter_specs` describes exactly
those declarations for ``--help`` and the README, one line each from :func:`descriptions` (the
environments' own keys) or from the safety filter's specs (the shared layout keys).
"""
from __future__ import annotations

from typing import Any, Sequence

from rcbf_ros.envs import env_class
from rcbf_ros.messages import systems
from rcbf_ros.node_logic.interface import NodeInterface, ParameterSpec, TopicSpec, type_of
from rcbf_ros.node_logic.safety_filter import FILTER_DESCRIPTIONS, FILTER_PARAMETERS
from rcbf_ros.parameters.reader import parameters_of, Rule
from rcbf_ros.parameters.rules import load_params
from rcbf_ros.ros.node_main import declare_specs

DEFAULT_SYSTEM = 'unicycle'


def descriptions(system: str) -> dict[str, str]:
    """Key -> one line, for the keys of ``system``'s env and nominal controller (from their
    settings dataclasses)."""
    return {key: rule.description for key, rule in _rules(system).items()}


def _rules(system: str) -> dict[str, Rule]:
    """Key -> its :class:`Rule`, for the described keys of ``system``'s env and nominal
    controller."""
    env = env_class(system)
    return {parameter.key: parameter.rule
            for cls in (env.settings_type, env.controller_settings) if cls is not None
            for parameter in parameters_of(cls) if parameter.rule.description}


def _description(name: str, system: str) -> tuple[str, str | None]:
    """(one line, declared type or None) of a packaged key."""
    own = descriptions(system)
    if name in own:
        return own[name], None
    for spec in FILTER_PARAMETERS:
        if spec.matches(name):
            return (FILTER_DESCRIPTIONS[spec.name],
                    None if spec.type == 'any' else spec.type)
    raise KeyError(name)


def packaged_parameters(system: str, section: str) -> dict[str, Any]:
    """The keys a node declares from the packaged params file of ``system`` (``/**`` and
    ``section``; ``system`` itself and empty values left out), with their values.

    Raises:
        ValueError: naming ``system`` when it is not a packaged system.
    """
    if system not in systems.system_names():
        raise ValueError(f'system: expected one of {sorted(systems.system_names())}, '
                         f'got {system!r}')
    values = load_params(systems.lookup(system).config_path(), section)
    values.pop('system', None)
    return {name: value for name, value in values.items()
            if value is not None and value != []}


def system_spec() -> ParameterSpec:
    """The ``system`` parameter of a simulated-system node."""
    return ParameterSpec('system', DEFAULT_SYSTEM, 'string',
                         f'the simulated system: {", ".join(sorted(systems.system_names()))} '
                         '(the other defaults below are those of its config/<system>.yaml)')


def packaged_parameter_specs(system: str, section: str,
                             skip: Sequence[str] = ()) -> tuple[ParameterSpec, ...]:
    """One spec per key :func:`declare_with_packaged_defaults` declares for ``system``
    (besides ``skip``: keys the node declares itself)."""
    specs = [system_spec()]
    rules = _rules(system)
    for name, value in packaged_parameters(system, section).items():
        if name in skip:
            continue
        description, declared = _description(name, system)
        rule = rules.get(name)
        bounds = ({} if rule is None else
                  {'minimum': rule.minimum, 'maximum': rule.maximum, 'positive': rule.positive})
        specs.append(ParameterSpec(name, value, declared or type_of(value), description,
                                   **bounds))
    return tuple(specs)


def packaged_interface(argv: Sequence[str], *, node: str, section: str, summary: str,
                       topics: tuple[TopicSpec, ...],
                       own: tuple[ParameterSpec, ...]) -> NodeInterface:
    """The interface (``--help``, README) of a simulated-system node for the ``system`` of a
    command line: its ``own`` parameters, then ``system`` and the keys of that system's
    packaged file (:func:`packaged_parameter_specs`)."""
    system = system_from_argv(argv)
    return NodeInterface(
        node=node, summary=f'{summary} Defaults below: system {system}.', topics=topics,
        parameters=own + packaged_parameter_specs(system, section,
                                                  skip=tuple(spec.name for spec in own)),
        notes=(f'Other systems: {node} --help --ros-args -p system:=pvtol '
               '(or car_following).',))


def system_from_argv(argv: Sequence[str]) -> str:
    """The ``system`` a command line sets with ``-p system:=...`` (else the default)."""
    from rcbf_ros.parameters.arguments import (
        parameter_overrides,
        parse_ros_arguments,
        RosArgumentError,
    )
    try:  # the rules as the node named in --help would see them (rcl's order)
        value = parameter_overrides([parse_ros_arguments(argv)], '/simulator').get(
            'system', DEFAULT_SYSTEM)
    except RosArgumentError:
        return DEFAULT_SYSTEM
    return str(value) if str(value) in systems.system_names() else DEFAULT_SYSTEM


def declare_with_packaged_defaults(node: Any, section: str,
                                   own: Sequence[ParameterSpec] = ()) -> dict[str, Any]:
    """Declare the node's ``own`` parameters, ``system`` and every key of the packaged
    ``config/<system>.yaml`` for ``section`` (:func:`rcbf_ros.ros.node_main.declare_specs`,
    with their descriptions: :func:`packaged_parameter_specs`).

    Overrides given on the command line or in ``--params-file`` were already declared by the
    node (``automatically_declare_parameters_from_overrides``) and win; the packaged file
    supplies the rest. Returns every declared parameter that is set as a flat dict (an empty
    string list is declared by type, unset: its reader's default applies).

    Raises:
        ValueError: naming ``system`` when it is not a packaged system, or the parameter a
            declaration refuses.
    """
    declare_specs(node, own, others=None)
    declare_specs(node, (system_spec(),), others=None)
    system = str(node.get_parameter('system').value)
    declare_specs(node, packaged_parameter_specs(system, section,
                                                 skip=tuple(spec.name for spec in own)))
    return {name: _plain(p.value)
            for name, p in node.get_parameters_by_prefix('').items() if p.value is not None}


def _plain(value: Any) -> Any:
    """rclpy may hand arrays back as ``array.array``; the envs take lists."""
    if isinstance(value, (str, bytes, bool, int, float)) or value is None:
        return value
    try:
        return list(value)
    except TypeError:
        return value
