"""ROS 2 command-line arguments and name resolution, as rcl parses them (pure, no DDS).

Implements the subset of rcl's argument grammar that our nodes use::

    --ros-args [-p|--param name:=value] [-r|--remap [node:]from:=to]
               [--params-file file.yaml] [--log-level [logger:=]level]
               [-e|--enclave e] [--(enable|disable)-(rosout|stdout|external-lib)-logs] [--]

Special remaps ``__node``/``__name`` and ``__ns`` rename the node and set its namespace.

Parameters follow rcl and rclpy exactly (:mod:`rcbf_ros.parameters.rules` has the rules): every
``--params-file`` and ``-p [node:]name:=value`` of one command line fills one table in
command-line order (a bare ``-p`` under the node key ``/**``, ``-p node:...`` under ``node``);
a node takes every key that matches its fully qualified name in the order the keys first
appeared, later ones overwriting earlier ones, global arguments before its own ``cli_args``.
A ``--params-file`` is read by :meth:`~rcbf_ros.parameters.rules.ParamRules.add_file` (within
:mod:`rcbf_ros.parameters.bounded_yaml`'s limits); this module only words its refusal.
"""
from __future__ import annotations

from dataclasses import dataclass, field
import re
from typing import Any, Iterable, Sequence

from rcbf_ros.parameters.rules import node_values, ParamRules, WILDCARD_KEY

_FLAG_ONLY = {
    '--enable-rosout-logs', '--disable-rosout-logs', '--enable-stdout-logs',
    '--disable-stdout-logs', '--enable-external-lib-logs', '--disable-external-lib-logs',
}
_TOKEN = re.compile(r'^[A-Za-z_][A-Za-z0-9_]*\Z')  # \Z: no trailing newline either
# rcl's _rcl_parse_param_rule: [token ':'] name ':=' value; a name is '.'-separated runs of
# tokens and '/' (a token does not start with a digit); no wildcards.
_PARAM_RULE = re.compile(r'(?:(?P<node>[A-Za-z_][A-Za-z0-9_]*):(?!=))?'
                         r'(?P<name>(?:/|[A-Za-z_][A-Za-z0-9_]*)+'
                         r'(?:\.(?:/|[A-Za-z_][A-Za-z0-9_]*)+)*):=(?P<value>.*)', re.DOTALL)


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

    parameter_rules: ParamRules = field(default_factory=ParamRules)
    """Every ``-p`` and ``--params-file`` in command-line order, read as rcl reads them."""
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
    rosout_logs: bool = True
    """False after ``--disable-rosout-logs`` (the last of it and ``--enable-rosout-logs``
    wins); rcl reads it from the process's global arguments only."""


def _split_assignment(flag: str, text: str) -> tuple[str, str]:
    if ':=' not in text:
        raise RosArgumentError(f'{flag} expects NAME:=VALUE, got {text!r}')
    name, value = text.split(':=', 1)
    if not name:
        raise RosArgumentError(f'{flag} has an empty name in {text!r}')
    return name, value


def parse_ros_arguments(argv: Sequence[str] | None) -> RosArguments:
    """Parse the ``--ros-args`` sections of ``argv`` (``argv[0]`` is treated like any word).

    Parameter files are read here, as rcl reads them when it parses the arguments.

    Raises:
        RosArgumentError: an unknown flag, a flag missing its value, a malformed rule, or a
            parameter file that cannot be read or that rcl refuses (one line naming it).
    """
    rules = ParamRules()
    params_files: list[str] = []
    remaps: list[RemapRule] = []
    unparsed: list[str] = []
    node_name = namespace = log_level = None
    rosout_logs = True
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
            if word.endswith('-rosout-logs'):
                rosout_logs = word == '--enable-rosout-logs'
            continue
        if word not in ('-p', '--param', '-r', '--remap', '--params-file', '--log-level', '-e',
                        '--enclave'):
            raise RosArgumentError(f'unknown ROS argument {word!r}')
        if index >= len(words):
            raise RosArgumentError(f'{word} expects a value')
        value = words[index]
        index += 1
        if word in ('-p', '--param'):
            _add_param_rule(rules, word, value)
        elif word in ('-r', '--remap'):
            lhs, rhs = _split_assignment(word, value)
            node = None
            if ':' in lhs:
                node, lhs = lhs.split(':', 1)
            if not rhs:
                raise RosArgumentError(f'{word} has an empty replacement in {value!r}')
            if lhs in ('__node', '__name'):
                check_node_name(rhs)
                if node is None:
                    node_name = rhs
                else:
                    remaps.append(RemapRule('__node', rhs, node))
            elif lhs == '__ns':
                namespace = check_namespace(rhs)
            else:
                remaps.append(RemapRule(lhs, rhs, node))
        elif word == '--params-file':
            _add_params_file(rules, value)
            params_files.append(value)
        elif word == '--log-level':
            log_level = (value.split(':=', 1)[1] if ':=' in value else value).lower()
    return RosArguments(rules, tuple(params_files), tuple(remaps), node_name, namespace,
                        log_level, tuple(unparsed), rosout_logs=rosout_logs)


def _add_param_rule(rules: ParamRules, flag: str, text: str) -> None:
    """One ``-p [node:]name:=value`` into ``rules`` (``/**`` without a node)."""
    match = _PARAM_RULE.fullmatch(text)
    if match is None:
        raise RosArgumentError(f'{flag} expects [NODE:]NAME:=VALUE (names of letters, digits, '
                               f'_ and / in .-separated parts), got {text!r}')
    if not match['value']:
        raise RosArgumentError(f'{flag} {text!r}: the value must not be empty')
    try:
        rules.add_rule(match['node'] or WILDCARD_KEY, match['name'], match['value'])
    except ValueError as exc:
        raise RosArgumentError(f'{flag} {text!r}: {exc}') from exc


def remove_ros_args(args: Sequence[str]) -> list[str]:
    """The command line without its ``--ros-args`` sections (like rclpy.utilities')."""
    return list(parse_ros_arguments(args).unparsed)


def _add_params_file(rules: ParamRules, path: str) -> None:
    """Read one ``--params-file`` into ``rules``.

    Raises:
        RosArgumentError: the file is missing or unreadable, not UTF-8, not YAML, or refused by
            rcl's rules (one line naming the file).
    """
    try:
        rules.add_file(path)
    except OSError as exc:
        raise RosArgumentError(f'--params-file {path!r}: {exc.strerror or exc}') from exc
    except ValueError as exc:  # one line naming the file (and line): not UTF-8, YAML, rcl's
        raise RosArgumentError(' '.join(f'--params-file {exc}'.split())) from exc


def parameter_overrides(arguments: Iterable[RosArguments], fully_qualified: str
                        ) -> dict[str, Any]:
    """The parameter overrides a node gets, as rclpy computes them (``Node.get_parameters`` in
    rclpy's node.cpp): each argument set in order (global, then the node's own), every table
    key matching ``fully_qualified`` in table order, later ones overwriting. None: NOT_SET."""
    return node_values((args.parameter_rules for args in arguments), fully_qualified)


def check_node_name(name: str) -> str:
    """Validate a node name (``[A-Za-z_][A-Za-z0-9_]*``); return it."""
    if not _TOKEN.match(name):
        raise RosArgumentError(f'invalid node name {name!r}: use letters, digits and _, '
                               'not starting with a digit')
    return name


def check_namespace(namespace: str) -> str:
    """Validate and normalize a namespace (``'ns'`` -> ``'/ns'``, ``''`` -> ``'/'``)."""
    if namespace in ('', '/'):
        return '/'
    if not namespace.startswith('/'):
        namespace = '/' + namespace
    namespace = namespace.rstrip('/')
    for token in namespace[1:].split('/'):
        if not _TOKEN.match(token):
            raise RosArgumentError(f'invalid namespace {namespace!r}: bad token {token!r}')
    return namespace


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
