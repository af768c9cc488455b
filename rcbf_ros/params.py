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
from typing import Any

import yaml

from rcbf_ros.core.config import flatten

_CONFIG_DIR = Path(__file__).resolve().parent.parent / 'config'


def _matches(section: str, node_name: str, namespace: str) -> bool:
    section = section.strip()
    if section in ('/**', '**'):
        return True
    full = f"{namespace.rstrip('/')}/{node_name}" if namespace else f'/{node_name}'
    return section in (node_name, f'/{node_name}', full, full.lstrip('/'))


def load_params(path: str | Path, node_name: str, namespace: str = '') -> dict[str, Any]:
    """Flat parameters for ``node_name`` from a ROS 2 params file.

    Raises:
        FileNotFoundError: the file does not exist.
        ValueError: the file is not a mapping of ``<node>: {ros__parameters: {...}}``.
    """
    path = Path(path)
    with path.open() as stream:
        document = yaml.safe_load(stream) or {}
    if not isinstance(document, dict):
        raise ValueError(f'{path}: expected a mapping of node names to ros__parameters')
    merged: dict[str, Any] = {}
    # '/**' first so that the node's own section wins.
    for section in sorted(document, key=lambda s: 0 if s.strip() in ('/**', '**') else 1):
        body = document[section]
        if not _matches(section, node_name, namespace):
            continue
        if not isinstance(body, dict) or 'ros__parameters' not in body:
            raise ValueError(f'{path}: section {section!r} has no ros__parameters')
        merged.update(flatten(body['ros__parameters'] or {}))
    return merged


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
