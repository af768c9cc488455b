"""GP data storage: one training step's ``add`` as the stored data grow, vs concatenation.

    python benchmarks/bench_gp_append.py [--repeats 200] [--no-write]

The learner adds one (state, residual) row to the disturbance GP on every environment step.
``DisturbanceGP.add`` writes it into storage that grows by doubling; the alternative is what it
replaced: the same input checks, then ``torch.cat`` of all stored rows with the new one (a copy
of everything, every step). PVTOL's shape (6 inputs, 6 outputs, float64). For each stored count
N the median and mean time of one add over ``repeats`` consecutive adds from N on (the mean
carries the occasional growth copy as often as it happens), next to the concatenation; the
ratio is concatenation / ours. Writes the ``## GP data storage`` section of
benchmarks/RESULTS.md.
"""
from __future__ import annotations

# First: numpy's BLAS set up as in every rcbf_ros process (rcbf_ros/__init__.py).
import rcbf_ros  # noqa: F401  # isort: skip

import argparse
from pathlib import Path
import statistics
import sys
import time

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks._results import publish_section  # noqa: E402
from rcbf_ros.learning.gp import DisturbanceGP  # noqa: E402

torch.set_num_threads(1)
DTYPE = torch.float64
N_X = 6


class ConcatenatingGP(DisturbanceGP):
    """The alternative: the same checks, then all stored rows and the new ones concatenated
    (what ``add`` did before the storage grew by doubling)."""

    def __init__(self, n_in: int, n_out: int) -> None:
        super().__init__(n_in, n_out)
        self._cat_x = torch.empty(0, n_in, dtype=DTYPE)
        self._cat_y = torch.empty(0, n_out, dtype=DTYPE)

    def add(self, x, y) -> None:
        x_t, y_t = self._checked_rows(x, y)
        self._cat_x = torch.cat([self._cat_x, x_t])
        self._cat_y = torch.cat([self._cat_y, y_t])


def time_adds(gp: DisturbanceGP, stored: int, rows: torch.Tensor) -> tuple[float, float]:
    """Median and mean time (us) of one ``add`` after ``stored`` rows."""
    gp.add(torch.zeros(stored, N_X, dtype=DTYPE), torch.zeros(stored, N_X, dtype=DTYPE))
    times = []
    for row in rows:
        start = time.perf_counter()
        gp.add(row, row)
        times.append(time.perf_counter() - start)
    return 1e6 * statistics.median(times), 1e6 * statistics.fmean(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('--repeats', type=int, default=200, help='adds per stored count')
    parser.add_argument('--no-write', action='store_true', help='do not touch RESULTS.md')
    args = parser.parse_args()

    note = ("One environment step's `DisturbanceGP.add` of a (state, residual) row, PVTOL's shape "
            '(6 x 6, float64), after N stored rows, over ' + str(args.repeats) + ' consecutive '
            'adds, next to the same checks followed by the `torch.cat` of all rows that it '
            'replaced. 30 000 rows is a 15-episode PVTOL run, 120 000 a 60-episode one, 200 000 '
            'the `paper` budget. A training step '
            '(SAC update, QP, GP prediction) takes about 24 ms on PVTOL.')
    rows = ['| stored rows N | ours, median (us) | ours, mean (us) | torch.cat, median (us) '
            '| torch.cat, mean (us) | ratio cat / ours (median) | ratio (mean) |',
            '|---:|---:|---:|---:|---:|---:|---:|']
    generator = torch.Generator().manual_seed(0)
    for stored in (1_000, 30_000, 120_000, 200_000):
        new = torch.randn(args.repeats, 1, N_X, generator=generator, dtype=DTYPE)
        ours = time_adds(DisturbanceGP(N_X, N_X), stored, new)
        cat = time_adds(ConcatenatingGP(N_X, N_X), stored, new)
        rows.append(f'| {stored} | {ours[0]:.1f} | {ours[1]:.1f} | {cat[0]:.1f} | {cat[1]:.1f} '
                    f'| {cat[0] / ours[0]:.1f}x | {cat[1] / ours[1]:.1f}x |')
        print(rows[-1], flush=True)
    publish_section('GP data storage', script='bench_gp_append.py', blocks=[note, rows],
                    write=not args.no_write)


if __name__ == '__main__':
    main()
