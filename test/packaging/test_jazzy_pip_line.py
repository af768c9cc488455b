"""The README's Jazzy pip line installs without an ERROR beside Jazzy's colcon.

On Ubuntu 24.04 the venv of "On a ROS 2 Jazzy machine" sees the system's packages: apt's
colcon-core 0.21.3 (which requires setuptools<80) and setuptools 68.1.2. torch needs
setuptools>=77.0.3, so pip puts a newer one into the venv; unpinned, that is the newest, and
pip ends with ``ERROR: ... colcon-core 0.21.3 requires setuptools<80``. ``constraints.txt``
pins one that both accept. Here a venv of that system's own stands in for /usr/lib/python3
(a ``.pth`` file: pip sees its packages and leaves them alone, as it leaves the system's), and
the README's line runs against it as written, with ``src/rcbf_ros`` this checkout.

Slow, and it needs the package index (colcon-core, setuptools, the line's packages; pip's
cache serves a second run).
"""
from __future__ import annotations

from pathlib import Path
import re
import shlex
import subprocess
import sys

import pytest

pytestmark = pytest.mark.slow

REPO = Path(__file__).resolve().parents[2]
SYSTEM_PACKAGES = ('colcon-core==0.21.3', 'setuptools==68.1.2', 'numpy==1.26.4')
"""What Ubuntu 24.04 with ROS 2 Jazzy has in /usr/lib/python3 that the line meets."""


def readme_pip_lines() -> list[list[str]]:
    """The ``pip install`` lines of the README's Jazzy block, in order, ``src/rcbf_ros`` made
    this checkout."""
    text = (REPO / 'README.md').read_text()
    section = text[text.index('## On a ROS 2 Jazzy machine'):]
    start = section.index('```bash')
    block = section[start:section.index('```\n', start + 7)]
    return [[word.replace('src/rcbf_ros', str(REPO)) for word in shlex.split(line, comments=True)]
            for line in block.splitlines() if line.startswith('pip install')]


def _run(*command: str | Path, cwd: Path) -> str:
    done = subprocess.run([str(c) for c in command], cwd=cwd, stdout=subprocess.PIPE,
                          stderr=subprocess.STDOUT, text=True, timeout=1500)
    assert done.returncode == 0, f'{command}: exit {done.returncode}\n{done.stdout[-4000:]}'
    return done.stdout


def _site(venv: Path) -> Path:
    """The venv's site-packages, as its own Python names it (Debian's scheme differs)."""
    return Path(_run(venv / 'bin' / 'python', '-c',
                     'import sysconfig; print(sysconfig.get_path("purelib"))', cwd=venv).strip())


def test_the_readme_pip_lines_are_found():
    lines = readme_pip_lines()
    assert lines and all(words[:2] == ['pip', 'install'] for words in lines)
    assert all(str(REPO / 'constraints.txt') in words for words in lines)


@pytest.mark.timeout(1800)
def test_the_jazzy_pip_line_prints_no_error(tmp_path):
    python = sys._base_executable if hasattr(sys, '_base_executable') else sys.executable
    system = tmp_path / 'system'
    _run(python, '-m', 'venv', system, cwd=tmp_path)
    _run(system / 'bin' / 'python', '-m', 'pip', 'install', '-q', *SYSTEM_PACKAGES, cwd=tmp_path)
    venv = tmp_path / 'ws' / 'venv'
    _run(python, '-m', 'venv', venv, cwd=tmp_path)
    # Python 3.12's venv (Jazzy's) holds pip alone; an older one's setuptools goes.
    _run(venv / 'bin' / 'python', '-m', 'pip', 'uninstall', '-q', '-y', 'setuptools',
         cwd=tmp_path)
    (_site(venv) / 'system_site.pth').write_text(f'{_site(system)}\n')
    before = _run(venv / 'bin' / 'python', '-c', 'import colcon_core, setuptools; '
                  'print(setuptools.__version__)', cwd=tmp_path)
    assert before.split()[-1] == '68.1.2'

    for words in readme_pip_lines():
        out = _run(venv / 'bin' / 'python', '-m', *words, cwd=tmp_path / 'ws')
        errors = [ln for ln in out.splitlines() if re.match(r'\s*ERROR\b', ln)]
        assert errors == [], '\n'.join(errors + [out[-3000:]])
    # The oracle of pip's message itself: every installed requirement holds, colcon's too.
    _run(venv / 'bin' / 'python', '-m', 'pip', 'check', cwd=tmp_path)
