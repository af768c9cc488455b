"""ROS 2 command-line arguments, parameter files and name resolution (pure, no DDS).

Implements the subset of rcl's argument grammar that our nodes use::

    --ros-args [-p|--param name:=value] [-r|--remap [node:]from:=to]
               [--params-file file.yaml] [--log-level [logger:=]level]
               [-e|--enclave e] [--(enable|disable)-(rosout|stdout|external-lib)-logs] [--]

``-p`` values are YAML scalars (or flow lists), as in ROS. Special remaps ``__node``/``__name``
and ``__ns`` rename the node and set its namespace. Parameter files hold
``/<node>: ros__parameters: {...}`` or ``/**: ros__parameters: {...}``; nested mappings flatten to
dotted names, as rclpy does.
"""
from __future__ import annotations

from dataclasses import dataclass, field
import re
from typing import Any, Iterable, Sequence

import yaml

from rcbf_ros.params import add_node_sections, read_params_file

_FLAG_ONLY = {
    '--enable-rosout-logs', '--disable-rosout-logs', '--enable-stdout-logs',
    '--disable-stdout-logs', '--enable-external-lib-logs', '--disable-external-lib-logs',
}
_TOKEN = re.compile(r'^[A-Za-z_][A-Za-z0-9_]*$')
_SUBSTITUTION = re.compile(r'^\{[A-Za-z_][A-Za-z0-9_]*\}$')


class RosArgumentError(ValueError):
    """A malformed ``--ros-args`` section, parameter file or name."""


@dataclass(frozen=True)
class RemapRule:
    """One ``-r [node:]from:=to`` rule."""

    match: str
    """Name to match (as given; expanded against each node when applied)."""
    replacement: str
    """Name to substitute (as given; expanded against each node when applied)."""
    node: str | None = None
    """Only nodes with this name use the rule (``None``: every node)."""


@dataclass(frozen=True)
class RosArguments:
    """Everything parsed out of the ``--ros-args`` sections of a command line."""

    parameters: dict[str, Any] = field(default_factory=dict)
    """``-p name:=value`` overrides (values already parsed as YAML)."""
    params_files: tuple[str, ...] = ()
    """``--params-file`` paths in command-line order."""
    remaps: tuple[RemapRule, ...] = ()
    """Topic remap rules in command-line order (first match wins)."""
    node_name: str | None = None
    """``-r __node:=name`` (or ``__name``)."""
    namespace: str | None = None
    """``-r __ns:=/ns``."""
    log_level: str | None = None
    """``--log-level`` for the default logger (``debug|info|warn|error|fatal``)."""
    unparsed: tuple[str, ...] = ()
    """Arguments outside ``--ros-args`` sections (what ``remove_ros_args`` returns)."""


def parse_yaml_value(text: str) -> Any:
    """A ``-p`` value as ROS reads it: a YAML scalar or flow sequence (``'1'`` -> ``1``)."""
    try:
        value = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise RosArgumentError(f'cannot parse parameter value {text!r} as YAML: {exc}') from exc
    return '' if value is None and text.strip() in ('', "''", '""') else value


def _split_assignment(flag: str, text: str) -> tuple[str, str]:
    if ':=' not in text:
        raise RosArgumentError(f'{flag} expects NAME:=VALUE, got {text!r}')
    name, value = text.split(':=', 1)
    if not name:
        raise RosArgumentError(f'{flag} has an empty name in {text!r}')
    return name, value


def parse_ros_arguments(argv: Sequence[str] | None) -> RosArguments:
    """Parse the ``--ros-args`` sections of ``argv`` (``argv[0]`` is treated like any word).

    Raises:
        RosArgumentError: an unknown flag, a flag missing its value, or a malformed rule.
    """
    parameters: dict[str, Any] = {}
    params_files: list[str] = []
    remaps: list[RemapRule] = []
    unparsed: list[str] = []
    node_name = namespace = log_level = None
    words = list(argv or [])
    index = 0
    in_ros = False
    while index < len(words):
        word = words[index]
        index += 1
        if word == '--ros-args':
            in_ros = True
            continue
        if not in_ros:
            unparsed.append(word)
            continue
        if word == '--':
            in_ros = False
            continue
        if word in _FLAG_ONLY:
            continue
        if word not in ('-p', '--param', '-r', '--remap', '--params-file', '--log-level', '-e',
                        '--enclave'):
            raise RosArgumentError(f'unknown ROS argument {word!r}')
        if index >= len(words):
            raise RosArgumentError(f'{word} expects a value')
        value = words[index]
        index += 1
        if word in ('-p', '--param'):
            name, text = _split_assignment(word, value)
            parameters[name] = parse_yaml_value(text)
        elif word in ('-r', '--remap'):
            lhs, rhs = _split_assignment(word, value)
            node = None
            if ':' in lhs:
                node, lhs = lhs.split(':', 1)
            if not rhs:
                raise RosArgumentError(f'{word} has an empty replacement in {value!r}')
            if lhs in ('__node', '__name'):
                _check_node_name(rhs)
                if node is None:
                    node_name = rhs
                else:
                    remaps.append(RemapRule('__node', rhs, node))
            elif lhs == '__ns':
                namespace = _check_namespace(rhs)
            else:
                remaps.append(RemapRule(lhs, rhs, node))
        elif word == '--params-file':
            params_files.append(value)
        elif word == '--log-level':
            log_level = (value.split(':=', 1)[1] if ':=' in value else value).lower()
    return RosArguments(parameters, tuple(params_files), tuple(remaps), node_name, namespace,
                        log_level, tuple(unparsed))


def remove_ros_args(args: Sequence[str]) -> list[str]:
    """The command line without its ``--ros-args`` sections (like rclpy.utilities')."""
    return list(parse_ros_arguments(args).unparsed)


def load_params_file(path: str) -> dict[str, dict[str, Any]]:
    """Read a ROS 2 parameter file: node key -> flattened ``ros__parameters``.

    Raises:
        RosArgumentError: the file is missing or unreadable, not UTF-8 YAML, or not a mapping of
            node sections with ``ros__parameters`` (one line naming the file).
    """
    try:
        return read_params_file(path)
    except OSError as exc:
        raise RosArgumentError(f'--params-file {path!r}: {exc.strerror or exc}') from exc
    except UnicodeDecodeError as exc:
        raise RosArgumentError(f'--params-file {path!r}: not UTF-8 text ({exc.reason} at byte '
                               f'{exc.start})') from exc
    except ValueError as exc:
        cause = exc.__cause__
        if isinstance(cause, yaml.MarkedYAMLError) and cause.problem_mark is not None:
            mark = cause.problem_mark
            raise RosArgumentError(f'--params-file {path!r}: not valid YAML at line '
                                   f'{mark.line + 1}, column {mark.column + 1}: '
                                   f'{cause.problem}') from exc
        raise RosArgumentError(' '.join(f'--params-file {exc}'.split())) from exc


def parameter_overrides(arguments: Iterable[RosArguments], node_name: str,
                        fully_qualified: str) -> dict[str, Any]:
    """The parameter overrides one node sees.

    Parameter files (in order) contribute their wildcard entries (``/**``) first and their
    entries for this node second; ``-p`` assignments override both, as in rcl/rclpy.
    """
    wildcard: dict[str, Any] = {}
    specific: dict[str, Any] = {}
    direct: dict[str, Any] = {}
    for args in arguments:
        for path in args.params_files:
            add_node_sections(load_params_file(path), node_name, fully_qualified, wildcard,
                              specific)
        direct.update(args.parameters)
    return {**wildcard, **specific, **direct}


def _check_node_name(name: str) -> str:
    if not _TOKEN.match(name):
        raise RosArgumentError(f'invalid node name {name!r}: use letters, digits and _, '
                               'not starting with a digit')
    return name


def check_node_name(name: str) -> str:
    """Validate a node name (``[A-Za-z_][A-Za-z0-9_]*``); return it."""
    return _check_node_name(name)


def _check_namespace(namespace: str) -> str:
    if namespace in ('', '/'):
        return '/'
    if not namespace.startswith('/'):
        namespace = '/' + namespace
    namespace = namespace.rstrip('/')
    for token in namespace[1:].split('/'):
        if not _TOKEN.match(token):
            raise RosArgumentError(f'invalid namespace {namespace!r}: bad token {token!r}')
    return namespace


def check_namespace(namespace: str) -> str:
    """Validate and normalize a namespace (``'ns'`` -> ``'/ns'``, ``''`` -> ``'/'``)."""
    return _check_namespace(namespace)


def expand_topic_name(name: str, node_name: str, namespace: str) -> str:
    """Fully qualified topic name: ``~`` is the node, relative names get the namespace.

    Raises:
        RosArgumentError: empty name, ``//``, trailing ``/`` or an invalid token.
    """
    if not name:
        raise RosArgumentError('topic name must not be empty')
    node_fqn = (namespace.rstrip('/') + '/' + node_name)
    if name == '~':
        expanded = node_fqn
    elif name.startswith('~/'):
        expanded = node_fqn + name[1:]
    elif name.startswith('~'):
        raise RosArgumentError(f'invalid topic name {name!r}: ~ must be followed by /')
    elif name.startswith('/'):
        expanded = name
    else:
        expanded = namespace.rstrip('/') + '/' + name
    expanded = expanded.replace('{node}', node_name).replace('{ns}', namespace.rstrip('/'))
    if expanded.endswith('/') and expanded != '/':
        raise RosArgumentError(f'invalid topic name {name!r}: must not end with /')
    for token in expanded[1:].split('/'):
        if not _TOKEN.match(token):
            raise RosArgumentError(f'invalid topic name {name!r}: bad token {token!r}')
    return expanded


def resolve_topic_name(name: str, node_name: str, namespace: str,
                       remaps: Iterable[RemapRule]) -> str:
    """Expand ``name`` and apply the first matching remap rule (rules expand the same way)."""
    expanded = expand_topic_name(name, node_name, namespace)
    for rule in remaps:
        if rule.match == '__node' or (rule.node is not None and rule.node != node_name):
            continue
        if expand_topic_name(rule.match, node_name, namespace) == expanded:
            return expand_topic_name(rule.replacement, node_name, namespace)
    return expanded
