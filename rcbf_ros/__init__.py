"""rcbf_ros: safe reinforcement learning with robust control barrier functions for ROS 2.

Importing the package sets numpy's OpenBLAS up for the package's one-state products, before
numpy first loads. numpy serves the per-step paths (the policy's action, the GP's prediction
at one state, the filter's small matrices). Two of OpenBLAS's defaults cost them several times
the arithmetic:

- **Threads.** Above ~10^4 elements OpenBLAS splits a product over a thread per core; on the
  shared cores of a run (simulator, filter, recorder, perhaps another run) that helper thread
  is often descheduled: benchmarks/bench_blas_threads.py measures a 1 x 256 x 256 product at a
  few ms p99 with the default and microseconds with one thread. So: one thread.
- **Kernel.** A DYNAMIC_ARCH OpenBLAS picks its kernels from the CPU's family and model number.
  A model newer than the library (a recent Xeon, often behind a hypervisor's generic model
  name) falls back to the oldest x86-64 kernels ('Prescott', SSE3), although the CPU has AVX2
  or AVX-512: benchmarks/bench_blas_threads.py measures the policy's products up to several
  times slower with them, a minibatch-sized one more. So: the kernel family that the CPU's
  instruction set flags (``/proc/cpuinfo``, which lists only what the kernel enabled) support,
  the choice OpenBLAS itself makes for a model it knows.

Both are environment variables that OpenBLAS reads once, when numpy loads it: this module sets
them (:func:`configure_openblas`) when it is imported, i.e. before numpy whenever the first
import of a process is of ``rcbf_ros`` (every entry point, the tests' conftest, the
benchmarks). A value already in the environment is kept; a process that imported numpy first
keeps what its OpenBLAS chose.
"""
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
    CPU's flags, each unless ``environ`` already has it."""
    environ.setdefault('OPENBLAS_NUM_THREADS', '1')
    if 'OPENBLAS_CORETYPE' not in environ:
        coretype = coretype_for(cpu_flags(cpuinfo))
        if coretype is not None:
            environ['OPENBLAS_CORETYPE'] = coretype


# Before numpy is first imported: every entry point imports this package first.
configure_openblas(os.environ)

__version__ = '0.1.0'
