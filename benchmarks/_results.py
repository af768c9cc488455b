"""Write one section of benchmarks/RESULTS.md without touching the others."""
from __future__ import annotations

from pathlib import Path
import platform
import re

RESULTS = Path(__file__).resolve().parent / 'RESULTS.md'
HEADER = ("# Benchmarks\n\nMeasured on this project's machine size (2 cores, no GPU), "
          'each by the command in its section. Numbers are medians unless noted.\n')


def machine_line() -> str:
    """A one-line description of where the numbers came from."""
    import torch
    return (f'Python {platform.python_version()}, torch {torch.__version__} '
            f'({torch.get_num_threads()} thread), {platform.machine()}')


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
