"""rcbf_ros: safe reinforcement learning with robust control barrier functions for ROS 2.
Importing it first sets numpy's OpenBLAS up for the per-step paths (:func:`configure_openblas`)."""
from __future__ import annotations

from collections.abc import Iterable, MutableMapping
import os
from pathlib import Path

AVX512_FLAGS = frozenset({'avx512f', 'avx512cd', 'avx512bw', 'avx512dq', 'avx512vl'})
"""The AVX-512 subsets OpenBLAS's SkylakeX kernels use."""
AVX2_FLAGS = frozenset({'avx2', 'fma'})
"""What OpenBLAS's Haswell kernels use (AVX2 and FMA3)."""


def coretype_for(flags: Iterable[str]) -> str | None:
    """The OpenBLAS kernel family (``OPENBLAS_CORETYPE`` value) for a CPU with these flags:
    'SkylakeX' with AVX-512 (F, CD, BW, DQ, VL), 'Haswell' with AVX2 and FMA, else None
    (leave the choice to OpenBLAS)."""
    present = set(flags)
    if AVX512_FLAGS <= present:
        return 'SkylakeX'
    if AVX2_FLAGS <= present:
        return 'Haswell'
    return None


def cpu_flags(cpuinfo: Path = Path('/proc/cpuinfo')) -> frozenset[str]:
    """The instruction set flags of the first processor in ``cpuinfo`` (empty where there is
    no such file, e.g. off Linux, or it has no flags line)."""
    try:
        with open(cpuinfo, encoding='utf-8', errors='replace') as lines:
            for line in lines:
                key, _, value = line.partition(':')
                if key.strip() == 'flags':
                    return frozenset(value.split())
    except OSError:
        pass
    return frozenset()


def configure_openblas(environ: MutableMapping[str, str], *,
              cpuinfo: Path = Path('/proc/cpuinfo')) -> None:
    """Set ``OPENBLAS_NUM_THREADS`` to 1 and ``OPENBLAS_CORETYPE`` to :func:`coretype_for` the
    CPU's flags, each unless ``environ`` already has it.

    numpy serves the per-step paths (the policy's action, the GP at one state, the filter's small
    matrices), where two OpenBLAS defaults cost several times the arithmetic
    (benchmarks/bench_blas_threads.py measures both): above ~10^4 elements it splits a product
    over a thread per core, often descheduled on shared cores; and a DYNAMIC_ARCH build falls
    back to its oldest x86-64 kernels on a CPU model newer than itself, although the CPU has
    AVX2 or AVX-512. OpenBLAS reads both variables once, when numpy loads it, so this runs when
    the package is imported: before numpy whenever a process imports ``rcbf_ros`` first (every
    entry point, the tests' conftest, the benchmarks). A process that imported numpy first keeps
    what its OpenBLAS chose.
    """
    environ.setdefault('OPENBLAS_NUM_THREADS', '1')
    if 'OPENBLAS_CORETYPE' not in environ:
        coretype = coretype_for(cpu_flags(cpuinfo))
        if coretype is not None:
            environ['OPENBLAS_CORETYPE'] = coretype


# Before numpy is first imported: every entry point imports this package first.
configure_openblas(os.environ)

__version__ = '0.1.0'
