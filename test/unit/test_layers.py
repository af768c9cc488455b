"""The layout is the architecture: every module sits in a layer or concern folder, and imports
point down only (the layers of docs/ARCHITECTURE.md, plus the concern folders around them).

Read from the sources with ``ast``: every import statement, also those inside functions, and
every ``importlib.import_module(...)`` / ``__import__(...)`` whose module name the file itself
spells (a string literal, the package part of one built from pieces, or string constants that
reach the call through names bound in the file: ``for module, name in NODES:
import_module(module)``). A lazy import that climbs a layer
fails here as surely as one at the top of a file. A name known only at run time (a command
line's module, a user's dotted path) is not an import of the package's own layout.
"""
from __future__ import annotations

import ast
from pathlib import Path
import re

import pytest

ROOT = Path(__file__).resolve().parents[2]
ARCHITECTURE = ROOT / 'docs' / 'ARCHITECTURE.md'

LAYERS: tuple[frozenset[str], ...] = (
    frozenset({'parameters', 'messages'}),  # leaves: ROS conventions without middleware
    frozenset({'core'}),                    # pure math
    frozenset({'learning'}),                # GP, SAC, buffers
    frozenset({'envs'}),                    # the systems as Gymnasium envs
    frozenset({'node_logic'}),              # what the nodes decide, without middleware
    frozenset({'bag'}),                     # MCAP writing, reading, recovery, re-filtering
    frozenset({'reports'}),                 # plots and run summaries
    frozenset({'training'}),                # in-process training runs
    frozenset({'experiments'}),             # the paper's experiments
    frozenset({'ros', 'sim_nodes'}),        # the nodes and the runtime
    frozenset({'launch'}),                  # launch setups and the local launcher
    frozenset({'cli'}),                     # the rcbf_ros command
)
"""Bottom first: a folder may import its own layer and the layers before it."""

RANK = {folder: rank for rank, layer in enumerate(LAYERS) for folder in layer}

IMPORTERS = frozenset({'import_module', '__import__'})
"""Calls that import the module named by their first argument."""

_MODULE_NAME = re.compile(r'rcbf_ros(?:\.[A-Za-z_][A-Za-z0-9_]*)+|sim_nodes(?:\.[A-Za-z_]\w*)*')


def _folder(module: str) -> str | None:
    parts = module.split('.')
    if parts[0] == 'sim_nodes':
        return 'sim_nodes'
    if parts[0] == 'rcbf_ros' and len(parts) > 1:
        return parts[1]
    return None


def _sources() -> list[Path]:
    return sorted([*ROOT.glob('rcbf_ros/**/*.py'), *ROOT.glob('sim_nodes/*.py')])


def _bindings(tree: ast.AST) -> dict[str, list[ast.expr]]:
    """Every expression a name is bound to anywhere in the file (assignments, for loops and
    comprehensions; a target unpacked from a value binds each of its names to all of it)."""
    bound: dict[str, list[ast.expr]] = {}

    def bind(target: ast.expr, value: ast.expr | None) -> None:
        if value is None:
            return
        for name in ast.walk(target):
            if isinstance(name, ast.Name):
                bound.setdefault(name.id, []).append(value)

    for node in ast.walk(tree):
        if isinstance(node, ast.Assign):
            for target in node.targets:
                bind(target, node.value)
        elif isinstance(node, (ast.AnnAssign, ast.AugAssign, ast.NamedExpr)):
            bind(node.target, node.value)
        elif isinstance(node, (ast.For, ast.AsyncFor, ast.comprehension)):
            bind(node.target, node.iter)
    return bound


def _strings(expr: ast.expr, bound: dict[str, list[ast.expr]], seen: set[str]) -> set[str]:
    """The string constants in ``expr`` and, through the names it reads, in their values."""
    found = set()
    for node in ast.walk(expr):
        if isinstance(node, ast.Constant) and isinstance(node.value, str):
            found.add(node.value)
            found.add(node.value.rstrip('.'))  # the package part of f'rcbf_ros.ros.{name}'
        elif isinstance(node, ast.Name) and node.id not in seen:
            seen.add(node.id)
            for value in bound.get(node.id, []):
                found |= _strings(value, bound, seen)
    return found


def _called_name(call: ast.Call) -> str | None:
    if isinstance(call.func, ast.Name):
        return call.func.id
    if isinstance(call.func, ast.Attribute):
        return call.func.attr
    return None


def _imports_in(source: str, filename: str = '<source>') -> list[tuple[int, str]]:
    """(line, module) of every import in ``source``: statements and spelled-out dynamic ones."""
    tree = ast.parse(source, filename=filename)
    bound = _bindings(tree)
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            found.append((node.lineno, node.module))
        elif isinstance(node, ast.Import):
            found.extend((node.lineno, alias.name) for alias in node.names)
        elif (isinstance(node, ast.Call) and _called_name(node) in IMPORTERS
              and node.args):
            named = _strings(node.args[0], bound, set())
            found.extend((node.lineno, name) for name in sorted(named)
                         if _MODULE_NAME.fullmatch(name))
    return found


def _upward(module: str, source: str) -> list[str]:
    here = _folder(module)
    if here not in RANK:  # rcbf_ros/__init__.py, __main__.py
        return []
    return [f'line {line}: {name} ({_folder(name)})' for line, name in _imports_in(source)
            if _folder(name) in RANK and RANK[_folder(name)] > RANK[here]]


def test_no_module_is_loose_at_the_package_top() -> None:
    loose = sorted(p.name for p in (ROOT / 'rcbf_ros').glob('*.py')
                   if p.name not in ('__init__.py', '__main__.py'))
    assert loose == [], f'modules outside any layer or concern folder: {loose}'


def test_every_folder_has_a_layer() -> None:
    folders = {p.parent.name for p in (ROOT / 'rcbf_ros').glob('*/__init__.py')}
    folders.discard('config')
    assert folders - set(RANK) == set(), 'a package folder missing from LAYERS'


@pytest.mark.parametrize('path', sorted([*ROOT.glob('rcbf_ros/**/__init__.py'),
                                         ROOT / 'sim_nodes' / '__init__.py']),
                         ids=lambda p: str(p.relative_to(ROOT)))
def test_every_package_says_in_two_lines_what_it_is_for(path: Path) -> None:
    """A package's face: a docstring of one or two lines that is a sentence, not its name."""
    face = ast.get_docstring(ast.parse(path.read_text())) or ''
    assert 0 < len(face.splitlines()) <= 2 and len(face.split()) >= 8, (
        f'{path.relative_to(ROOT)}: say in two lines what the package is for')


def test_the_architecture_page_lists_the_layers_in_order() -> None:
    """docs/ARCHITECTURE.md's layer table names the folders of LAYERS, bottom first."""
    rows = re.findall(r'^\| *(\d+) *\| *(.+?) *\|', ARCHITECTURE.read_text(), re.MULTILINE)
    listed = [frozenset(re.findall(r'`([a-z_]+)/`', folders)) for _, folders in rows]
    assert listed == list(LAYERS), 'docs/ARCHITECTURE.md: the layer table differs from LAYERS'


@pytest.mark.parametrize('source, expected', [
    ("import importlib\nimportlib.import_module('rcbf_ros.cli.main')\n",
     ['line 2: rcbf_ros.cli.main (cli)']),
    ("__import__('sim_nodes.simulator_node')\n",
     ['line 1: sim_nodes.simulator_node (sim_nodes)']),
    ("from importlib import import_module\nNODES = (('rcbf_ros.ros.policy_node', 'I'),)\n"
     'def f():\n    return [import_module(m) for m, _ in NODES]\n',
     ['line 4: rcbf_ros.ros.policy_node (ros)']),
    ("import importlib\nTARGET = 'rcbf_ros.launch.local'\nmodule = TARGET\n"
     'importlib.import_module(module)\n', ['line 4: rcbf_ros.launch.local (launch)']),
    ('def f():\n    from rcbf_ros.training import loop\n',
     ['line 2: rcbf_ros.training (training)']),
    ("import importlib\nimportlib.import_module('rcbf_ros.messages.cdr')\n", []),
    ('import importlib\ndef f(name):\n    return importlib.import_module(name)\n', []),
    ("import importlib\ndef f(n):\n    return importlib.import_module(f'rcbf_ros.ros.{n}')\n",
     ['line 3: rcbf_ros.ros (ros)']),
    ("import importlib\ndef f(name):\n    return importlib.import_module('sim_nodes.' + name)\n",
     ['line 3: sim_nodes (sim_nodes)']),
    ("NAME = 'rcbf_ros.cli.main'  # data, never imported here\n", []),
])
def test_the_scan_follows_spelled_out_dynamic_imports(source: str, expected: list[str]) -> None:
    """The oracle for the scan itself: as if each source were a module of ``core``."""
    assert _upward('rcbf_ros.core.example', source) == expected


@pytest.mark.parametrize('path', _sources(), ids=lambda p: str(p.relative_to(ROOT)))
def test_imports_point_down(path: Path) -> None:
    module = '.'.join(path.relative_to(ROOT).with_suffix('').parts)
    upward = _upward(module, path.read_text())
    assert upward == [], f'{_folder(module)} imports a higher layer: {upward}'
