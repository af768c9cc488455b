"""ROS 2 parameter files and ``-p`` rules read exactly as rcl and rclpy (Jazzy) read them.

Every ``--params-file`` and ``-p`` of one command line fills one table of node keys, which a
node reads in the order the keys first appeared (the last matching key wins), typed as rcl's
YAML parser types values (``rcl_yaml_param_parser``; rclpy's ``node.cpp`` for the overrides).
Files are read within :mod:`rcbf_ros.parameters.bounded_yaml`'s limits. Pure (no ROS, no DDS):
the Cyclone runtime's nodes and the offline scripts (``load_params``) read parameters here, so
both get what a node on rclpy gets. The rules in full: docs/NODES.md.
"""
from __future__ import annotations

from importlib import resources
import math
import os
from pathlib import Path
import re
from typing import Any, Iterable

import yaml

from rcbf_ros.parameters import bounded_yaml

_SOURCE_CONFIG_DIR = Path(__file__).resolve().parents[2] / 'config'
PACKAGE = 'rcbf_ros'

PARAMS_KEY = 'ros__parameters'
WILDCARD_KEY = '/**'
"""The node key of a bare ``-p name:=value`` (every node)."""
MAX_PARAMS_FILE_BYTES = 128 * 2**10
"""Largest params file read (128 KiB): a larger one is refused after reading this much, never
read whole. The packaged configs hold at most 6 KiB, a large ROS 2 params file (nav2's) about
20 KiB; rcl's table is quadratic in the number of parameters, so that 128 KiB of distinct
one-line parameters still reads in seconds."""

# rcl_variant_t's slots in the order rclpy reads them (_parameter_from_rcl_variant).
_SLOTS = ('bool', 'integer', 'double', 'string', 'bool_array', 'integer_array', 'double_array',
          'string_array')
_TRUE = frozenset({'Y', 'y', 'yes', 'Yes', 'YES', 'true', 'True', 'TRUE', 'on', 'On', 'ON'})
_FALSE = frozenset({'N', 'n', 'no', 'No', 'NO', 'false', 'False', 'FALSE', 'off', 'Off', 'OFF'})
_SPECIAL_FLOATS = frozenset({'.nan', '.NaN', '.NAN', '.inf', '.Inf', '.INF', '+.inf', '+.Inf',
                             '+.INF', '-.inf', '-.Inf', '-.INF'})
_STR_TAG = 'tag:yaml.org,2002:str'
_C_SPACE = ' \t\n\v\f\r'
_STRTOLL = re.compile(r'[+-]?(?:0[xX][0-9a-fA-F]+|0[0-7]*|[1-9][0-9]*)')
_STRTOD = re.compile(
    r'[+-]?(?:0[xX](?:[0-9a-fA-F]+\.?[0-9a-fA-F]*|\.[0-9a-fA-F]+)(?:[pP][+-]?[0-9]+)?'
    r'|(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][+-]?[0-9]+)?'
    r'|[iI][nN][fF](?:[iI][nN][iI][tT][yY])?|[nN][aA][nN](?:\([0-9A-Za-z_]*\))?)')
_NAME_TOKEN = re.compile(r'[A-Za-z_][A-Za-z0-9_]*')
_INT64 = (-2**63, 2**63 - 1)
_DBL_MIN = 2.2250738585072014e-308
_NODE_LEVEL, _PARAMS_LEVEL = 1, 2


class ParamsFileError(ValueError):
    """A parameter file or ``-p`` rule that rcl refuses (the message says where and why)."""


# ----------------------------------------------------------------------------- scalars
def _c_whole(pattern: re.Pattern[str], text: str) -> tuple[int, str] | None:
    """(sign, the unsigned number) when ``pattern`` reads all of ``text`` after C's leading
    white space (as ``strto*`` with ``*end == '\\0'``), else None."""
    body = text.lstrip(_C_SPACE)
    match = pattern.match(body)
    if body == '' or match is None or match.end() != len(body):
        return None
    number = match.group(0)
    return (-1 if number.startswith('-') else 1), number.lstrip('+-')


def _c_strtoll(text: str) -> int | None:
    """``strtoll(text, &end, 0)`` when it reads all of ``text`` without overflow, else None."""
    whole = _c_whole(_STRTOLL, text)
    if whole is None:
        return None
    sign, digits = whole
    if digits[:2] in ('0x', '0X'):
        value = int(digits[2:], 16)
    elif digits.startswith('0'):
        value = int(digits, 8)
    else:
        value = int(digits)
    value *= sign
    return value if _INT64[0] <= value <= _INT64[1] else None


def _c_strtod(text: str) -> float | None:
    """``strtod(text, &end)`` when it reads all of ``text`` without ERANGE, else None."""
    whole = _c_whole(_STRTOD, text)
    if whole is None:
        return None
    sign, unsigned = whole
    if unsigned[0] in 'iInN':
        value = float(unsigned[:3])
    else:
        is_hex = unsigned[:2] in ('0x', '0X')
        value = float.fromhex(unsigned) if is_hex else float(unsigned)
        mantissa = re.split('[pP]' if is_hex else '[eE]', unsigned[2:] if is_hex else unsigned)[0]
        if math.isinf(value) or (abs(value) < _DBL_MIN and mantissa.strip('0.') != ''):
            return None  # overflow or underflow: strtod sets ERANGE
    return sign * value


def scalar_value(text: str, *, quoted: bool = False, str_tag: bool = False) -> tuple[str, Any]:
    """The type slot and value rcl gives a YAML scalar (``get_value``).

    Args:
        text: the scalar's text.
        quoted: single- or double-quoted (then never a bool or a number).
        str_tag: tagged ``!!str``.

    Returns:
        ``('bool' | 'integer' | 'double' | 'string', value)``.
    """
    if str_tag:
        return 'string', text
    if not quoted:
        if text in _TRUE:
            return 'bool', True
        if text in _FALSE:
            return 'bool', False
        integer = _c_strtoll(text)
        if integer is not None:
            return 'integer', integer
        if text in _SPECIAL_FLOATS:
            value = float('nan') if 'nan' in text.lower() else float('inf')
            return 'double', -value if text.startswith('-') else value
        number = _c_strtod(text)
        if number is not None:
            return 'double', number
    return 'string', text


# ----------------------------------------------------------------------------- the table
class _Variant:
    """rcl_variant_t: one slot per type; the first set slot (in ``_SLOTS`` order) counts."""

    __slots__ = ('slots',)

    def __init__(self) -> None:
        self.slots: dict[str, Any] = {}

    @property
    def value(self) -> Any:
        """The value rclpy reads (None: NOT_SET). Lists are copies."""
        for slot in _SLOTS:
            if slot in self.slots:
                value = self.slots[slot]
                return list(value) if isinstance(value, list) else value
        return None


class ParamRules:
    """rcl_params_t: node keys in order of first appearance, each holding ``[name, variant]``
    entries in order of first appearance (see the module docstring for the rules).

    Built by :meth:`add_file` (``--params-file``) and :meth:`add_rule` (``-p``) in command-line
    order; read by :meth:`values_for` (what one node gets) and :meth:`sections`.
    """

    def __init__(self) -> None:
        self._keys: list[str] = []
        self._entries: list[list[list[Any]]] = []
        self.repeated_keys: list[str] = []
        """One line per key given twice in one mapping of a params file: read as rcl reads it
        (the later value of the same type replaces the earlier), and reported, since which of
        two lines sets a safety parameter should not go unsaid."""

    def __bool__(self) -> bool:
        return bool(self._keys)

    def __repr__(self) -> str:
        return f'ParamRules({self.sections()!r})'

    # rcl's find_node / find_parameter ---------------------------------------------------
    def _node_index(self, key: str) -> int:
        if key in self._keys:
            return self._keys.index(key)
        self._keys.append(key)
        self._entries.append([])
        return len(self._keys) - 1

    def _parameter_index(self, node: int, name: str) -> int:
        entries = self._entries[node]
        for index, (existing, _) in enumerate(entries):
            if existing == name:
                return index
        entries.append([name, _Variant()])
        return len(entries) - 1

    # building -------------------------------------------------------------------------------
    def add_file(self, path: str | Path) -> None:
        """Read one ``--params-file`` into the table (``rcl_parse_yaml_file``).

        Raises:
            OSError: the file cannot be read, or is not a regular file.
            ParamsFileError: not UTF-8, not YAML (``'<file>': not valid YAML at line L,
                column C: <problem>``, one line; its ``__cause__`` is PyYAML's error), refused
                by rcl, or past a limit (size, depth, tag; the message names the file and the
                line).
        """
        path = str(path)
        try:
            text = bounded_yaml.read_limited(path, max_bytes=MAX_PARAMS_FILE_BYTES,
                                             what='params file')
        except bounded_yaml.YAMLLimitError as exc:
            raise ParamsFileError(f'{path!r}: larger than the {MAX_PARAMS_FILE_BYTES}-byte '
                                  'limit of a params file') from exc
        except UnicodeDecodeError as exc:
            raise ParamsFileError(f'{path!r}: not UTF-8 text ({exc.reason} at byte '
                                  f'{exc.start})') from exc
        try:  # YAML syntax first: its position says more than where rcl's rules would stop
            events = list(bounded_yaml.checked_events(text, source=repr(path),
                                                      repeated_keys=self.repeated_keys))
        except bounded_yaml.YAMLLimitError as exc:
            raise ParamsFileError(str(exc)) from exc
        except yaml.YAMLError as exc:
            raise ParamsFileError(f'{path!r}: {bounded_yaml.syntax_error_line(exc)}') from exc
        _FileParser(self, path).run(events)

    def add_rule(self, node_key: str, name: str, text: str) -> None:
        """One ``-p [node:]name:=text`` (``rcl_parse_yaml_value``).

        Raises:
            ParamsFileError: an empty part, or a value that is not a scalar or a flat list of
                one type.
        """
        if not node_key or not name or not text:
            raise ParamsFileError(f'-p {name}:={text}: the name and the value must not be empty')
        node = self._node_index(node_key)
        parameter = self._parameter_index(node, name)
        variant = self._entries[node][parameter][1]
        in_sequence, sequence_slot = False, None
        try:
            for event in bounded_yaml.checked_events(text, source=f'-p {name}'):
                if isinstance(event, yaml.ScalarEvent):
                    sequence_slot = _set_value(variant, event, in_sequence, sequence_slot,
                                               f'-p {name}')
                elif isinstance(event, yaml.SequenceStartEvent):
                    in_sequence, sequence_slot = True, None
                elif isinstance(event, yaml.SequenceEndEvent):
                    in_sequence = False
                elif not isinstance(event, (yaml.StreamStartEvent, yaml.StreamEndEvent,
                                            yaml.DocumentStartEvent, yaml.DocumentEndEvent)):
                    raise ParamsFileError(f'-p {name}:={text}: a value must be a scalar or a '
                                          'list of scalars')
        except bounded_yaml.YAMLLimitError as exc:
            raise ParamsFileError(str(exc)) from exc
        except yaml.YAMLError as exc:
            raise ParamsFileError(f'-p {name}:={text}: {bounded_yaml.syntax_error_line(exc)}'
                                  ) from exc

    # reading --------------------------------------------------------------------------------
    def sections(self) -> dict[str, dict[str, Any]]:
        """Node key (as written) -> {parameter name: value (None: NOT_SET)}, in table order."""
        result: dict[str, dict[str, Any]] = {}
        for key, entries in zip(self._keys, self._entries):
            result[key] = {name: variant.value for name, variant in entries}
        return result

    def values_for(self, fully_qualified: str) -> dict[str, Any]:
        """What a node of this fully qualified name gets: every matching key in table order,
        the later ones overwriting (None: NOT_SET)."""
        values: dict[str, Any] = {}
        for key, entries in zip(self._keys, self._entries):
            if key_matches(key, fully_qualified):
                for name, variant in entries:
                    values[name] = variant.value
        return values


def node_values(rules: Iterable[ParamRules], fully_qualified: str) -> dict[str, Any]:
    """rclpy's parameter overrides of one node: the tables in order (global arguments, then the
    node's own), each as :meth:`ParamRules.values_for`; later ones overwrite earlier ones."""
    values: dict[str, Any] = {}
    for table in rules:
        values.update(table.values_for(fully_qualified))
    return values


def key_pattern(key: str) -> re.Pattern[str]:
    """The regular expression rclpy matches a node's fully qualified name against.

    A leading ``/`` is added if missing; every ``/*`` becomes one ``/token`` group, so ``/**``
    is any number of tokens (``/*`` followed by ``*``).
    """
    name = key if key.startswith('/') else '/' + key
    pieces = [re.escape(piece).replace(r'\*', '*') for piece in name.split('/*')]
    return re.compile(r'(/\w+)'.join(pieces), re.ASCII)


def key_matches(key: str, fully_qualified: str) -> bool:
    """True if a params-file key applies to the node ``fully_qualified``."""
    try:
        return key_pattern(key).fullmatch(fully_qualified) is not None
    except re.error:
        return False


def node_key_level(key: str, node_name: str, fully_qualified: str) -> int:
    """How a params-file key applies to a node: 0 not at all, 1 through a wildcard, 2 by its
    own name (``node_name`` is kept for callers that know only the name)."""
    del node_name
    if not key_matches(key, fully_qualified):
        return 0
    return 1 if '*' in key else 2


# ----------------------------------------------------------------------------- the file parser
def _set_value(variant: _Variant, event: yaml.ScalarEvent, in_sequence: bool,
               sequence_slot: str | None, where: str) -> str | None:
    """rcl's ``parse_value``: put one scalar into ``variant``; returns the sequence's slot."""
    quoted = event.style in ("'", '"')
    if not quoted and event.value == '':
        raise ParamsFileError(f'{where}: no value')
    slot, value = scalar_value(event.value, quoted=quoted, str_tag=event.tag == _STR_TAG)
    if not in_sequence:
        variant.slots[slot] = value
        return sequence_slot
    if sequence_slot is None:
        variant.slots[slot + '_array'] = [value]
        return slot
    if slot != sequence_slot:
        raise ParamsFileError(f'{where}: a list must hold one type; {event.value!r} is a '
                              f'{slot}, the first item a {sequence_slot}')
    variant.slots[slot + '_array'].append(value)
    return sequence_slot


class _Namespace:
    """rcl's namespace tracker of one kind: the joined names and how many were joined."""

    def __init__(self, separator: str) -> None:
        self.separator = separator
        self.text: str | None = None
        self.count = 0

    def push(self, name: str) -> None:
        if self.count == 0 or self.text is None:
            self.text = name
        elif self.text.endswith(self.separator):
            self.text += name
        else:
            self.text += self.separator + name
        self.count += 1

    def pop(self) -> None:
        if self.count == 0:
            return
        if self.count == 1 or self.text is None:
            self.text = None
        else:
            cut = self.text.rfind(self.separator)
            if cut >= 0:
                self.text = self.text[:cut]
        self.count -= 1

    def replace(self, text: str, count: int) -> None:
        self.text, self.count = text, count


def _check_node_key(key: str, where: str) -> None:
    """rcl's ``_validate_name``: ``/**``, ``/*``, or [namespace/]node whose namespace tokens and
    node name are names or the wildcards ``*`` and ``**``."""
    if key in ('/**', '/*'):
        return
    cut = key.rfind('/')
    node = key[cut + 1:]
    absolute = key[:cut + 1] if key.startswith('/') else '/' + key[:cut + 1]
    for token in absolute[1:-1].split('/') if cut >= 0 and len(absolute) > 1 else ():
        if token == '':
            raise ParamsFileError(f'{where}: node key {key!r} repeats /')
        if token not in ('*', '**') and not _NAME_TOKEN.fullmatch(token):
            raise ParamsFileError(f'{where}: node key {key!r}: invalid namespace token '
                                  f'{token!r}')
    if node not in ('*', '**') and not _NAME_TOKEN.fullmatch(node):
        raise ParamsFileError(f'{where}: node key {key!r}: invalid node name {node!r} '
                              '(letters, digits and _, or the wildcards * and **)')


class _FileParser:
    """rcl's ``parse_file_events`` state machine over PyYAML's events, filling a table."""

    def __init__(self, rules: ParamRules, path: str) -> None:
        self.rules = rules
        self.path = path
        self.nodes = _Namespace('/')
        self.params = _Namespace('.')
        self.is_key = True
        self.in_sequence = False
        self.sequence_slot: str | None = None
        self.level = _NODE_LEVEL
        self.depth = 0
        self.new_map = False
        self.node = 0
        self.parameter = 0

    def fail(self, line: int, problem: str) -> ParamsFileError:
        return ParamsFileError(f'{self.path!r}: line {line}: {problem}')

    def run(self, events: Iterable[yaml.Event]) -> None:
        for event in events:
            line = event.start_mark.line + 1 if event.start_mark is not None else 0
            if isinstance(event, yaml.ScalarEvent):
                if self.is_key:
                    self.key(event.value, line)
                    self.is_key = False
                else:
                    self.value(event, line)
            elif isinstance(event, yaml.SequenceStartEvent):
                if self.depth == 0:
                    raise self.fail(line, 'top level must map node names')
                if self.is_key:
                    raise self.fail(line, 'a list cannot be a key')
                if self.level < _PARAMS_LEVEL:
                    raise self.fail(line, f'{self.nodes.text!r} has no {PARAMS_KEY}')
                self.in_sequence, self.sequence_slot = True, None
            elif isinstance(event, yaml.SequenceEndEvent):
                self.in_sequence, self.is_key = False, True
            elif isinstance(event, yaml.MappingStartEvent):
                self.mapping_start()
            elif isinstance(event, yaml.MappingEndEvent):
                self.mapping_end()
            elif isinstance(event, yaml.AliasEvent):
                raise self.fail(line, 'YAML aliases are not supported')

    def key(self, text: str, line: int) -> None:
        """rcl's ``parse_key``."""
        if text == '':
            raise self.fail(line, 'empty key')
        if self.level == _NODE_LEVEL:
            if not text.startswith(PARAMS_KEY):
                self.nodes.push(text)
                return
            if self.nodes.count == 0 or self.nodes.text is None:
                raise self.fail(line, f'{PARAMS_KEY} without a node name above it')
            _check_node_key(self.nodes.text, f'{self.path!r}: line {line}')
            self.node = self.rules._node_index(self.nodes.text)
            self.nodes.pop()
            self.level = _PARAMS_LEVEL
            return
        entries = self.rules._entries[self.node]
        if self.new_map:
            if not entries:
                raise self.fail(line, 'a mapping without a parameter name above it')
            self.params.replace(entries[self.parameter][0], self.params.count + 1)
            self.new_map = False
        if self.params.text is None:
            self.parameter = self.rules._parameter_index(self.node, text)
        else:
            self.parameter = self.rules._parameter_index(self.node, self.params.text)
            entries[self.parameter][0] = f'{self.params.text}.{text}'

    def value(self, event: yaml.ScalarEvent, line: int) -> None:
        node_key = self.nodes.text or ''
        if self.level < _PARAMS_LEVEL:
            raise self.fail(line, f'{node_key!r} has no {PARAMS_KEY}')
        if not self.rules._keys:
            raise self.fail(line, f'a value before {PARAMS_KEY}')
        if not self.rules._entries[self.node]:
            raise self.fail(line, f'{PARAMS_KEY} of {self.rules._keys[self.node]!r} must be '
                            'a mapping')
        name = self.rules._entries[self.node][self.parameter][0]
        variant = self.rules._entries[self.node][self.parameter][1]
        self.sequence_slot = _set_value(variant, event, self.in_sequence, self.sequence_slot,
                                        f'{self.path!r}: line {line}: {name}')
        if not self.in_sequence:
            self.is_key = True

    def mapping_start(self) -> None:
        self.depth += 1
        self.new_map = True
        self.is_key = True
        if self.level == _PARAMS_LEVEL and self.depth - (self.nodes.count + 1) == 2:
            self.new_map = False  # the ros__parameters mapping itself

    def mapping_end(self) -> None:
        if self.level == _PARAMS_LEVEL:
            if self.params.count > 0:
                self.params.pop()
            else:
                self.level -= 1
        elif self.level == _NODE_LEVEL and self.depth == self.nodes.count + 1:
            self.nodes.pop()
        self.depth -= 1


# ----------------------------------------------------------------------------- files
def read_params_file(path: str | Path) -> dict[str, dict[str, Any]]:
    """Every section of a ROS 2 params file as rcl reads it: node key (as written) -> {name:
    value} (None: NOT_SET, e.g. ``[]``).

    Raises:
        OSError (FileNotFoundError): the file cannot be read.
        ValueError: rcl refuses it (:class:`ParamsFileError`; the message names the file).
    """
    rules = ParamRules()
    rules.add_file(path)
    return rules.sections()


def load_params(path: str | Path, node_name: str, namespace: str = '') -> dict[str, Any]:
    """Flat parameters a node called ``node_name`` gets from a ROS 2 params file, as on rclpy.

    Parameters without a value (``[]``: rclpy's NOT_SET, which no node can declare) are left
    out, so the reader's own default applies.

    Raises:
        FileNotFoundError: the file does not exist.
        ValueError: rcl refuses the file.
    """
    fully_qualified = f"{namespace.rstrip('/')}/{node_name}" if namespace else f'/{node_name}'
    rules = ParamRules()
    rules.add_file(path)
    return {name: value for name, value in rules.values_for(fully_qualified).items()
            if value is not None}


# ----------------------------------------------------------------------------- packaged configs
def config_directories() -> list[Path]:
    """Where packaged config files are looked for, in order.

    1. ``rcbf_ros/config`` inside the installed package (package data: wheel, pip install,
       colcon install);
    2. ``config/`` beside the ``rcbf_ros`` sources (source tree, editable install);
    3. ``share/rcbf_ros/config`` of the ament index (colcon install; only where
       ``ament_index_python`` is importable and the package is on ``AMENT_PREFIX_PATH``).
    """
    search = []
    packaged = resources.files(PACKAGE) / 'config'
    if isinstance(packaged, Path):
        search.append(packaged)
    search.append(_SOURCE_CONFIG_DIR)
    try:
        from ament_index_python.packages import get_package_share_directory
        search.append(Path(get_package_share_directory(PACKAGE)) / 'config')
    except Exception:  # noqa: BLE001 - ament_index absent, or the package not in the index
        pass
    return search


def find_config(name: str) -> Path:
    """Path of a packaged config file: ``unicycle`` -> ``.../config/unicycle.yaml``.

    A path to an existing file is returned as is; a bare name is looked up in
    :func:`config_directories`.

    Raises:
        FileNotFoundError: naming the file and every directory searched.
    """
    candidate = Path(name)
    if (candidate.suffix in ('.yaml', '.yml') or len(candidate.parts) > 1) and \
            os.path.exists(candidate):
        return candidate  # a FIFO, a device or a directory: the reader says what it is
    if len(candidate.parts) > 1:  # a path, not a packaged name
        raise FileNotFoundError(f'config: no such file {name}')
    filename = name if name.endswith(('.yaml', '.yml')) else f'{name}.yaml'
    search = config_directories()
    for directory in search:
        if (directory / filename).is_file():
            return directory / filename
    raise FileNotFoundError(f'config: no {filename} in {[str(d) for d in search]}')
