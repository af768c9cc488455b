"""numpy's OpenBLAS setup at ``import rcbf_ros``: the kernel from the CPU's flags, one thread,
and what the environment already sets is kept (rcbf_ros/__init__.py)."""
from __future__ import annotations

import json
import os
from pathlib import Path
import subprocess
import sys

import pytest

from rcbf_ros import AVX2_FLAGS, AVX512_FLAGS, configure_openblas, coretype_for, cpu_flags

CPUINFO = """processor\t: 0
vendor_id\t: GenuineIntel
model name\t: Intel(R) Xeon(R) Processor
flags\t\t: fpu sse sse2 {extra}

processor\t: 1
flags\t\t: fpu
"""

# What numpy's OpenBLAS reports in a new process whose first import is rcbf_ros.
PROBE = """
import json, os, sys
import rcbf_ros
import numpy
import threadpoolctl
kernel = next(info.get('architecture') for info in threadpoolctl.threadpool_info()
              if info.get('internal_api') == 'openblas')
print(json.dumps({'kernel': kernel, 'threads': os.environ.get('OPENBLAS_NUM_THREADS'),
                  'coretype': os.environ.get('OPENBLAS_CORETYPE')}))
"""


def test_avx512_picks_skylakex_avx2_haswell_and_older_cpus_are_left_to_openblas() -> None:
    assert coretype_for(AVX512_FLAGS | AVX2_FLAGS | {'sse4_2'}) == 'SkylakeX'
    assert coretype_for(AVX2_FLAGS | {'avx512f'}) == 'Haswell'  # AVX-512F alone is not enough
    assert coretype_for(AVX2_FLAGS) == 'Haswell'
    assert coretype_for({'avx2'}) is None  # no FMA
    assert coretype_for({'sse', 'sse2', 'avx'}) is None
    assert coretype_for(()) is None


def test_the_flags_are_the_first_processors(tmp_path: Path) -> None:
    info = tmp_path / 'cpuinfo'
    info.write_text(CPUINFO.format(extra='avx2 fma'))
    assert cpu_flags(info) == {'fpu', 'sse', 'sse2', 'avx2', 'fma'}
    assert cpu_flags(tmp_path / 'missing') == frozenset()
    (tmp_path / 'noflags').write_text('processor\t: 0\n')
    assert cpu_flags(tmp_path / 'noflags') == frozenset()


def test_configure_sets_what_is_unset_and_keeps_what_is_set(tmp_path: Path) -> None:
    info = tmp_path / 'cpuinfo'
    info.write_text(CPUINFO.format(extra=' '.join(sorted(AVX512_FLAGS | AVX2_FLAGS))))
    environ: dict[str, str] = {}
    configure_openblas(environ, cpuinfo=info)
    assert environ == {'OPENBLAS_NUM_THREADS': '1', 'OPENBLAS_CORETYPE': 'SkylakeX'}
    environ = {'OPENBLAS_NUM_THREADS': '2', 'OPENBLAS_CORETYPE': 'Prescott'}
    configure_openblas(environ, cpuinfo=info)
    assert environ == {'OPENBLAS_NUM_THREADS': '2', 'OPENBLAS_CORETYPE': 'Prescott'}
    environ = {}
    # No flags: the kernel is OpenBLAS's choice.
    configure_openblas(environ, cpuinfo=tmp_path / 'missing')
    assert environ == {'OPENBLAS_NUM_THREADS': '1'}


def _probe(**overrides: str) -> dict[str, str | None]:
    env = {k: v for k, v in os.environ.items()
           if k not in ('OPENBLAS_NUM_THREADS', 'OPENBLAS_CORETYPE')}
    env.update(overrides)
    out = subprocess.run([sys.executable, '-c', PROBE], env=env, check=True,
                         capture_output=True, text=True, timeout=120).stdout
    return json.loads(out)


def test_a_process_that_imports_rcbf_ros_first_runs_numpy_on_the_chosen_kernel() -> None:
    pytest.importorskip('threadpoolctl')
    chosen = coretype_for(cpu_flags())
    if chosen is None:
        pytest.skip('this CPU has no AVX2 + FMA flags (or no /proc/cpuinfo): OpenBLAS chooses')
    probe = _probe()
    assert probe == {'kernel': chosen, 'threads': '1', 'coretype': chosen}
    # An explicit choice is the user's: kept, and OpenBLAS runs it.
    assert _probe(OPENBLAS_CORETYPE='Sandybridge')['kernel'] == 'Sandybridge'
