"""The same params files and ``-p`` rules give the same overrides on real rclpy as on ours.

Every case of test/unit/test_parameter_rules.py (precedence, wildcards, empty lists, type
slots, scalar typing, refused keys) runs through rclpy 7.1 under Jazzy
(``rclpy_overrides.py``: ``Node._parameter_overrides`` of a node of that name) and through
:func:`rcbf_ros.parameters.arguments.parameter_overrides`; the dicts must be equal, and a command
line one refuses the other must refuse too.
"""
from __future__ import annotations

import importlib.util
import json
import math
from pathlib import Path
from typing import Any

import pytest

from rcbf_ros.parameters.arguments import (
    parameter_overrides,
    parse_ros_arguments,
    RosArgumentError,
)

pytestmark = pytest.mark.ros2
HERE = Path(__file__).resolve().parent


def _rules_module() -> Any:
    path = HERE.parent / 'unit' / 'test_parameter_rules.py'
    spec = importlib.util.spec_from_file_location('parameter_rules_cases', path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _cases(tmp_path: Path) -> list[dict[str, Any]]:
    rules = _rules_module()
    cases = [{'id': name, 'argv': rules.command_line(tmp_path, words), 'name': 'simulator'}
             for name, (words, _, _) in rules.CASES.items()]
    for key, fully_qualified, _ in rules.WILDCARD_KEYS:
        namespace, _, name = fully_qualified.rpartition('/')
        cases.append({'id': f'key {key} for {fully_qualified}', 'name': name,
                      'namespace': namespace or '/', 'argv': rules.command_line(
                          tmp_path, [f'@"{key}":\n  ros__parameters: {{w: 1}}\n'])})
    for key in rules.REFUSED_KEYS:
        cases.append({'id': f'refused key {key}', 'name': 'simulator', 'argv': rules.command_line(
            tmp_path, [f'@"{key}":\n  ros__parameters: {{w: 1}}\n'])})
    scalars = [f'v{i}:={text}' for i, (text, _, _) in enumerate(rules.SCALARS)]
    cases.append({'id': 'scalars', 'name': 'simulator', 'argv': rules.command_line(
        tmp_path, scalars)})
    cases.append({'id': 'a node key and a string list', 'name': 'simulator',
                  'argv': rules.command_line(tmp_path, ['simulator:x:=1', 'y:=[a, b]'])})
    return cases


def _ours(case: dict[str, Any]) -> dict[str, Any]:
    namespace = case.get('namespace', '/').rstrip('/')
    try:
        parsed = parse_ros_arguments(case['argv'])
    except RosArgumentError as exc:
        return {'error': str(exc)}
    return {'overrides': parameter_overrides([parsed], f'{namespace}/{case["name"]}')}


def _same(ours: Any, theirs: Any) -> bool:
    if isinstance(ours, float) and isinstance(theirs, float):
        return ours == theirs or (math.isnan(ours) and math.isnan(theirs))
    if isinstance(ours, dict) and isinstance(theirs, dict):
        return ours.keys() == theirs.keys() and all(_same(ours[k], theirs[k]) for k in ours)
    if isinstance(ours, list) and isinstance(theirs, list):
        return len(ours) == len(theirs) and all(map(_same, ours, theirs))
    return type(ours) is type(theirs) and ours == theirs


def test_overrides_match_rclpy(jazzy, tmp_path, ros_domain_id):
    cases = _cases(tmp_path)
    spec = tmp_path / 'cases.json'
    spec.write_text(json.dumps(cases))
    # The interpreter of the ros2 command, as on a stock install.
    done = jazzy.run(f'PY=$(head -1 "$(command -v ros2)" | cut -c3-); '
                     f'"$PY" {HERE / "rclpy_overrides.py"} {spec}',
                     domain_id=ros_domain_id, timeout=120)
    assert done.returncode == 0, done.stdout[-3000:]
    theirs = json.loads(done.stdout.strip().splitlines()[-1])
    differences = []
    for case, rclpy_result in zip(cases, theirs, strict=True):
        ours = _ours(case)
        if 'error' in rclpy_result or 'error' in ours:
            if ('error' in rclpy_result) != ('error' in ours):
                differences.append((case['id'], ours, rclpy_result))
        elif not _same(ours['overrides'], rclpy_result['overrides']):
            differences.append((case['id'], ours['overrides'], rclpy_result['overrides']))
    assert not differences, '\n'.join(f'{i}: ours {o}, rclpy {t}' for i, o, t in differences)
