"""The benchmarks' modules for their tests: benchmarks/ is no package, so load them by path."""
from __future__ import annotations

import importlib.util
from pathlib import Path
import sys
from types import ModuleType

BENCHMARKS = Path(__file__).resolve().parents[2] / 'benchmarks'


def load_benchmark(name: str) -> ModuleType:
    """``benchmarks/<name>.py`` as the module ``name`` (registered in sys.modules), with
    benchmarks/ importable while it loads (a benchmark imports its siblings by name)."""
    spec = importlib.util.spec_from_file_location(name, BENCHMARKS / f'{name}.py')
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    sys.path.insert(0, str(BENCHMARKS))
    try:
        spec.loader.exec_module(module)
    finally:
        sys.path.remove(str(BENCHMARKS))
    return module
