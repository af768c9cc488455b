"""docs/RELIABILITY.md names, for every fault, the test that exercises it: each named test must
exist, so the table cannot outlive its tests."""
from __future__ import annotations

import ast
from pathlib import Path
import re

REPO = Path(__file__).resolve().parents[2]
DOC = REPO / 'docs' / 'RELIABILITY.md'
# `test_file.py::test_name` or, after one of those in the same cell, `::test_name`.
REFERENCE = re.compile(r'`(test_\w+\.py)?::(test_\w+)`')
FILE_ONLY = re.compile(r'`(test_\w+\.py)`')


def _test_functions() -> dict[str, set[str]]:
    found: dict[str, set[str]] = {}
    for path in (REPO / 'test').rglob('test_*.py'):
        tree = ast.parse(path.read_text(encoding='utf-8'))
        found[path.name] = {node.name for node in ast.walk(tree)
                            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef))
                            and node.name.startswith('test_')}
    return found


def references(text: str) -> list[tuple[str, str]]:
    """(file, test) pairs named in the table's rows, a bare ``::name`` taking the last file."""
    pairs = []
    for line in text.splitlines():
        if not line.startswith('|'):
            continue
        current = None
        for match in REFERENCE.finditer(line):
            current = match.group(1) or current
            assert current is not None, f'{match.group(0)} names no file: {line}'
            pairs.append((current, match.group(2)))
    return pairs


def test_every_test_named_in_the_reliability_doc_exists():
    text = DOC.read_text(encoding='utf-8')
    pairs = references(text)
    assert len(pairs) >= 40
    tests = _test_functions()
    missing = [f'{file}::{name}' for file, name in pairs
               if name not in tests.get(file, set())]
    assert not missing, f'docs/RELIABILITY.md names tests that do not exist: {missing}'
    files = {m.group(1) for m in FILE_ONLY.finditer(text)}
    assert files <= set(tests), sorted(files - set(tests))


def test_the_reference_parser_sees_a_missing_test():
    row = '| x | `test_a.py::test_one`, `::test_two` | y |'
    assert references(row) == [('test_a.py', 'test_one'), ('test_a.py', 'test_two')]
