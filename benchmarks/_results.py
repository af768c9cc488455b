"""Write one section of benchmarks/RESULTS.md without touching the others."""
from __future__ import annotations

from collections.abc import Sequence
import os
from pathlib import Path
import platform
import re

RESULTS = Path(__file__).resolve().parent / 'RESULTS.md'
HEADER = ("# Benchmarks\n\nMeasured on this project's machine size (2 cores, no GPU), "
          'each by the command in its section. Numbers are medians unless noted.\n')


def load_averages() -> str:
    """The machine's 1, 5 and 15 minute load averages, as a section's conditions print them."""
    return 'load averages ' + ', '.join(f'{x:.2f}' for x in os.getloadavg())


def load_before_after(before: Sequence[float], after: Sequence[float]) -> str:
    """``Load average (1, 5, 15 min) before a, b, c, after d, e, f``: the machine's load
    around a run (``os.getloadavg()`` taken before and after), without the closing words."""
    def text(values: Sequence[float]) -> str:
        return ', '.join(f'{v:.2f}' for v in values)
    return f'Load average (1, 5, 15 min) before {text(before)}, after {text(after)}'


def machine_line() -> str:
    """A one-line description of where the numbers came from."""
    import torch
    return (f'Python {platform.python_version()}, torch {torch.__version__} '
            f'({torch.get_num_threads()} thread), {platform.machine()}{cpu_model()}'
            f'{numpy_blas()}')


def cpu_model(cpuinfo: Path = Path('/proc/cpuinfo')) -> str:
    """', <model name> (family F model M)' of the first CPU in ``cpuinfo`` (empty where the
    file is missing). Hosts of one machine size differ in CPU model, and absolute times differ
    with it: compare figures within one run, or between runs on the same model."""
    try:
        text = cpuinfo.read_text()
    except OSError:
        return ''
    fields: dict[str, str] = {}
    for line in text.splitlines():
        if not line.strip():
            break  # the first processor's block only
        key, _, value = line.partition(':')
        fields.setdefault(key.strip(), value.strip())
    name = fields.get('model name', '')
    if not name:
        return ''
    family, model = fields.get('cpu family'), fields.get('model')
    return f', {name}' + (f' (family {family} model {model})' if family and model else '')


def numpy_blas() -> str:
    """', numpy OpenBLAS <kernel>' as this process's numpy runs it (empty without
    threadpoolctl or OpenBLAS)."""
    try:
        import numpy  # noqa: F401  (loads the BLAS that threadpoolctl inspects)
        import threadpoolctl
    except ImportError:
        return ''
    for info in threadpoolctl.threadpool_info():
        if info.get('internal_api') == 'openblas':
            return f", numpy OpenBLAS {info.get('architecture')} kernels"
    return ''


def write_section(title: str, body: str) -> None:
    """Replace (or append) the ``## title`` section of RESULTS.md."""
    text = RESULTS.read_text() if RESULTS.exists() else HEADER
    section = f'## {title}\n\n{body.strip()}\n'
    pattern = re.compile(rf'^## {re.escape(title)}\n.*?(?=^## |\Z)', re.S | re.M)
    if pattern.search(text):
        text = pattern.sub(lambda _: section + '\n', text)
    else:
        text = text.rstrip('\n') + '\n\n' + section
    RESULTS.write_text(text.rstrip('\n') + '\n')


def publish_section(title: str, *, script: str, blocks: Sequence[str | Sequence[str]],
                    write: bool, conditions: str = '') -> str:
    """Print the ``## title`` section of a benchmark's one run; also write it when ``write``.

    The body: ``python benchmarks/<script>`` and where it ran (:func:`machine_line`, then
    ``conditions``, e.g. ``'; 2 busy processes beside'``), then ``blocks``, a blank line before
    each: a string is a paragraph, a sequence of strings the lines of a table. Returns the body.
    """
    lines = [f'`python benchmarks/{script}` (one run; {machine_line()}{conditions}).']
    for block in blocks:
        lines += [''] + ([block] if isinstance(block, str) else list(block))
    body = '\n'.join(lines)
    if write:
        write_section(title, body)
    print(body)
    return body


def publish_table(title: str, *, script: str, command: str, table: Sequence[str],
                  load_before: Sequence[float], write: bool) -> str:
    """Print a benchmark's ``table`` and the load around its run (``load_before`` against now);
    also write them as the ``## title`` section when ``write``, after ``Command: `command`.``,
    :func:`machine_line` and a pointer to the method in ``benchmarks/<script>``'s docstring.
    Returns the printed text."""
    load = load_before_after(load_before, os.getloadavg()) + ' (2 cores).'
    text = '\n'.join([*table, '', load])
    print(text)
    if write:
        write_section(title, (f'Command: `{command}`. {machine_line()}. Method: the docstring '
                              f'of benchmarks/{script}.\n\n' + text))
    return text
