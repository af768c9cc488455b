"""Node interfaces as data: the parameters each node declares and the topics it uses.

One :class:`ParameterSpec` per declared parameter (name, default, type, one line) is the single
source of a node's declarations, of its ``--help`` (:func:`help_text`, printed without starting
the node: no DDS participant) and of docs/INTERFACE.md's tables
(:mod:`rcbf_ros.cli.interface_doc`), so that the three cannot drift apart. Pure: no
middleware, no messages.
"""
from __future__ import annotations

from dataclasses import dataclass
import math
import typing
from typing import Any, Callable, Sequence, Union

from rcbf_ros.messages.conversions import FLOAT64_MULTIARRAY
from rcbf_ros.parameters.reader import INT64_MAX, parameters_of

DEFAULT_QOS = 'reliable, keep-last 10'
"""The QoS text of a topic with ROS 2's default profile (``--help``, README)."""
DIAGNOSTIC_ARRAY = 'diagnostic_msgs/msg/DiagnosticArray'
"""The type of ``diagnostics``."""
OBSTACLES_QOS = 'reliable, keep-last 1, transient-local'
"""QoS of an ``obstacles`` subscription: the latest set only; a latched one is picked up."""
STATE_TOPIC_TYPES = f'{FLOAT64_MULTIARRAY} or nav_msgs/msg/Odometry'
"""The types a ``state`` topic takes (``state_type``)."""
COMMAND_TOPIC_TYPES = (f'{FLOAT64_MULTIARRAY}, geometry_msgs/msg/Twist or '
                       'geometry_msgs/msg/TwistStamped')
"""The types a command topic takes (``command_type``)."""
READ_ONLY_SUFFIX = '; read-only'
"""Ends the description of a parameter fixed at start."""
RANGE_TOLERANCE = 1e-6
"""rclpy's relative tolerance at the ends of a FloatingPointRange."""

PARAMETER_TYPES = ('string', 'bool', 'integer', 'double', 'string[]', 'integer[]', 'double[]',
                   'any')
"""ROS 2 parameter types a spec can name (``any``: whatever the user gives, e.g. a system's
constructor arguments)."""


@dataclass(frozen=True)
class ParameterSpec:
    """One parameter a node declares."""

    name: str
    """Dotted name as in the params file (``input_bounds.state``). ``<name>`` marks a part the
    user chooses (``bands.<name>.index``): such parameters are declared when given."""
    default: Any
    """The declared default; None: not set (taken from the params file, else the behaviour the
    description names)."""
    type: str
    """One of :data:`PARAMETER_TYPES`."""
    description: str
    """One line: what it is, its unit and its allowed values."""
    minimum: float | None = None
    """Numbers: the least value (inclusive); None: none."""
    maximum: float | None = None
    """Numbers: the largest value (inclusive); None: none."""
    positive: bool = False
    """Numbers: must be > 0."""

    def __post_init__(self) -> None:
        if self.type not in PARAMETER_TYPES:
            raise ValueError(f'{self.name}: type {self.type!r} not in {list(PARAMETER_TYPES)}')
        if '\n' in self.description or not self.description.strip():
            raise ValueError(f'{self.name}: the description must be one non-empty line')

    @property
    def range(self) -> tuple[float, float] | None:
        """(least, largest) value of a ``double`` or ``integer`` parameter, both inclusive, as
        a ROS 2 FloatingPointRange / IntegerRange declares it; None: no range (other types, or
        no bound). ``positive`` is the least value above 0: the smallest subnormal double
        (5e-324) or 1; an open end is +-inf, or the int64 ends."""
        if self.type not in ('double', 'integer') or (
                self.minimum is None and self.maximum is None and not self.positive):
            return None
        integer = self.type == 'integer'
        low, high = ((-INT64_MAX - 1, INT64_MAX) if integer else (-math.inf, math.inf))
        if self.minimum is not None:
            low = math.ceil(self.minimum) if integer else float(self.minimum)
        if self.positive:
            low = max(low, 1 if integer else math.ulp(0.0))
        if self.maximum is not None:
            high = math.floor(self.maximum) if integer else float(self.maximum)
        return low, high

    def range_refuses(self, value: Any) -> bool:
        """Whether the declared :attr:`range` refuses ``value``, as rclpy's check does: a value
        of the range's type only (a double's range leaves an integer to the node's own checks),
        the ends within :data:`RANGE_TOLERANCE` in for a double and exactly for an integer,
        NaN not refused."""
        bounds = self.range
        kind = {'double': float, 'integer': int}.get(self.type)
        if bounds is None or type(value) is not kind or not (
                value < bounds[0] or value > bounds[1]):
            return False
        return not (kind is float and any(
            math.isclose(value, edge, rel_tol=RANGE_TOLERANCE) for edge in bounds))

    @property
    def pattern(self) -> bool:
        """Whether the name holds a user-chosen part (``<name>``)."""
        return '<' in self.name

    def matches(self, name: str) -> bool:
        """Whether a declared parameter ``name`` is this spec (a pattern matches any word)."""
        if not self.pattern:
            return name == self.name
        mine, theirs = self.name.split('.'), name.split('.')
        if mine[-1] == '<name>' and len(theirs) >= len(mine):  # system_params.<name>
            theirs = theirs[:len(mine) - 1] + ['.'.join(theirs[len(mine) - 1:])]
        return len(mine) == len(theirs) and all(
            a == b or (a.startswith('<') and b) for a, b in zip(mine, theirs))


@dataclass(frozen=True)
class TopicSpec:
    """One topic a node publishes or subscribes (name relative to the node: remappable)."""

    name: str
    """Topic name as the node uses it (``cmd_safe``)."""
    direction: str
    """``pub`` or ``sub``."""
    type: str
    """Message type (``std_msgs/msg/Float64MultiArray``), or the choice a parameter makes."""
    layout: str
    """What the message holds (sections, fields, units), one line."""
    qos: str = DEFAULT_QOS
    """``reliable``/``best effort``, history and depth."""

    def __post_init__(self) -> None:
        if self.direction not in ('pub', 'sub'):
            raise ValueError(f'{self.name}: direction must be pub or sub, got {self.direction!r}')


@dataclass(frozen=True)
class NodeInterface:
    """What ``<node> --help`` prints and the README's section on the node shows."""

    node: str
    """Node (and console script) name."""
    summary: str
    """One line: what the node does."""
    topics: tuple[TopicSpec, ...]
    """Every topic, publications and subscriptions."""
    parameters: tuple[ParameterSpec, ...]
    """Every parameter it declares, in declaration order."""
    notes: tuple[str, ...] = ()
    """Lines printed after the parameters (e.g. where system-dependent keys come from)."""

    def __post_init__(self) -> None:
        names = [p.name for p in self.parameters]
        repeated = sorted({n for n in names if names.count(n) > 1})
        if repeated:
            raise ValueError(f'{self.node}: parameters declared twice: {repeated}')

    def spec(self, name: str) -> ParameterSpec | None:
        """The spec a declared parameter ``name`` falls under (None: undocumented)."""
        for spec in self.parameters:
            if spec.matches(name):
                return spec
        return None


InterfaceSource = Union[NodeInterface, Callable[[Sequence[str]], NodeInterface]]
"""A node's interface, or a function of its command line (when ``system`` changes it)."""


_SCALAR_TYPES = {str: 'string', bool: 'bool', int: 'integer', float: 'double'}


def parameter_type(kind: Any) -> str:
    """The ROS parameter type (:data:`PARAMETER_TYPES`) of a dataclass field's annotation."""
    args = [a for a in typing.get_args(kind) if a is not type(None)]
    if typing.get_origin(kind) is tuple:
        return _SCALAR_TYPES[args[0]] + '[]'
    if args and typing.get_origin(kind) is not None:  # X | None
        return parameter_type(args[0])
    return _SCALAR_TYPES[kind]


def parameter_specs(cls: type, *, prefix: str = '', declared_defaults: bool = True,
                    say_default: bool = False, mark_read_only: bool = True
                    ) -> tuple[ParameterSpec, ...]:
    """One spec per parameter of the dataclass ``cls`` (:func:`rcbf_ros.parameters.reader.
    parameters_of`), in field order: the description from its rule (``; read-only`` added when
    it is fixed at start), the type from its annotation, the default from the dataclass.

    Args:
        declared_defaults: declare the dataclass's defaults; False: not set (None), the reader
            applies the default (keys of a params file, declared when given).
        say_default: add ``(default <value>)`` to the description (with ``declared_defaults``
            False, so that the default is still shown).
        mark_read_only: say ``read-only`` for a parameter the node declares read-only (the
            rule's ``read_only``); False for a node that declares none so.
    """
    specs = []
    for parameter in parameters_of(cls, prefix=prefix):
        default = None if parameter.required else parameter.default
        if isinstance(default, tuple):
            default = list(default)  # what a params file and the runtimes hold
        description = parameter.rule.description
        if say_default and default not in (None, '', []):
            description += f' (default {format_value(default)})'
        if mark_read_only and parameter.rule.read_only:
            description += READ_ONLY_SUFFIX
        rule = parameter.rule
        specs.append(ParameterSpec(
            parameter.key, default if declared_defaults else None,
            parameter_type(parameter.kind), description, minimum=rule.minimum,
            maximum=rule.maximum, positive=rule.positive))
    return tuple(specs)


def declarations(specs: Sequence[ParameterSpec]) -> list[tuple[str, Any]]:
    """(name, default) of every spec with a fixed name, in order: what a node declares."""
    return [(spec.name, spec.default) for spec in specs if not spec.pattern]


def wants_help(argv: Sequence[str]) -> bool:
    """Whether ``-h`` or ``--help`` is among the words outside ``--ros-args`` sections
    (``argv[0]``, the program, is not looked at)."""
    inside = False
    for word in list(argv)[1:]:
        if word == '--ros-args':
            inside = True
        elif word == '--' and inside:
            inside = False
        elif not inside and word in ('-h', '--help'):
            return True
    return False


def format_value(value: Any) -> str:
    """A parameter value as it is written on the command line (``-p name:=<value>``)."""
    if value is None:
        return 'not set'
    if isinstance(value, bool):
        return 'true' if value else 'false'
    if isinstance(value, float):
        return repr(value) if math.isfinite(value) else str(value)
    if isinstance(value, str):
        return repr(value) if value == '' or value.strip() != value else value
    if isinstance(value, (list, tuple)):
        return '[' + ', '.join(format_value(v) for v in value) + ']'
    return str(value)


def help_text(interface: NodeInterface) -> str:
    """The ``--help`` of a node: usage, topics, parameters (type, default, one line each)."""
    lines = [f'usage: {interface.node} [-h] [--ros-args [-p name:=value] [-r from:=to] '
             '[--params-file file.yaml]]', '', interface.summary, '', 'topics:']
    width = max((len(t.name) for t in interface.topics), default=0)
    for topic in interface.topics:
        lines.append(f'  {topic.direction} {topic.name:<{width}}  {topic.type}')
        lines.append(f'      {topic.layout}; QoS: {topic.qos}')
    lines += ['', 'parameters (-p name:=value):']
    for spec in interface.parameters:
        lines.append(f'  {spec.name}  ({spec.type}, default {format_value(spec.default)}'
                     f'{range_text(spec)})')
        lines.append(f'      {spec.description}')
    if interface.notes:
        lines += [''] + list(interface.notes)
    return '\n'.join(lines) + '\n'


def range_text(spec: ParameterSpec, lead: str = ', range ') -> str:
    """``<lead><least> to <largest>`` of a spec with a declared range, else ''."""
    bounds = spec.range
    if bounds is None:
        return ''
    return f'{lead}{bound_text(bounds[0])} to {bound_text(bounds[1])}'


def bound_text(bound: float) -> str:
    """A range's end as people read it: an integer as it is, a float in its shortest exact
    form when that is short (``5e-324``, ``0.0``, ``inf``), else to 6 digits (``1e+15``)."""
    if isinstance(bound, int):
        return str(bound)
    text = repr(float(bound))
    return text if len(text) <= 12 else f'{bound:.6g}'


def _cell(text: str) -> str:
    """Text for a markdown table cell: ``|`` escaped, ``<name>`` shown rather than taken for
    HTML (code spans, where GitHub shows ``<`` as it is, are left alone)."""
    parts = text.replace('|', '\\|').split('`')
    for index in range(0, len(parts), 2):  # outside code spans
        parts[index] = parts[index].replace('<', '&lt;')
    return '`'.join(parts)


def _table(header: Sequence[str], rows: Sequence[Sequence[str]]) -> str:
    """A markdown table."""
    lines = ['| ' + ' | '.join(header) + ' |', '|' + '---|' * len(header)]
    lines += ['| ' + ' | '.join(row) + ' |' for row in rows]
    return '\n'.join(lines)


def topic_table(interface: NodeInterface) -> str:
    """The node's topics as a markdown table."""
    return _table(('topic', 'direction', 'type', 'layout', 'QoS'), [
        (f'`{t.name}`', t.direction, _cell(t.type), _cell(t.layout), t.qos)
        for t in interface.topics])


def parameter_table(interface: NodeInterface) -> str:
    """The node's parameters as a markdown table."""
    return _table(('parameter', 'type', 'default', 'description'), [
        (f'`{p.name}`', p.type + range_text(p, lead=', '),
         f'`{format_value(p.default)}`', _cell(p.description))
        for p in interface.parameters])


def resolve(source: InterfaceSource, argv: Sequence[str]) -> NodeInterface:
    """The interface of ``source`` for the command line ``argv``."""
    return source if isinstance(source, NodeInterface) else source(argv)


def type_of(value: Any) -> str:
    """The parameter type of a (YAML) value: ``double[]`` for a list of numbers, ..."""
    if isinstance(value, bool):
        return 'bool'
    if isinstance(value, int):
        return 'integer'
    if isinstance(value, float):
        return 'double'
    if isinstance(value, (list, tuple)):
        if value and all(isinstance(v, str) for v in value):
            return 'string[]'
        if value and all(isinstance(v, int) and not isinstance(v, bool) for v in value):
            return 'integer[]'
        return 'double[]'
    return 'string'
