"""YAML from outside the program, read within limits that are checked while it is parsed.

Every YAML text the tools take from outside goes through here: params files (``--params-file``,
``-p`` values, refilter's ``--params-file``), a bag's ``metadata.yaml`` and the QoS strings in
its MCAP channels, and launch argument values. A text past a limit raises
:class:`YAMLLimitError`, one line naming the source, the line and the limit:

- size: a file is read up to its limit plus one byte, never further (``max_bytes``: 128 KiB for
  params files, 16 MiB for ``metadata.yaml``), so a file of any size, or a device that never
  ends, costs at most that;
- depth: collections nest at most :data:`MAX_DEPTH` (64) levels, counted through aliases;
- nodes: the document holds at most :data:`MAX_NODES` (1,000,000) nodes, every alias counted
  as the nodes it repeats (a billion-laughs bomb stops at the alias that crosses the limit);
- aliases: refused outright where the writer never makes them (``allow_aliases=False``:
  rosbag2's yaml-cpp emitter and our writer build every node afresh, so their files hold none);
- tags: only the YAML core schema's (``!!str``, ``!!int``, ``!!float``, ``!!bool``, ``!!null``,
  ``!!seq``, ``!!map``, ...); ``!!python/...`` and local tags (``!x``) are refused;
- keys: a mapping names each key once (YAML 1.2 requires it); PyYAML and rcl's parser would
  let a second ``alpha:`` silently replace the first (or, in rcl, keep the first when the types
  differ), so a repeated key is refused, naming it and both lines, except in a ROS 2 params
  file, which is read as rcl reads it, each repeat reported (``repeated_keys``).

The limits are checked on the parser's events, one event at a time, before anything is built,
so a refused text costs at most one pass over its first bytes, up to the size limit.
"""
from __future__ import annotations

import errno
import os
import stat
from typing import Any, Iterator

import yaml

MAX_DEPTH = 64
"""Deepest nesting of collections (ROS params files and rosbag2 metadata nest under 10)."""
MAX_NODES = 1_000_000
"""Most nodes in one document, aliases counted as what they repeat."""
CORE_TAGS = frozenset(f'tag:yaml.org,2002:{name}' for name in (
    'str', 'int', 'float', 'bool', 'null', 'seq', 'map', 'binary', 'timestamp', 'omap',
    'pairs', 'set', 'merge', 'value'))
"""The tags a document may carry (what ``yaml.SafeLoader`` builds, nothing executable)."""

_Loader: Any = getattr(yaml, 'CSafeLoader', yaml.SafeLoader)


class YAMLLimitError(yaml.YAMLError, ValueError):
    """A YAML text past a size, depth, node, alias or tag limit, or with a key repeated in one
    mapping (one line: source, where and which limit)."""


def syntax_error_line(exc: yaml.YAMLError) -> str:
    """PyYAML's error as one line: ``not valid YAML at line L, column C: <problem>`` (its own
    message spans several lines, with the offending text and a caret)."""
    mark = getattr(exc, 'problem_mark', None)
    problem = getattr(exc, 'problem', None) or str(exc)
    where = f' at line {mark.line + 1}, column {mark.column + 1}' if mark is not None else ''
    return ' '.join(f'not valid YAML{where}: {problem}'.split())


def file_kind(mode: int) -> str:
    """What a file of ``st_mode`` ``mode`` is, for a message (``a FIFO``, ``a directory``...)."""
    for test, kind in ((stat.S_ISDIR, 'a directory'), (stat.S_ISFIFO, 'a FIFO'),
                       (stat.S_ISCHR, 'a character device'), (stat.S_ISBLK, 'a block device'),
                       (stat.S_ISSOCK, 'a socket')):
        if test(mode):
            return kind
    return 'not a plain file'


def read_limited(path: str | os.PathLike[str], *, max_bytes: int, what: str) -> str:
    """The UTF-8 text of ``path``, read no further than ``max_bytes`` + 1 bytes.

    Only a regular file is read: it is opened without blocking (a FIFO would wait for a writer)
    and checked on the open file, so a FIFO, a directory or a device is refused before a byte
    is read.

    Args:
        path: the file.
        max_bytes: the largest file accepted.
        what: what the file is, for the message (e.g. ``params file``).

    Raises:
        OSError: the file cannot be read, or is not a regular file (``strerror``: ``not a
            regular file (a FIFO)``).
        UnicodeDecodeError: it is not UTF-8.
        YAMLLimitError: it holds more than ``max_bytes`` bytes.
    """
    fd = os.open(path, os.O_RDONLY | getattr(os, 'O_NONBLOCK', 0))
    try:
        mode = os.fstat(fd).st_mode
        if not stat.S_ISREG(mode):
            raise OSError(errno.EINVAL, f'not a regular file ({file_kind(mode)})', os.fspath(path))
        os.set_blocking(fd, True)
        stream = os.fdopen(fd, 'rb')
    except BaseException:
        os.close(fd)
        raise
    with stream:
        data = stream.read(max_bytes + 1)
    if len(data) > max_bytes:
        raise YAMLLimitError(f'{os.fspath(path)}: larger than the {max_bytes}-byte limit of a '
                             f'{what}')
    return data.decode('utf-8')


def checked_events(text: str, *, source: str, max_depth: int = MAX_DEPTH,
                   max_nodes: int = MAX_NODES, allow_aliases: bool = True,
                   loader: Any = yaml.SafeLoader,
                   repeated_keys: list[str] | None = None) -> Iterator[yaml.Event]:
    """The parser's events of ``text``, each checked against the limits before it is yielded.

    Args:
        text: the YAML text.
        source: where it comes from (a path, ``-p name``), the start of every message.
        max_depth: deepest nesting of collections (aliases counted as what they repeat).
        max_nodes: most nodes (scalars and collections; aliases as what they repeat).
        allow_aliases: False refuses every alias.
        loader: the PyYAML loader class whose parser reads ``text``.
        repeated_keys: None refuses a key repeated in one mapping; a list takes it and gets
            one line per repeat (a ROS 2 params file: rcl reads repeats, see
            :meth:`rcbf_ros.parameters.rules.ParamRules.add_file`).

    Raises:
        YAMLLimitError: past a limit (the message names the line).
        yaml.YAMLError: not YAML.
    """
    depth = 0
    nodes = 0
    # Per open collection: its anchor, the node count before it, its own depth, the deepest
    # depth reached inside it, and for a mapping its scalar keys' first lines (None: a
    # sequence) and whether its next node is a key.
    open_collections: list[list[Any]] = []
    anchors: dict[str, tuple[int, int]] = {}  # anchor -> (nodes, height)

    def refuse(event: yaml.Event, problem: str) -> YAMLLimitError:
        line = event.start_mark.line + 1 if event.start_mark is not None else 0
        return YAMLLimitError(f'{source}: line {line}: {problem}')

    def take_node(event: yaml.Event) -> None:
        """Count ``event`` (a node's first event) as the next node of the open mapping: a key
        seen before in it is refused."""
        if not open_collections or open_collections[-1][4] is None:
            return
        mapping = open_collections[-1]
        is_key, mapping[5] = mapping[5], not mapping[5]
        if not is_key or not isinstance(event, yaml.ScalarEvent):
            return
        line = event.start_mark.line + 1 if event.start_mark is not None else 0
        first = mapping[4].get(event.value)
        if first is not None:
            problem = (f'the key {event.value!r} is given twice in one mapping (lines {first} '
                       f'and {line}; YAML keys are unique)')
            if repeated_keys is None:
                raise refuse(event, problem)
            repeated_keys.append(f'{source}: line {line}: {problem}')
            return
        mapping[4][event.value] = line

    def grow(event: yaml.Event, count: int, reached: int) -> None:
        nonlocal nodes
        nodes += count
        if nodes > max_nodes:
            raise refuse(event, f'more than {max_nodes} YAML nodes (aliases counted as what '
                                'they repeat)')
        if reached > max_depth:
            raise refuse(event, f'nested deeper than {max_depth} levels')
        if open_collections:
            open_collections[-1][3] = max(open_collections[-1][3], reached)

    for event in yaml.parse(text, Loader=loader):
        tag = getattr(event, 'tag', None)
        if tag is not None and tag != '!' and tag not in CORE_TAGS:
            shown = tag.replace('tag:yaml.org,2002:', '!!')
            raise refuse(event, f'the tag {shown} is not allowed (only the YAML core tags)')
        if isinstance(event, (yaml.AliasEvent, yaml.ScalarEvent, yaml.SequenceStartEvent,
                              yaml.MappingStartEvent)):
            take_node(event)
        if isinstance(event, yaml.AliasEvent):
            if not allow_aliases:
                raise refuse(event, f'the alias *{event.anchor} is not allowed here (no '
                                    'aliases in this file)')
            if any(opened[0] == event.anchor for opened in open_collections):
                raise refuse(event, f'the alias *{event.anchor} lies inside the collection it '
                                    'names (a structure that contains itself)')
            count, height = anchors.get(event.anchor, (1, 0))
            grow(event, count, depth + height)
        elif isinstance(event, yaml.ScalarEvent):
            grow(event, 1, depth)
            if event.anchor is not None:
                anchors[event.anchor] = (1, 0)
        elif isinstance(event, (yaml.SequenceStartEvent, yaml.MappingStartEvent)):
            before = nodes
            grow(event, 1, depth + 1)
            depth += 1
            open_collections.append([
                event.anchor, before, depth, depth,
                {} if isinstance(event, yaml.MappingStartEvent) else None, True])
        elif isinstance(event, (yaml.SequenceEndEvent, yaml.MappingEndEvent)):
            anchor, before, own_depth, deepest, _, _ = open_collections.pop()
            depth -= 1
            if anchor is not None:
                anchors[anchor] = (nodes - before, deepest - own_depth + 1)
            if open_collections:
                open_collections[-1][3] = max(open_collections[-1][3], deepest)
        yield event


def check(text: str, *, source: str, **limits: Any) -> None:
    """Raise :class:`YAMLLimitError` if ``text`` is past a limit (see :func:`checked_events`).

    Raises:
        YAMLLimitError: past a limit.
        yaml.YAMLError: not YAML.
    """
    for _ in checked_events(text, source=source, loader=_Loader, **limits):
        pass


def safe_load(text: str, *, source: str, **limits: Any) -> Any:
    """``yaml.safe_load(text)`` once :func:`check` has found it within the limits.

    Raises:
        YAMLLimitError: past a limit (the message names ``source`` and the line).
        yaml.YAMLError: not YAML.
    """
    check(text, source=source, **limits)
    return yaml.load(text, Loader=_Loader)  # noqa: S506 - a safe loader (C or Python)


def load_file(path: str | os.PathLike[str], *, max_bytes: int, what: str,
              **limits: Any) -> Any:
    """The document of a YAML file within ``max_bytes`` and the limits of :func:`check`.

    Raises:
        OSError: the file cannot be read.
        UnicodeDecodeError: it is not UTF-8.
        YAMLLimitError: past a limit (the message names the file).
        yaml.YAMLError: not YAML.
    """
    text = read_limited(path, max_bytes=max_bytes, what=what)
    return safe_load(text, source=os.fspath(path), **limits)
