"""GP disturbance model: fit time as data grow, and per-state prediction vs GPyTorch's own.

    python benchmarks/bench_gp.py [--repeats 300] [--no-write]

Data: the Unicycle slope disturbance d(x) = g(x) u_d, u_d = -0.1 cos(theta) [1, 0], at
uniform states in the arena with noise std 0.01 (3 inputs, 3 outputs). One run measures:
- ``DisturbanceGP.fit()`` (default ``GPConfig``: posterior on <= 512 farthest-point
  points, marginal likelihood on the first 256 of them, 30 Adam steps, cold start) at 2000
  and 5000 points, median of 3 fits;
- ``predict`` for one state (B = 1) and for a minibatch (B = 256) with our cached closed
  form, next to GPyTorch's exact predictive (eval mode, same training points and
  hyperparameters, ``fast_pred_var`` off, caches warm) at the same query points; the ratio
  is GPyTorch's time / ours;
- one-state ``predict`` with each system's state size and its exactly known dimensions
  (positions and other rows the nominal model predicts to rounding error: residual 0), with
  those dimensions skipped (default ``exact_output_tol``) and with a GP on every dimension
  (``exact_output_tol=0``), caches warm and with the last-level cache flushed before each call
  (as after a SAC update in the training loop).
Writes the ``## GP disturbance model`` section of benchmarks/RESULTS.md.
"""
from __future__ import annotations

# First: numpy's BLAS set up as in every rcbf_ros process (rcbf_ros/__init__.py).
import rcbf_ros  # noqa: F401  # isort: skip

import argparse
import math
from pathlib import Path
import statistics
import sys
import time

import gpytorch
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks._results import publish_section  # noqa: E402
from rcbf_ros.learning.gp import DisturbanceGP, GPConfig  # noqa: E402

torch.set_num_threads(1)
DTYPE = torch.float64
HALF_WIDTH = torch.tensor([3.0, 3.0, math.pi], dtype=DTYPE)


def slope_data(count: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    generator = torch.Generator().manual_seed(seed)
    states = (2 * torch.rand(count, 3, generator=generator, dtype=DTYPE) - 1) * HALF_WIDTH
    theta = states[:, 2]
    truth = torch.stack([-0.1 * torch.cos(theta) ** 2, -0.1 * torch.cos(theta) * torch.sin(theta),
                         torch.zeros_like(theta)], dim=1)
    return states, truth + 0.01 * torch.randn(count, 3, generator=generator, dtype=DTYPE)


class _GPyTorchBatchGP(gpytorch.models.ExactGP):
    def __init__(self, x, y, likelihood):
        super().__init__(x, y, likelihood)
        batch = torch.Size([y.shape[0]])
        self.mean_module = gpytorch.means.ZeroMean(batch_shape=batch)
        self.covar_module = gpytorch.kernels.ScaleKernel(
            gpytorch.kernels.RBFKernel(ard_num_dims=x.shape[-1], batch_shape=batch),
            batch_shape=batch)

    def forward(self, x):
        return gpytorch.distributions.MultivariateNormal(self.mean_module(x),
                                                         self.covar_module(x))


def gpytorch_twin(gp: DisturbanceGP):
    """GPyTorch's exact GP with our training points and hyperparameters, in eval mode."""
    n_out = gp.n_out
    x = gp.train_x.unsqueeze(0).expand(n_out, -1, -1)
    y = gp.train_y.T.contiguous()
    likelihood = gpytorch.likelihoods.GaussianLikelihood(
        batch_shape=torch.Size([n_out]),
        noise_constraint=gpytorch.constraints.GreaterThan(1e-12)).to(DTYPE)
    model = _GPyTorchBatchGP(x, y, likelihood).to(DTYPE)
    model.covar_module.base_kernel.lengthscale = gp.lengthscales.unsqueeze(1)
    model.covar_module.outputscale = gp.outputscale
    likelihood.noise = gp.noise.unsqueeze(1)
    model.eval()
    likelihood.eval()

    def predict(query: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        with torch.no_grad(), gpytorch.settings.fast_pred_var(False), \
                gpytorch.settings.max_cholesky_size(10_000):
            latent = model(query.unsqueeze(0).expand(n_out, -1, -1))
            return latent.mean.T, latent.variance.sqrt().T

    return predict


def per_call_us(fn, queries: list[torch.Tensor], before=None) -> float:
    """Median time of ``fn(q)`` over ``queries``; ``before()`` runs untimed ahead of each."""
    for q in queries[:20]:
        fn(q)
    times = []
    for q in queries:
        if before is not None:
            before()
        start = time.perf_counter()
        fn(q)
        times.append(time.perf_counter() - start)
    return 1e6 * statistics.median(times)


SYSTEM_SHAPES = {'unicycle': (3, (2,)), 'pvtol': (6, (0, 1, 2, 3, 5)),
                 'car_following': (10, (0, 2, 4, 6, 7, 8))}
"""state size, and the dimensions with residual 0 (as measured in training runs: Unicycle
theta; PVTOL all but theta; Car Following the five positions and car 4's speed)."""


def known_dimension_rows(repeats: int) -> list[str]:
    """One-state predict: known dimensions skipped vs a GP on every one, warm and cold."""
    flush = torch.empty(64 * 2 ** 20 // 8, dtype=DTYPE)  # 64 MB > the 32 MB last-level cache
    rows = ['| system | state dims | known dims | caches | every dim (us) '
            '| known skipped (us) | ratio every / skipped | max abs diff, active dims |',
            '|---|---:|---:|---|---:|---:|---:|---:|']
    for system, (n_x, known) in SYSTEM_SHAPES.items():
        generator = torch.Generator().manual_seed(n_x)
        states = torch.randn(2000, n_x, generator=generator, dtype=DTYPE)
        residuals = 0.1 * torch.sin(states @ torch.randn(n_x, n_x, generator=generator,
                                                         dtype=DTYPE))
        residuals[:, list(known)] = 0.0
        hyper = (torch.full((n_x, n_x), 1.5, dtype=DTYPE), torch.full((n_x,), 0.01, dtype=DTYPE),
                 torch.full((n_x,), 1e-4, dtype=DTYPE))
        models = {}
        for tol, name in ((0.0, 'every'), (1e-9, 'skipped')):
            gp = DisturbanceGP(n_x, n_x, GPConfig(exact_output_tol=tol))
            gp.add(states, residuals)
            gp.set_hyperparameters(*hyper)
            models[name] = gp
        queries = [torch.randn(n_x, generator=generator, dtype=DTYPE) for _ in range(repeats)]
        calls = {'every': models['every'].predict, 'skipped': models['skipped'].predict}
        active = [d for d in range(n_x) if d not in known]
        diff = max(float((a - b)[:, active].abs().max()) for a, b in zip(
            calls['every'](queries[0]), calls['skipped'](queries[0])))
        for caches, before in (('warm', None), ('cold', lambda: flush.add_(1.0))):
            t = {name: per_call_us(fn, queries, before=before) for name, fn in calls.items()}
            rows.append(f"| {system} | {n_x} | {len(known)} | {caches} | {t['every']:.0f} "
                        f"| {t['skipped']:.0f} | {t['every'] / t['skipped']:.1f}x | {diff:.1e} |")
            print(rows[-1], flush=True)
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('--repeats', type=int, default=300, help='predict calls per case')
    parser.add_argument('--no-write', action='store_true', help='do not touch RESULTS.md')
    args = parser.parse_args()

    rows = ['| data points | fit (s) | training points | RMSE vs truth |', '|---|---|---|---|']
    fitted = None
    for count in (2000, 5000):
        states, residuals = slope_data(count, seed=count)
        fit_times = []
        for _ in range(3):
            gp = DisturbanceGP(3, 3)
            gp.add(states, residuals)
            start = time.perf_counter()
            gp.fit()
            fit_times.append(time.perf_counter() - start)
        held_out, _ = slope_data(1000, seed=1)
        theta = held_out[:, 2]
        truth = torch.stack([-0.1 * torch.cos(theta) ** 2,
                             -0.1 * torch.cos(theta) * torch.sin(theta),
                             torch.zeros_like(theta)], dim=1)
        rmse = float((gp.predict(held_out)[0] - truth).pow(2).mean().sqrt())
        rows.append(f'| {count} | {statistics.median(fit_times):.2f} | {gp.train_x.shape[0]} '
                    f'| {rmse:.4f} |')
        fitted = gp
        print(rows[-1], flush=True)

    assert fitted is not None
    reference = gpytorch_twin(fitted)
    predict_rows = ['| query batch | ours (us) | GPyTorch exact (us) | ratio GPyTorch / ours | '
                    'max abs diff (mean, std) |', '|---|---|---|---|---|']
    for batch in (1, 256):
        repeats = args.repeats if batch == 1 else max(args.repeats // 10, 20)
        queries = [slope_data(batch, seed=10_000 + i)[0] for i in range(repeats)]
        ours = per_call_us(fitted.predict, queries)
        theirs = per_call_us(reference, queries)
        ours_mean, ours_std = fitted.predict(queries[0])
        ref_mean, ref_std = reference(queries[0])
        diff = max(float((ours_mean - ref_mean).abs().max()),
                   float((ours_std - ref_std).abs().max()))
        predict_rows.append(f'| {batch} | {ours:.0f} | {theirs:.0f} | {theirs / ours:.1f} '
                            f'| {diff:.1e} |')
        print(predict_rows[-1], flush=True)

    blocks = [
        'Unicycle slope disturbance, 3 inputs / 3 outputs, noise std 0.01. Default `GPConfig`: '
        'posterior on <= 512 farthest-point points, marginal likelihood on the first 256, '
        '30 Adam steps, cold start. Fit: median of 3.',
        rows,
        'Prediction with the 5000-point model (512 training points), median per call; '
        'GPyTorch: same points and hyperparameters, eval mode, exact variances, warm caches.',
        predict_rows,
        'One state, 2000 points (512 training points), synthetic residuals with each '
        "system's exactly known dimensions at 0 (`SYSTEM_SHAPES`); median per call. "
        "'every dim': `exact_output_tol=0`, a posterior on every output; "
        "'known skipped': the default, known outputs return 0 / 0 without a kernel matrix. "
        "'cold': a 64 MB buffer is written (untimed) before each call, as a SAC update evicts "
        "the GP's factors in the training loop.", known_dimension_rows(args.repeats)]
    publish_section('GP disturbance model', script='bench_gp.py', blocks=blocks,
                    write=not args.no_write)


if __name__ == '__main__':
    main()
