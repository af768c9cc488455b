"""One typed reader: flat ROS parameters (dotted names) -> a frozen dataclass, field by field.

A field's type annotation says how its parameter is read; its default is the dataclass's own
(nothing here repeats a default); :func:`setting` adds the parameter's dotted name and the
checks a type cannot say (``positive``, ``minimum``, ``length``, ``choices``, ...)::

    @dataclass(frozen=True)
    class Bounds:
        state: float = setting(1e6, positive=True, description='largest |x_i| of a state')

    read_parameters(Bounds, {'state': 2.0}, prefix='input_bounds.')  # key input_bounds.state

Supported annotations: ``str``, ``bool``, ``int``, ``float``, ``tuple[float, ...]``,
``tuple[int, ...]``, ``tuple[str, ...]``, any of them ``| None`` (a value of None stays None),
and a nested dataclass (a group, read from ``<key>.``; ``Group | None`` with
``setting(None, when='x')``: read only when ``<key>.x`` is set).

Every value is bounded whatever its rule says: a float is finite, an integer fits the int64 a
ROS parameter holds (:data:`INT64_MAX`), and a list holds at most :data:`LIST_LIMIT` values
(``max_length`` lowers it), checked before any value of it is converted, and a string at most
:data:`STRING_LIMIT` characters, none of them a C0 control character (a NUL ends the string in
C, where rcl, DDS and the viewers read it; the others are terminal escapes or line breaks in a
name, a frame id, a topic or a path). Every error is one line that
starts with the parameter's full dotted name (``input_bounds.state: must be > 0, got -1.0``), as a
:class:`ParameterError`, a ``ValueError``: the nodes print it and exit with status 2.

Pure: no other module of ``rcbf_ros`` is imported here (any layer may use it).
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field, fields, is_dataclass
import math
import types
import typing
from typing import Any, Iterator, Mapping, Sequence, TypeVar

import numpy as np

T = TypeVar('T')

METADATA_KEY = 'rcbf_ros.parameter'
"""Key of a field's :class:`Rule` in ``dataclasses.field(metadata=...)``."""


INT64_MAX = 2 ** 63 - 1
"""The largest integer a ROS 2 parameter holds (rcl_interfaces' int64)."""
LIST_LIMIT = 4096
"""The most values a list parameter may hold unless its rule says fewer (``max_length``)."""
STRING_LIMIT = 4096
"""The most characters a string parameter (or a string of a list) may hold."""
RATE_LIMITS_HZ = (1e-3, 1e3)
"""The widest range of a rate a node's timer runs at (``rate_hz``, ``*_rate_hz``): slower, a
node seems dead (one call in over 16 minutes); faster, an idle node spins a core and its
period no longer fits the clock. Each node may declare a narrower one."""
PERIOD_LIMITS_S = (1e-3, 3600.0)
"""The widest range of a period or timeout a node's timer or wait runs on (``*_period_s``,
``*_timeout_s``; a wait that may be 0 starts at 0): its timer fits the clock (a positive
number of nanoseconds in an int64) and fires within the hour. Each node may declare a
narrower one."""


class ParameterError(ValueError):
    """A parameter value the reader refuses: one line, ``<dotted key>: <why>``."""


@dataclass(frozen=True)
class Rule:
    """How one field's parameter is named and checked (beyond its type)."""

    key: str | None = None
    """Dotted name relative to the prefix (None: the field's name)."""
    description: str = ''
    """One line for ``--help`` and the README (what it is, its unit)."""
    positive: bool = False
    """Numbers: must be > 0."""
    minimum: float | None = None
    """Numbers: must be >= this."""
    maximum: float | None = None
    """Numbers (and every number of a list): must be <= this."""
    length: int | None = None
    """Lists: exactly this many values."""
    max_length: int = LIST_LIMIT
    """Lists: at most this many values (checked before any is converted)."""
    choices: tuple[str, ...] = ()
    """Strings (or every string of a list): one of these."""
    nonempty: bool = False
    """Lists and strings: must not be empty."""
    distinct: bool = False
    """Lists: no value twice."""
    strict: bool = False
    """Integers: only an integer (an integral float such as 2.0 is refused too)."""
    text_bool: bool = False
    """Booleans: also the words true / false (any case) and numpy booleans."""
    read_only: bool = False
    """Fixed at start (a node declares it read-only)."""
    when: str | None = None
    """A nested group (``Group | None``): read only when its parameter ``when`` is set and not
    empty (``obstacles.*`` when ``obstacles.x`` lists obstacles), else None."""


def setting(default: Any = dataclasses.MISSING, **rule: Any) -> Any:
    """A dataclass field with a default and a :class:`Rule` (keyword arguments of Rule).

    Without a default the parameter is required.
    """
    return field(default=default, metadata={METADATA_KEY: Rule(**rule)})


def rule_of(item: dataclasses.Field) -> Rule:
    """The :class:`Rule` of a dataclass field (a plain field: the defaults)."""
    return item.metadata.get(METADATA_KEY, Rule())


# ------------------------------------------------------------------------------- values
def _fail(key: str, why: str) -> ParameterError:
    return ParameterError(f'{key}: {why}')


def read_bool(key: str, value: Any, *, text: bool = False) -> bool:
    """A bool; with ``text`` also 'true' / 'false' (any case) and numpy booleans."""
    if text and isinstance(value, str) and value.lower() in ('true', 'false'):
        return value.lower() == 'true'
    if isinstance(value, bool) or (text and isinstance(value, np.bool_)):
        return bool(value)
    raise _fail(key, f'expected true or false, got {_shown(value)}')


def read_float(key: str, value: Any, *, positive: bool = False, minimum: float | None = None,
               maximum: float | None = None) -> float:
    """A finite float (a numeric string counts: YAML 1.1 reads ``1.0e6`` as one; a bool does
    not)."""
    if isinstance(value, bool):
        raise _fail(key, f'expected a number, got {_shown(value)}')
    try:
        out = float(value)
    except (TypeError, ValueError, OverflowError):
        raise _fail(key, f'expected a number, got {_shown(value)}') from None
    if not math.isfinite(out):
        raise _fail(key, f'must be finite, got {out}')
    _check_range(key, out, positive=positive, minimum=minimum, maximum=maximum)
    return out


def read_int(key: str, value: Any, *, strict: bool = False, positive: bool = False,
             minimum: float | None = None, maximum: float | None = None) -> int:
    """An integer: an int, or (unless ``strict``) an integral float or an integer's text; a
    bool and 1.5 are refused (a typo must not pick another number)."""
    if isinstance(value, (int, np.integer)) and not isinstance(value, (bool, np.bool_)):
        out = int(value)
    elif strict or isinstance(value, (bool, np.bool_)):
        raise _fail(key, f'expected an integer, got {_shown(value)}')
    elif isinstance(value, (float, np.floating)):
        if not float(value).is_integer():
            raise _fail(key, f'expected an integer, got {_shown(value)}')
        out = int(value)
    else:
        try:
            out = int(str(value).strip())
        except ValueError:
            raise _fail(key, f'expected an integer, got {_shown(value)}') from None
    if not -INT64_MAX - 1 <= out <= INT64_MAX:
        raise _fail(key, f'must fit a 64-bit integer, got {_shown(out)}')
    _check_range(key, out, positive=positive, minimum=minimum, maximum=maximum)
    return out


def _shown(value: Any, width: int = 60) -> str:
    """``repr(value)`` cut to ``width`` characters (an error line stays one short line)."""
    text = repr(value)
    return text if len(text) <= width else text[:width - 3] + '...'



def _check_range(key: str, value: float, *, positive: bool, minimum: float | None,
                 maximum: float | None) -> None:
    if positive and not value > 0:
        raise _fail(key, f'must be > 0, got {value}')
    if minimum is not None and value < minimum:
        raise _fail(key, f'must be >= {minimum}, got {value}')
    if maximum is not None and value > maximum:
        raise _fail(key, f'must be <= {maximum}, got {value}')


def control_character_refusal(text: str) -> str:
    """Why ``text`` is not a parameter's string: its first C0 control character (U+0000 to
    U+001F) and where it is; '' when it holds none."""
    for index, char in enumerate(text):
        if char < ' ':
            return (f'contains the control character U+{ord(char):04X} at position {index} '
                    '(no string parameter holds one)')
    return ''


def read_str(key: str, value: Any, *, choices: Sequence[str] = (), nonempty: bool = False
             ) -> str:
    """A string, one of ``choices`` when given."""
    if not isinstance(value, str):
        if choices:
            raise _fail(key, f'expected one of {list(choices)}, got {_shown(value)}')
        raise _fail(key, f'expected a string, got {_shown(value)}')
    if choices and value not in choices:
        raise _fail(key, f'expected one of {list(choices)}, got {_shown(value)}')
    if len(value) > STRING_LIMIT:
        raise _fail(key, f'at most {STRING_LIMIT} characters, got {len(value)}')
    why = control_character_refusal(value)
    if why:
        raise _fail(key, why)
    if nonempty and not value:
        raise _fail(key, 'required (empty)')
    return value


def _items(key: str, value: Any, what: str, max_length: int = LIST_LIMIT) -> list[Any]:
    """The values of a list parameter (a scalar counts as one; None as none), at most
    ``max_length`` of them (a longer list is refused before it is copied)."""
    if value is None:
        return []
    if isinstance(value, (str, bytes)):
        raise _fail(key, f'expected a list of {what}, got {_shown(value)}')
    if isinstance(value, (bool, int, float, np.generic)):
        return [value]
    try:
        size = len(value)
    except TypeError:
        raise _fail(key, f'expected a list of {what}, got {_shown(value)}') from None
    if size > max_length:
        raise _fail(key, f'at most {max_length} values, got {size}')
    try:
        return list(value)
    except TypeError:
        raise _fail(key, f'expected a list of {what}, got {_shown(value)}') from None


def read_floats(key: str, value: Any, *, length: int | None = None, positive: bool = False,
                minimum: float | None = None, maximum: float | None = None,
                max_length: int = LIST_LIMIT) -> tuple[float, ...]:
    """Finite floats (a single number counts as one, None as none), at most ``max_length``."""
    items = _items(key, value, 'numbers', max_length)
    out = []
    for item in items:
        if isinstance(item, (bool, np.bool_)):
            raise _fail(key, f'expected a list of numbers, got {_shown(value)}')
        try:
            out.append(float(item))
        except (TypeError, ValueError, OverflowError):
            raise _fail(key, f'expected a list of numbers, got {_shown(value)}') from None
    if any(not math.isfinite(v) for v in out):
        raise _fail(key, 'contains NaN or inf')
    if length is not None and len(out) != length:
        raise _fail(key, f'expected {length} values, got {len(out)}')
    for item in out:
        _check_range(key, item, positive=positive, minimum=minimum, maximum=maximum)
    return tuple(out)


def read_ints(key: str, value: Any, *, length: int | None = None, strict: bool = False,
              max_length: int = LIST_LIMIT) -> tuple[int, ...]:
    """Integers (each as :func:`read_int`), at most ``max_length``."""
    out = tuple(read_int(key, item, strict=strict)
                for item in _items(key, value, 'integers', max_length))
    if length is not None and len(out) != length:
        raise _fail(key, f'expected {length} values, got {len(out)}')
    return out


def read_strs(key: str, value: Any, *, length: int | None = None,
              choices: Sequence[str] = (), nonempty: bool = False, distinct: bool = False,
              max_length: int = LIST_LIMIT) -> tuple[str, ...]:
    """Strings; a single string is refused (a list was meant); at most ``max_length``."""
    out = tuple(_items(key, value, 'strings', max_length))
    if not all(isinstance(v, str) for v in out):
        raise _fail(key, f'expected a list of strings, got {_shown(value)}')
    if any(len(v) > STRING_LIMIT for v in out):
        raise _fail(key, f'at most {STRING_LIMIT} characters a string')
    for index, item in enumerate(out):
        why = control_character_refusal(item)
        if why:
            raise _fail(key, f'value {index}: {why}')
    bad = [v for v in out if choices and v not in choices]
    if bad:
        raise _fail(key, f'{_shown(bad)} not in {list(choices)}')
    if nonempty and not out:
        raise _fail(key, 'must not be empty')
    if distinct and len(set(out)) != len(out):
        raise _fail(key, f'repeated value in {_shown(list(out))}')
    if length is not None and len(out) != length:
        raise _fail(key, f'expected {length} values, got {len(out)}')
    return out


# ------------------------------------------------------------------------------- fields
def _unwrap(kind: Any) -> tuple[Any, bool]:
    """(the type without ``| None``, whether None is allowed)."""
    args = typing.get_args(kind)
    union = getattr(types, 'UnionType', None)
    if typing.get_origin(kind) is typing.Union or (union and isinstance(kind, union)):
        rest = [a for a in args if a is not type(None)]
        if len(rest) == 1:
            return rest[0], len(rest) < len(args)
    return kind, False


def read_value(key: str, value: Any, kind: Any, rule: Rule = Rule()) -> Any:
    """One parameter value as the annotation ``kind`` with ``rule``'s checks.

    Raises:
        ParameterError: naming ``key``.
        TypeError: ``kind`` is not a supported annotation (a programming error).
    """
    kind, optional = _unwrap(kind)
    if value is None and optional:
        return None
    numbers = dict(positive=rule.positive, minimum=rule.minimum, maximum=rule.maximum)
    if kind is bool:
        return read_bool(key, value, text=rule.text_bool)
    if kind is int:
        return read_int(key, value, strict=rule.strict, **numbers)
    if kind is float:
        return read_float(key, value, **numbers)
    if kind is str:
        return read_str(key, value, choices=rule.choices, nonempty=rule.nonempty)
    if typing.get_origin(kind) is tuple:
        item = typing.get_args(kind)[0]
        if item is float:
            out = read_floats(key, value, length=rule.length, positive=rule.positive,
                              minimum=rule.minimum, maximum=rule.maximum,
                              max_length=rule.max_length)
        elif item is int:
            out = read_ints(key, value, length=rule.length, strict=rule.strict,
                            max_length=rule.max_length)
        elif item is str:
            out = read_strs(key, value, length=rule.length, choices=rule.choices,
                            nonempty=rule.nonempty, distinct=rule.distinct,
                            max_length=rule.max_length)
        else:
            raise TypeError(f'{key}: unsupported list type {kind!r}')
        if rule.nonempty and not out:
            raise _fail(key, 'must not be empty')
        return out
    raise TypeError(f'{key}: unsupported parameter type {kind!r}')


@dataclass(frozen=True)
class Parameter:
    """One parameter of a dataclass, as :func:`parameters_of` lists it."""

    key: str
    """Full dotted name."""
    kind: Any
    """The field's type annotation (resolved)."""
    default: Any
    """The dataclass's default (``dataclasses.MISSING``: required)."""
    rule: Rule
    """Name and checks."""

    @property
    def required(self) -> bool:
        """Whether the dataclass has no default for it."""
        return self.default is dataclasses.MISSING


def _default(item: dataclasses.Field) -> Any:
    if item.default is not dataclasses.MISSING:
        return item.default
    if item.default_factory is not dataclasses.MISSING:  # type: ignore[misc]
        return item.default_factory()  # type: ignore[misc]
    return dataclasses.MISSING


def _group(kind: Any) -> type | None:
    """The dataclass of a nested group field (``Group`` or ``Group | None``), else None."""
    kind = _unwrap(kind)[0]
    return kind if isinstance(kind, type) and is_dataclass(kind) else None


def _fields(cls: type) -> Iterator[tuple[dataclasses.Field, Any, Rule]]:
    hints = typing.get_type_hints(cls)
    for item in fields(cls):
        if item.init:
            yield item, hints[item.name], rule_of(item)


def parameters_of(cls: type, *, prefix: str = '') -> tuple[Parameter, ...]:
    """Every parameter :func:`read_parameters` reads for ``cls``, nested ones flattened, in
    field order."""
    out: list[Parameter] = []
    for item, kind, rule in _fields(cls):
        key = prefix + (rule.key or item.name)
        group = _group(kind)
        if group is not None:
            out.extend(parameters_of(group, prefix=key + '.'))
        else:
            out.append(Parameter(key=key, kind=kind, default=_default(item), rule=rule))
    return tuple(out)


def parameter_keys(cls: type, *, prefix: str = '') -> tuple[str, ...]:
    """The full dotted names of :func:`parameters_of`."""
    return tuple(p.key for p in parameters_of(cls, prefix=prefix))


def defaults_of(cls: type, *, prefix: str = '') -> dict[str, Any]:
    """Dotted name -> the dataclass's default, for every parameter that has one."""
    return {p.key: p.default for p in parameters_of(cls, prefix=prefix) if not p.required}


def read_parameters(cls: type[T], params: Mapping[str, Any], *, prefix: str = '') -> T:
    """``cls`` from flat parameters: each field from ``params[prefix + key]``, else its default.

    Keys of ``params`` that ``cls`` does not name are left alone (a params file holds the
    keys of several readers). ``cls``'s own ``__post_init__`` checks run after the fields'; a
    ``ValueError`` there passes through as it is (it names the field).

    Raises:
        ParameterError: one line naming the bad (or missing required) key.
    """
    values: dict[str, Any] = {}
    for item, kind, rule in _fields(cls):
        key = prefix + (rule.key or item.name)
        group = _group(kind)
        if group is not None:
            if rule.when is None or params.get(f'{key}.{rule.when}') not in (None, [], ()):
                values[item.name] = read_parameters(group, params, prefix=key + '.')
        elif key in params:
            values[item.name] = read_value(key, params[key], kind, rule)
        elif _default(item) is dataclasses.MISSING:
            raise _fail(key, 'required')
    return cls(**values)  # type: ignore[call-arg]
