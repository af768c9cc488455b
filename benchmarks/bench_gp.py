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
  (as after a SAC update in the training loop);
- one-state prediction on a GP fitted to each system's own residuals (2000 simulator steps of
  uniform random actions, default ``GPConfig``), by variance bound: the bound each output took
  at the refit (``predict_state``), the low-rank bound on every output and the exact variance,
  interleaved state by state, warm and cold, with the numbers each reads per state and its std
  against the exact one on the stored states.
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
import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks._results import publish_section  # noqa: E402
from rcbf_ros.learning.gp import DisturbanceGP, GPConfig  # noqa: E402
from rcbf_ros.learning.gp_bounds import predict_plan  # noqa: E402

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


def system_residuals(system: str, steps: int) -> tuple[np.ndarray, np.ndarray]:
    """States and residuals ``x_dot_hat - f - g u`` of ``steps`` simulator steps with uniform
    random actions, as the learner labels them."""
    from rcbf_ros.training.agent import LearnerConfig
    from rcbf_ros.training.build import build_run, RunConfig
    run = RunConfig(system=system, episodes=1, max_steps=10 ** 6, record_bag=False,
                    out_dir='/tmp/bench_gp', learner=LearnerConfig(mode='baseline', seed=0))
    env, _, learner, _ = build_run(run)
    rng = np.random.default_rng(0)
    _, info = env.reset(seed=0)
    states, residuals = [], []
    for _ in range(steps):
        u = rng.uniform(learner.sac.u_low.numpy(), learner.sac.u_high.numpy())
        _, _, terminated, truncated, next_info = env.step(u)
        x = torch.as_tensor(np.asarray(info['state'], dtype=np.float64)).unsqueeze(0)
        model = learner.system
        nominal = model.f(x) + (model.g(x) @ torch.as_tensor(u).reshape(1, -1, 1)).squeeze(-1)
        residuals.append(((torch.as_tensor(next_info['state']) - x[0]) / env.dt
                          - nominal[0]).numpy())
        states.append(x[0].numpy())
        info = next_info
        if terminated or truncated:
            _, info = env.reset()
    return np.stack(states), np.stack(residuals)


def numbers_read(plan: dict) -> int:
    """Numbers one state's prediction on a plan reads: the training inputs, the lengthscales
    and each part's rows (of a neighbourhood factor, the one block it gathers)."""
    count = plan['points_t'].size + plan['neg_half_w'].size
    for part in plan['parts']:
        for name in ('project', 'project_t', 'alpha', 'basis', 'vectors', 'kept_weights'):
            count += part[name].size if name in part else 0
        if 'factor_t' in part:
            count += part['factor_t'][:, 0].size + part['neighbours'][:, 0].size
    return count


def bound_rows(repeats: int) -> list[str]:
    """One-state prediction by bound on GPs fitted to each system's residuals."""
    flush = torch.empty(64 * 2 ** 20 // 8, dtype=DTYPE)
    rows = ['| system | outputs with a posterior | bound per output (rank) | numbers read per '
            'state: chosen, low-rank, exact | warm (us): chosen, low-rank, exact | cold (us): '
            'chosen, low-rank, exact | std chosen / exact on the stored states (max, min) |',
            '|---|---:|---|---|---|---|---|']
    for system in SYSTEM_SHAPES:
        states, residuals = system_residuals(system, 2000)
        gp = DisturbanceGP(states.shape[1], residuals.shape[1])
        gp.add(states, residuals)
        gp.fit()
        cache = gp._cache
        assert cache is not None
        queries = [torch.as_tensor(row) for row in states[-repeats:]]
        calls = {
            'chosen': lambda q, gp=gp: gp.predict_state(q.numpy()),
            'low-rank': lambda q, gp=gp: gp.predict_state(q.numpy(), bound='low_rank'),
            'exact': lambda q, gp=gp: gp.predict(q.unsqueeze(0), exact=True)}
        times: dict[tuple[str, str], list[float]] = {}
        for q in queries:  # interleaved: every path and setting at each state
            for caches in ('warm', 'cold'):
                for name, fn in calls.items():
                    fn(q)
                    if caches == 'cold':
                        flush.add_(1.0)
                    start = time.perf_counter()
                    fn(q)
                    times.setdefault((caches, name), []).append(time.perf_counter() - start)
        med = {key: 1e6 * statistics.median(value) for key, value in times.items()}
        active = gp.active_outputs
        exact_std = gp.predict(torch.as_tensor(states), exact=True)[1][:, active]
        ratio = (gp.predict(torch.as_tensor(states))[1][:, active]
                 / exact_std.clamp_min(1e-300))
        bound = gp.variance_bound
        names = ', '.join(f"{name.replace('_', ' ')} {rank}"
                          for name, rank in zip(bound['bound'], bound['rank'].tolist()))
        if bound['shared']:
            names += f" (shared basis {bound['shared']})"
        read = [numbers_read(cache['plans']['chosen']), numbers_read(cache['plans']['low_rank']),
                cache['chol_inv_t'].numel() + cache['x_scaled'].numel()]
        # The plan's arithmetic is the one predict_state runs: check it once here.
        assert np.array_equal(predict_plan(cache['plans']['chosen'], states[-1:])[:-1, 0, 1],
                              gp.predict_state(states[-1])[1][active.numpy()])
        rows.append(
            f"| {system} | {int(active.sum())} of {active.numel()} | {names} "
            f"| {read[0]:,}, {read[1]:,}, {read[2]:,} "
            f"| {med[('warm', 'chosen')]:.0f}, {med[('warm', 'low-rank')]:.0f}, "
            f"{med[('warm', 'exact')]:.0f} | {med[('cold', 'chosen')]:.0f}, "
            f"{med[('cold', 'low-rank')]:.0f}, {med[('cold', 'exact')]:.0f} "
            f"| {float(ratio.max()):.4f}, {float(ratio.min()):.6f} |")
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
        "the GP's factors in the training loop.", known_dimension_rows(args.repeats),
        "One state, by variance bound, on a GP fitted (default `GPConfig`, 512 training "
        "points) to 2000 steps of each system's simulator under uniform random actions; "
        'median per call over the last states visited, every path and setting interleaved '
        "state by state. 'chosen': `predict_state`, each output's bound as the refit chose "
        "it; 'low-rank': the low-rank bound on every output; 'exact': `predict(exact=True)`. "
        "'cold' as above. Every bound is never below the exact variance.",
        bound_rows(min(args.repeats, 300))]
    publish_section('GP disturbance model', script='bench_gp.py', blocks=blocks,
                    write=not args.no_write)


if __name__ == '__main__':
    main()
