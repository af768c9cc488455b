"""A hidden layer's backward products through oneDNN: the transposed operands passed as views,
against copied to a contiguous layout first.

    python benchmarks/bench_linear_transpose.py [--calls 300] [--rounds 5] [--no-write]

The backward of a hidden layer y = x W^T (rcbf_ros.learning.networks: ``Linear``'s gradient and
``twin_minimum``'s) takes two products with transposed operands: grad_x = grad W
(``linear(grad, W^T)``) and grad_W = grad^T x (``linear(grad^T, x^T)``). rcbf_ros passes the
transposes to oneDNN as views of contiguous tensors: it reads a transposed weight in place, and
copies a transposed input itself (torch's profiler shows one copy in grad_W, none in grad_x).
The other way copies each transpose to a contiguous tensor first (``.t().contiguous()``, three
copies of a (B, 256) or (256, 256) float32 tensor per layer), then multiplies.

Two tables, one thread, each way's calls in alternating blocks of ``--calls`` consecutive calls
(``--rounds`` blocks each, after 20 untimed calls), best block median and median of block
medians:

- the two products alone, at 256x256 weights and batch sizes from 64 to 1024;
- the whole eager SAC update (256x256 networks, minibatch 256, a random batch), with the
  backward of ``Linear`` and ``twin_minimum`` as the library has it (views) and as the copies
  version (the library's backward with ``.contiguous()`` on each transpose, swapped in for its
  blocks and restored after).

Which is faster depends on the CPU and on oneDNN's kernels for the strides it is given; the
printed figures are this machine's.
"""
from __future__ import annotations

import argparse
import contextlib
import os
from pathlib import Path
import statistics
import sys
import time
from typing import Callable, Iterator

import numpy as np
import torch
from torch.autograd.function import once_differentiable

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks._results import publish_section  # noqa: E402
from rcbf_ros.learning import networks  # noqa: E402
from rcbf_ros.learning.buffers import TransitionBatch  # noqa: E402
from rcbf_ros.learning.networks import linear  # noqa: E402
from rcbf_ros.learning.sac import SAC, SACConfig  # noqa: E402

torch.set_num_threads(1)
HIDDEN = 256
BATCHES = (64, 128, 256, 512, 1024)


@staticmethod
@once_differentiable
def _linear_backward_copies(ctx, grad):
    """``Linear``'s backward with each transpose copied to a contiguous layout first."""
    x, weight = ctx.saved_tensors
    need_x, need_weight, need_bias = ctx.needs_input_grad
    grad = grad.contiguous()
    grad_x = linear(grad, weight.t().contiguous()) if need_x else None
    grad_weight = (linear(grad.t().contiguous(), x.t().contiguous())
                   if need_weight else None)
    grad_bias = grad.sum(0) if need_bias and ctx.has_bias else None
    return grad_x, grad_weight, grad_bias


@contextlib.contextmanager
def copies_first() -> Iterator[None]:
    """The library's hidden-layer backward passes with the transposes copied first: ``Linear``'s
    (above) and ``twin_minimum``'s (its ``linear`` sees ``weight.t().contiguous()``)."""
    saved_backward, saved_linear = networks._LinearFunction.backward, networks.linear

    def linear_copying(x, weight, bias=None):
        return saved_linear(x, weight.contiguous(), bias)

    networks._LinearFunction.backward = _linear_backward_copies
    # Module-wide: twin_minimum's backward multiplies by weight.t(), now copied first; every
    # other weight passed to it is contiguous already (.contiguous() returns it as it is).
    networks.linear = linear_copying
    try:
        yield
    finally:
        networks._LinearFunction.backward = saved_backward
        networks.linear = saved_linear


def blocks(ways: dict[str, Callable[[], object]], calls: int, rounds: int
           ) -> dict[str, list[float]]:
    """Each way's block medians (us): ``rounds`` blocks of ``calls`` consecutive calls each,
    the ways' blocks alternating, each block after 20 untimed calls."""
    medians: dict[str, list[float]] = {name: [] for name in ways}
    for _ in range(rounds):
        for name, call in ways.items():
            for _ in range(20):
                call()
            times = []
            for _ in range(calls):
                start = time.perf_counter()
                call()
                times.append(time.perf_counter() - start)
            medians[name].append(1e6 * statistics.median(times))
    return medians


def product_ways(grad: torch.Tensor, x: torch.Tensor, weight: torch.Tensor
                 ) -> dict[str, dict[str, Callable[[], torch.Tensor]]]:
    """The backward's two products of one layer, each with its transposes copied or viewed."""
    return {
        'grad_x = grad W': {
            'copies': lambda: linear(grad, weight.t().contiguous()),
            'views': lambda: linear(grad, weight.t())},
        'grad_W = grad^T x': {
            'copies': lambda: linear(grad.t().contiguous(), x.t().contiguous()),
            'views': lambda: linear(grad.t(), x.t())},
    }


def products_table(calls: int, rounds: int) -> list[str]:
    rows = ['| batch | product | copies first: best, median us | views: best, median us '
            '| copies / views (medians) |', '|---:|---|---:|---:|---:|']
    generator = torch.Generator().manual_seed(0)
    weight = torch.randn(HIDDEN, HIDDEN, generator=generator)
    for batch in BATCHES:
        grad = torch.randn(batch, HIDDEN, generator=generator)
        x = torch.randn(batch, HIDDEN, generator=generator)
        cases = product_ways(grad, x, weight)
        for name, ways in cases.items():
            difference = float((ways['copies']() - ways['views']()).abs().max())
            scale = float(ways['views']().abs().max())
            assert difference <= 1e-5 * scale, (name, batch, difference)
            got = blocks(ways, calls, rounds)
            copies, views = (statistics.median(got[w]) for w in ('copies', 'views'))
            rows.append(f'| {batch} | {name} | {min(got["copies"]):.1f}, {copies:.1f} '
                        f'| {min(got["views"]):.1f}, {views:.1f} | {copies / views:.2f}x |')
            print(rows[-1], flush=True)
    return rows


def update_table(calls: int, rounds: int) -> list[str]:
    obs_dim, n_u, size = 7, 2, 256
    generator = torch.Generator().manual_seed(1)

    def rand(*shape: int) -> torch.Tensor:
        return torch.randn(*shape, generator=generator)

    batch = TransitionBatch(obs=rand(size, obs_dim), state=rand(size, 3), u_rl=rand(size, n_u),
                            u_safe=rand(size, n_u), u_s=rand(size, n_u), reward=rand(size),
                            next_obs=rand(size, obs_dim), next_state=rand(size, 3),
                            done=torch.zeros(size))
    sac = SAC(obs_dim, n_u, -np.ones(n_u), np.ones(n_u), SACConfig(mode='baseline'), seed=0)

    def copies() -> None:
        with copies_first():
            sac.update(batch)

    got = blocks({'copies': copies, 'views': lambda: sac.update(batch)}, calls, rounds)
    copies_ms, views_ms = (statistics.median(got[w]) / 1e3 for w in ('copies', 'views'))
    rows = ['| update | copies first: best, median ms | views: best, median ms '
            '| copies / views (medians) |', '|---|---:|---:|---:|',
            f'| eager SAC update, minibatch {size}, {HIDDEN}x{HIDDEN} networks '
            f'| {min(got["copies"]) / 1e3:.2f}, {copies_ms:.2f} '
            f'| {min(got["views"]) / 1e3:.2f}, {views_ms:.2f} | {copies_ms / views_ms:.2f}x |']
    print(rows[-1], flush=True)
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--calls', type=int, default=300, help='calls per block')
    parser.add_argument('--rounds', type=int, default=5, help='blocks per way')
    parser.add_argument('--no-write', action='store_true', help='print only')
    args = parser.parse_args()
    load_before = os.getloadavg()[0]
    update_calls = max(args.calls // 10, 10)  # an update takes some 30 products' time
    products = products_table(args.calls, args.rounds)
    update = update_table(update_calls, args.rounds)
    note = (f'Per block: the median of {args.calls} consecutive calls of one way (the update: '
            f"{update_calls}), {args.rounds} blocks per way, the ways' blocks "
            'alternating; "best" is the best block median. "copies first" copies each '
            'transposed operand to a contiguous tensor before the product; "views" passes the '
            'transpose as a strided view (what rcbf_ros.learning.networks does). Both give the '
            'same products to float32 round-off (checked).')
    publish_section('Hidden-layer backward: transposed views against copies',
                    script='bench_linear_transpose.py', blocks=[note, products, update],
                    write=not args.no_write,
                    conditions=f'; 1-minute load average {load_before:.1f} before, '
                               f'{os.getloadavg()[0]:.1f} after, on 2 cores')


if __name__ == '__main__':
    main()
