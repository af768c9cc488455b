"""Read ROS 2 parameter YAML files without ROS (for offline scripts and the in-process trainer).

The file format is the one ``--params-file`` takes::

    /**:                      # every node
      ros__parameters: {...}
    /safety_filter:           # one node (leading slash and namespace optional)
      ros__parameters: {...}

Parameters of the node's own section override ``/**``; nested mappings flatten to dotted names,
as ROS does.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any, Mapping

import yaml

from rcbf_ros.core.mappings import flatten

_CONFIG_DIR = Path(__file__).resolve().parent.parent / 'config'


def read_params_file(path: str | Path) -> dict[str, dict[str, Any]]:
    """Every section of a ROS 2 params file: node key (``/**``, ``/ns/node``) -> flat
    ``ros__parameters``. Nested sections (``/ns: {node: {ros__parameters: ...}}``) join.

    Raises:
        OSError (FileNotFoundError): the file cannot be read.
        ValueError: not YAML, or not a mapping of node keys to ``ros__parameters`` (the message
            names the file and the section).
    """
    path = str(path)
    with open(path, encoding='utf-8') as stream:
        try:
            document = yaml.safe_load(stream)
        except yaml.YAMLError as exc:
            raise ValueError(f'{path!r} is not valid YAML: {exc}') from exc
    if document is None:
        return {}
    if not isinstance(document, Mapping):
        raise ValueError(f'{path!r}: top level must map node names')
    result: dict[str, dict[str, Any]] = {}
    _collect_sections(document, '', path, result)
    return result


def _collect_sections(tree: Mapping[str, Any], prefix: str, path: str,
                      result: dict[str, dict[str, Any]]) -> None:
    for key, value in tree.items():
        key = str(key)
        if key == 'ros__parameters':
            if not isinstance(value, Mapping):
                raise ValueError(f'{path!r}: ros__parameters of {prefix or "/"!r} must be a '
                                 'mapping')
            node_key = prefix if prefix.startswith('/') else '/' + prefix
            result.setdefault(node_key, {}).update(flatten(value))
        elif isinstance(value, Mapping):
            joined = key if not prefix else f'{prefix.rstrip("/")}/{key.lstrip("/")}'
            _collect_sections(value, joined, path, result)
        else:
            raise ValueError(f'{path!r}: {prefix}/{key} has no ros__parameters')


def node_key_level(key: str, node_name: str, fully_qualified: str) -> int:
    """How a params-file section applies to a node: 0 not at all, 1 wildcard ``/**``,
    2 this node (``/ns/node`` or ``/**/node``)."""
    if key == '/**':
        return 1
    if key in (fully_qualified, '/**/' + node_name):
        return 2
    return 0


def load_params(path: str | Path, node_name: str, namespace: str = '') -> dict[str, Any]:
    """Flat parameters for ``node_name`` from a ROS 2 params file: its own section over ``/**``.

    Raises:
        FileNotFoundError: the file does not exist.
        ValueError: the file is not a mapping of ``<node>: {ros__parameters: {...}}``.
    """
    fully_qualified = f"{namespace.rstrip('/')}/{node_name}" if namespace else f'/{node_name}'
    wildcard: dict[str, Any] = {}
    specific: dict[str, Any] = {}
    add_node_sections(read_params_file(path), node_name, fully_qualified, wildcard, specific)
    return {**wildcard, **specific}


def add_node_sections(sections: Mapping[str, Mapping[str, Any]], node_name: str,
                      fully_qualified: str, wildcard: dict[str, Any],
                      specific: dict[str, Any]) -> None:
    """Merge the sections of one params file that apply to the node: ``/**`` entries into
    ``wildcard``, the node's own into ``specific`` (the caller lets specific win)."""
    for key, params in sections.items():
        level = node_key_level(key, node_name, fully_qualified)
        if level == 1:
            wildcard.update(params)
        elif level == 2:
            specific.update(params)


def find_config(name: str) -> Path:
    """Path of a packaged config file: ``unicycle`` -> ``<share or repo>/config/unicycle.yaml``.

    Looks in the ament share directory when installed with colcon, then next to the sources.
    A path to an existing file is returned as is.
    """
    candidate = Path(name)
    if candidate.suffix in ('.yaml', '.yml') and candidate.is_file():
        return candidate
    if len(candidate.parts) > 1:  # a path, not a packaged name
        raise FileNotFoundError(f'config: no such file {name}')
    filename = name if name.endswith(('.yaml', '.yml')) else f'{name}.yaml'
    search = []
    try:  # pragma: no cover - only on a ROS install
        from ament_index_python.packages import get_package_share_directory
        search.append(Path(get_package_share_directory('rcbf_ros')) / 'config')
    except Exception:  # noqa: BLE001 - ament_index absent or package not installed
        pass
    search.append(_CONFIG_DIR)
    for directory in search:
        if (directory / filename).is_file():
            return directory / filename
    raise FileNotFoundError(f'config: no {filename} in {[str(d) for d in search]}')
