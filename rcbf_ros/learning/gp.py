"""Gaussian-process model of the unknown disturbance (paper: "Disturbance Estimation").

Labels are residuals of the nominal model, computed by the caller,

    y_i = x_dot_hat_i - f(x_i) - g(x_i) u_i,      y_i in R^{n_out},

and one independent exact GP with a zero prior mean and an ARD RBF kernel is kept per output
dimension d:

    k_d(x, x') = s_d * exp(-1/2 sum_j (x_j - x'_j)^2 / l_{d,j}^2),   y_d = f_d(x) + eps,
    eps ~ N(0, n_d).

Hyperparameters (l, s, n) are fitted with GPyTorch by maximising the exact marginal likelihood
for a bounded number of Adam steps, on inputs standardised per column and outputs scaled by
their root mean square (optimisation only: the fitted values are mapped back to raw units, see
``_fit_hyperparameters``). Weak Gamma priors keep lengthscales near the data's scale, so the
fit cannot collapse to the nearly constant GP that a huge initial lengthscale gives.

Prediction does not go through GPyTorch: after a fit we cache, per output dimension,
``L`` with ``L L^T = K + n I`` and ``alpha = K^-1 y``, and evaluate in closed form

    mean_d(x*) = k_d(x*, X)^T alpha_d,
    var_d(x*)  = s_d - |L_d^-1 k_d(x*, X)|^2   (+ n_d if ``include_noise_in_std``),

batched over query points and output dimensions. The disturbance box of eq.
(disturb_estimate) is ``mean +/- k_c std`` (``bounds``); ``k_c`` is the caller's.

Low-rank variance bound: the exact variance reads one M x M factor
per output and query, which at M = 512 (2 MB in float64) is most of a per-step action's cost.
With the eigendecomposition ``K + n I = U diag(mu) U^T`` (descending ``mu``) computed at each
refit, ``k^T (K + nI)^-1 k = sum_i (u_i . k)^2 / mu_i``; keeping the first r terms and giving
every discarded direction the weight of the largest discarded eigenvalue,

    var_r(x*) = s - sum_{i<=r} (u_i . k)^2 / mu_i - (|k|^2 - sum_{i<=r} (u_i . k)^2) / mu_{r+1},

can only subtract less than the exact sum (the discarded directions have ``mu_i <= mu_{r+1}``,
and their squared projections add up to ``|k|^2`` minus the kept ones), so ``var_r >= var``
for every query and the box ``mean +/- k_c std_r`` contains the exact one. The excess is at
most ``s * rho(mu_{r+1} - n)`` with ``rho(a) = max_{0<=l<=a} l (a - l) / ((l + n)(a + n))``
(since ``sum_i (u_i . k)^2 / (mu_i - n) <= s``, the prior variance), and r is the smallest
rank whose ``rho`` is within ``GPConfig.variance_rank_tolerance`` (0: every eigenpair, the
exact variance to round-off). A query then reads r x M numbers instead of M x M (twice:
the discarded part is evaluated as ``|k - U_r U_r^T k|^2``, not as the difference above,
whose terms are of size ``|k|^2 / n`` and cancel to round-off when the noise is far below the
signal; from r = M / 2 on, every eigenpair, in one pass, costs no more). ``predict(x,
exact=True)`` evaluates the exact variance (the reference). The mean is
exact either way. In floating point both variances carry round-off of about
``eps M s^2 / n``; the bound's measured deficits against the exact evaluation stay within it.

Hybrid variance bound (low rank plus a neighbourhood): for any vector w,
``2 w . k - w^T (K + nI) w <= k^T (K + nI)^-1 k`` (the maximum over w is at
``w = (K + nI)^-1 k``), so ``s - (2 w . k - w^T (K + nI) w)`` is never below the exact variance.
Maximising over w in the span of the first r eigenvectors and the unit vectors of a set S of
m training points, with ``E = K + nI - U_r diag(mu_r) U_r^T`` (the discarded part) gives

    var_h(x*) = s - sum_{i<=r} (u_i . k)^2 / mu_i - q^T E_SS^-1 q,    q = (k - U_r U_r^T k)_S.

``E_SS`` can be singular, so the bound uses ``E'_SS`` from ``E' = E + n U_r U_r^T`` (every
eigenvalue >= n, as conditioned as ``K + nI`` itself): ``E' >= E`` only lowers the subtracted
term. (``E'_SS`` is formed as ``(K + nI)_SS - U_S diag(mu_r - n) U_S^T``: M m^2 r work per rank.)
The bound keeps the larger of this term and the low-rank one, ``|k_perp|^2 / mu_{r+1}``
(both are valid), so it is at least as tight as the low-rank bound at the same rank. With
r = 0 it is the variance conditioned on S alone (fewer data never lower a GP's variance).
S is the neighbourhood of the training point nearest to the query (its m nearest training
points in the output's lengthscale-scaled metric), whose ``E'_SS`` factor is cached per
training point and rank at each refit (M m^2 numbers). The worst-case excess of the hybrid
bound has no closed form; at each refit, an output uses it at the smallest rank (of 0, 8, 16,
..., below the low-rank bound's own) whose std is within ``GPConfig.hybrid_std_tolerance`` of
the exact std on probe states, and keeps the low-rank bound when none is. Short lengthscales
and noise near the signal variance (where the low-rank bound needs nearly every eigenpair) are
where the neighbourhood carries the posterior. ``predict(x, bound='low_rank')`` evaluates the
low-rank bound on every output.

Exactly known outputs: a dimension whose residuals are all within ``exact_output_tol`` of zero
(e.g. a position whose derivative is a velocity in the state, so the nominal model predicts it
to rounding error) gets no posterior: ``predict`` returns mean 0 and std 0 for it without
touching a kernel matrix. Such dimensions are common (6 of 10 on Car Following, 5 of 6 on
PVTOL), and the single-query variance reads an M x M factor per output dimension, so this
cuts the per-step cost in proportion. A single residual beyond the tolerance makes the
dimension a normal GP output again at the next fit.

Data management: ``add`` appends to the full data set; ``fit`` trains on at most
``max_train_points`` of it, chosen by greedy farthest-point sampling in standardised input
space (or a seeded uniform random subsample), so fit and predict cost stay bounded as data grows.
"""
from __future__ import annotations

from dataclasses import dataclass
import math
from typing import Any, Literal

import gpytorch
import numpy as np
import torch

ArrayLike = torch.Tensor | np.ndarray


@dataclass(frozen=True)
class GPConfig:
    """Configuration of ``DisturbanceGP``."""

    prior_std: float = 1.0
    """Predictive std of every output before any data was fitted (the prior mean is 0)."""
    max_train_points: int = 512
    """Cap on the training set the posterior conditions on (exact GP cost is cubic in it)."""
    hyperparameter_points: int = 256
    """Cap on the points the marginal likelihood is optimised on: the first ones of the
    training subset in selection order (itself a farthest-point / random subset), so the
    Adam loop stays cheap while the posterior uses ``max_train_points``."""
    subset_rule: Literal['farthest_point', 'random'] = 'farthest_point'
    """How the capped training set is chosen when more data exist: greedy farthest-point
    sampling in standardised input space (covers the visited region evenly; first point picked
    with ``seed``), or a uniform random subsample drawn with ``seed``."""
    seed: int = 0
    """Seed of the subset selection."""
    training_iterations: int = 30
    """Adam steps on the negative marginal log likelihood per ``fit``."""
    learning_rate: float = 0.15
    """Adam learning rate (on GPyTorch's raw, softplus-constrained hyperparameters)."""
    initial_lengthscale: float = 1.0
    """Initial lengthscale in standardised input units (1 = one standard deviation of data)."""
    warm_start: bool = True
    """Start each ``fit`` after the first from the previous hyperparameters (re-expressed in
    the new normalisation) instead of the initial values."""
    lengthscale_prior: tuple[float, float] = (2.0, 2.0)
    """Gamma(concentration, rate) prior on lengthscales in standardised units (mean 1)."""
    outputscale_prior: tuple[float, float] = (2.0, 0.15)
    """Gamma prior on the signal variance in RMS-scaled output units (mean 1)."""
    noise_prior: tuple[float, float] = (1.1, 0.05)
    """Gamma prior on the noise variance in RMS-scaled output units (mean 0.11)."""
    min_noise: float = 1e-6
    """Lower bound of the noise variance in RMS-scaled output units (keeps K + nI well
    conditioned)."""
    include_noise_in_std: bool = False
    """If True ``predict`` returns the std of a noisy observation, else of the latent
    disturbance (the default: the RCBF bounds the disturbance itself)."""
    exact_output_tol: float = 1e-9
    """Output dimensions with every residual ``|y| <= exact_output_tol`` (raw units) are
    treated as exactly known: mean 0, std 0, no posterior cached. 0 keeps a GP on every
    output (then an all-zero dimension still gets one, with a tiny fitted signal variance)."""
    variance_rank_tolerance: float = 1e-4
    """Worst-case excess of the predicted variance over the exact one, relative to the
    output's signal variance, that the low-rank variance bound may have (see the module
    docstring); it never predicts less than the exact variance. 0: keep every eigenpair (the
    exact variance, to round-off, at the exact cost)."""
    variance_neighbours: int = 32
    """Neighbourhood size m of the hybrid variance bound (module docstring), which an output
    uses instead of the low-rank bound when the bound at a smaller rank stays within
    ``hybrid_std_tolerance`` of the exact std on probe states at the refit. Both bounds are
    never below the exact variance. 0 (or m >= M): the low-rank bound only."""
    hybrid_std_tolerance: float = 0.01
    """Largest relative excess of the hybrid bound's std over the exact std, on every probe
    state, for an output to use it (see ``variance_neighbours``)."""
    dtype: torch.dtype = torch.float64
    """Floating point type of data, hyperparameters and predictions."""

    def __post_init__(self) -> None:
        if not self.prior_std > 0:
            raise ValueError(f'prior_std must be > 0, got {self.prior_std}')
        if self.max_train_points < 1:
            raise ValueError(f'max_train_points must be >= 1, got {self.max_train_points}')
        if self.hyperparameter_points < 1:
            raise ValueError(
                f'hyperparameter_points must be >= 1, got {self.hyperparameter_points}')
        if self.subset_rule not in ('farthest_point', 'random'):
            raise ValueError(
                f"subset_rule must be 'farthest_point' or 'random', got {self.subset_rule!r}")
        if self.training_iterations < 0:
            raise ValueError(
                f'training_iterations must be >= 0, got {self.training_iterations}')
        if not self.min_noise > 0:
            raise ValueError(f'min_noise must be > 0, got {self.min_noise}')
        if not self.exact_output_tol >= 0:
            raise ValueError(f'exact_output_tol must be >= 0, got {self.exact_output_tol}')
        if not 0 <= self.variance_rank_tolerance < 1:
            raise ValueError('variance_rank_tolerance must be in [0, 1), got '
                             f'{self.variance_rank_tolerance}')
        if self.variance_neighbours < 0:
            raise ValueError(
                f'variance_neighbours must be >= 0, got {self.variance_neighbours}')
        if not self.hybrid_std_tolerance >= 0:
            raise ValueError(
                f'hybrid_std_tolerance must be >= 0, got {self.hybrid_std_tolerance}')


def _jittered_cholesky(a: torch.Tensor, tries: int = 6) -> torch.Tensor:
    """Cholesky factors of a batch (B, M, M) of covariance matrices.

    A batch element that is not numerically positive definite (near-duplicate inputs, a signal
    variance ~1e7 times the noise: a Car Following checkpoint held one) is refactored with
    jitter j * mean(diag) added, j = 1e-8 (float64; 1e-6 float32), then 10x per try, as GPyTorch
    does; the rest keep their exact factor.

    Raises:
        torch.linalg.LinAlgError: still not positive definite after ``tries`` jitters.
    """
    chol, info = torch.linalg.cholesky_ex(a)
    failed = info > 0
    if not bool(failed.any()):
        return chol
    eye = torch.eye(a.shape[-1], dtype=a.dtype)
    scale = a.diagonal(dim1=-2, dim2=-1).mean(-1)
    jitter = 1e-8 if a.dtype == torch.float64 else 1e-6
    for _ in range(tries):
        index = failed.nonzero().squeeze(-1)
        fixed, info_fixed = torch.linalg.cholesky_ex(
            a[index] + (jitter * scale[index])[:, None, None] * eye)
        chol[index] = fixed
        failed[index] = info_fixed > 0
        if not bool(failed.any()):
            return chol
        jitter *= 10.0
    raise torch.linalg.LinAlgError(
        f'GP covariance of output(s) {failed.nonzero().squeeze(-1).tolist()} is not positive '
        f'definite even with jitter {jitter / 10.0:g} x mean(diag)')


def variance_excess_ratio(*, tail: torch.Tensor, noise: torch.Tensor) -> torch.Tensor:
    """Worst-case excess of the low-rank variance bound over the exact variance, relative to
    the signal variance: ``rho(a) = max_{0<=l<=a} l (a - l) / ((l + n)(a + n))``, elementwise.

    Args:
        tail: the largest discarded eigenvalue of ``K + n I`` minus ``n`` (``a``); <= 0 gives 0.
        noise: the noise variance ``n`` (> 0), broadcast against ``tail``.

    The maximiser is ``l* = sqrt(n^2 + a n) - n``; rho grows with ``a`` from 0 (about
    ``a^2 / (4 n^2)`` for ``a << n``) towards 1.
    """
    a = tail.clamp_min(0.0)
    best = torch.sqrt(noise * noise + a * noise) - noise
    return best * (a - best) / ((best + noise) * (a + noise))


def _rank_groups(ranks: torch.Tensor) -> list[torch.Tensor]:
    """Outputs (indices into ``ranks``, ascending within a group) batched together: in order of
    rank, a new group starts where the rank exceeds twice the group's smallest plus 32 (one
    more group costs about as much as that many extra columns)."""
    groups: list[list[int]] = []
    smallest = 0
    for output in torch.argsort(ranks, stable=True).tolist():
        rank = int(ranks[output])
        if not groups or rank > 2 * smallest + 32:
            groups.append([])
            smallest = rank
        groups[-1].append(output)
    return [torch.tensor(sorted(group), dtype=torch.int64) for group in groups]


_HYBRID_RANKS = (0, 8, 16, 32, 64, 128, 256)
"""Ranks the hybrid bound is tried at, smallest (cheapest) first."""
_HYBRID_COST_COLUMNS = 16
"""The hybrid bound's neighbourhood term costs about as much as this many more low-rank
columns: a hybrid rank is only tried this far below the low-rank bound's own."""


def _check_bound(bound: str) -> None:
    """Refuse a ``bound`` argument of ``predict``/``predict_state`` that names no bound."""
    if bound not in ('chosen', 'low_rank'):
        raise ValueError(f"bound must be 'chosen' or 'low_rank', got {bound!r}")


def variance_ranks(*, eigenvalues: torch.Tensor, noise: torch.Tensor,
                   tolerance: float) -> torch.Tensor:
    """Per output, the fewest leading eigenpairs whose bound is within ``tolerance``.

    Args:
        eigenvalues: (D, M) of ``K_d + n_d I``, descending.
        noise: (D,) the ``n_d``.
        tolerance: largest allowed :func:`variance_excess_ratio` (0: all M).

    Returns:
        (D,) int64 ranks r_d in [0, M]: the ratio at tail ``mu_{r+1} - n`` is <= tolerance.
    """
    ratio = variance_excess_ratio(tail=eigenvalues - noise[:, None], noise=noise[:, None])
    # rho grows with the tail eigenvalue, which falls with r: the rank is the count above.
    return (ratio > tolerance).sum(dim=-1)


class _BatchIndependentExactGP(gpytorch.models.ExactGP):
    """``n_out`` independent exact GPs as one GPyTorch batch (zero mean, scaled ARD RBF)."""

    def __init__(self, train_x: torch.Tensor, train_y: torch.Tensor,
                 likelihood: gpytorch.likelihoods.GaussianLikelihood,
                 config: GPConfig) -> None:
        super().__init__(train_x, train_y, likelihood)
        n_out, _, n_in = train_x.shape
        batch = torch.Size([n_out])
        self.mean_module = gpytorch.means.ZeroMean(batch_shape=batch)
        self.covar_module = gpytorch.kernels.ScaleKernel(
            gpytorch.kernels.RBFKernel(
                ard_num_dims=n_in, batch_shape=batch,
                lengthscale_prior=gpytorch.priors.GammaPrior(*config.lengthscale_prior)),
            batch_shape=batch,
            outputscale_prior=gpytorch.priors.GammaPrior(*config.outputscale_prior))

    def forward(self, x: torch.Tensor) -> gpytorch.distributions.MultivariateNormal:
        return gpytorch.distributions.MultivariateNormal(self.mean_module(x),
                                                         self.covar_module(x))


def _as_tensor(value: ArrayLike, name: str, dtype: torch.dtype) -> torch.Tensor:
    if isinstance(value, np.ndarray):
        value = torch.from_numpy(value)
    if not isinstance(value, torch.Tensor):
        raise TypeError(f'{name} must be a torch.Tensor or numpy array, got {type(value)}')
    return value.detach().to(dtype)


def farthest_point_subset(points: torch.Tensor, count: int, first: int) -> torch.Tensor:
    """Greedy farthest-point sampling.

    Starting from ``points[first]``, repeatedly add the point whose distance to the chosen set
    is largest.

    Args:
        points: (N, n_in).
        count: number of points to choose, <= N.
        first: index of the first chosen point.

    Returns:
        (count,) int64 indices into ``points``, in the order chosen.
    """
    n_points = points.shape[0]
    chosen = torch.empty(count, dtype=torch.long)
    chosen[0] = first
    min_sq_dist = ((points - points[first]) ** 2).sum(dim=1)
    for i in range(1, count):
        nxt = int(torch.argmax(min_sq_dist))
        chosen[i] = nxt
        min_sq_dist = torch.minimum(min_sq_dist, ((points - points[nxt]) ** 2).sum(dim=1))
    if count > n_points:  # pragma: no cover - guarded by the caller
        raise ValueError('count exceeds the number of points')
    return chosen


class DisturbanceGP:
    """One exact GP per disturbance dimension, with cached closed-form prediction.

    Args:
        n_in: input (state) dimension.
        n_out: output (disturbance) dimension.
        config: see ``GPConfig``.
    """

    def __init__(self, n_in: int, n_out: int, config: GPConfig | None = None) -> None:
        if n_in < 1:
            raise ValueError(f'n_in must be >= 1, got {n_in}')
        if n_out < 1:
            raise ValueError(f'n_out must be >= 1, got {n_out}')
        self.n_in = n_in
        self.n_out = n_out
        self.config = config if config is not None else GPConfig()
        dtype = self.config.dtype
        # Storage grows by doubling; rows [:_count] are the data. One row is added per
        # environment step, so concatenating would copy all data on every step.
        self._store_x = torch.empty(0, n_in, dtype=dtype)
        self._store_y = torch.empty(0, n_out, dtype=dtype)
        self._count = 0
        # Raw-unit hyperparameters: lengthscales (n_out, n_in), outputscale (n_out,),
        # noise variance (n_out,). None until the first fit.
        self.lengthscales: torch.Tensor | None = None
        self.outputscale: torch.Tensor | None = None
        self.noise: torch.Tensor | None = None
        self.train_indices: torch.Tensor | None = None
        self._posterior: dict[str, torch.Tensor] | None = None
        self._pending: dict[str, Any] | None = None
        self._version = 0

    @property
    def _cache(self) -> dict[str, Any] | None:
        """The posterior's factors (None before a fit)."""
        return self._posterior

    @_cache.setter
    def _cache(self, value: dict[str, Any] | None) -> None:
        self._posterior = value
        self._version += 1

    @property
    def version(self) -> int:
        """Changes whenever the predictions may change (each posterior rebuilt or dropped);
        data added without a refit leaves it, and the predictions, as they are."""
        return self._version

    # ------------------------------------------------------------------ data
    @property
    def _x(self) -> torch.Tensor:
        return self._store_x[:self._count]

    @property
    def _y(self) -> torch.Tensor:
        return self._store_y[:self._count]

    @property
    def num_data(self) -> int:
        """Number of stored (x, y) pairs."""
        return self._count

    @property
    def is_fitted(self) -> bool:
        """Whether predictions come from a posterior (True) or the prior (False)."""
        return self._cache is not None

    @property
    def train_x(self) -> torch.Tensor:
        """Inputs the current posterior conditions on: (M, n_in)."""
        if self.train_indices is None:
            return self._x[:0]
        return self._x[self.train_indices]

    @property
    def train_y(self) -> torch.Tensor:
        """Targets the current posterior conditions on: (M, n_out)."""
        if self.train_indices is None:
            return self._y[:0]
        return self._y[self.train_indices]

    def add(self, x: ArrayLike, y: ArrayLike) -> None:
        """Append data; ``fit`` must be called for it to affect predictions.

        Args:
            x: (N, n_in) states.
            y: (N, n_out) residuals ``x_dot_hat - f(x) - g(x) u``.
        """
        x_t, y_t = self._checked_rows(x, y)
        end = self._count + x_t.shape[0]
        if end > self._store_x.shape[0]:
            capacity = max(end, 2 * self._store_x.shape[0], 1024)
            self._store_x = self._grown(self._store_x, capacity)
            self._store_y = self._grown(self._store_y, capacity)
        self._store_x[self._count:end] = x_t
        self._store_y[self._count:end] = y_t
        self._count = end

    def _checked_rows(self, x: ArrayLike, y: ArrayLike) -> tuple[torch.Tensor, torch.Tensor]:
        """``x``, ``y`` as tensors of this model's dtype; ValueError naming a bad one."""
        x_t = _as_tensor(x, 'X', self.config.dtype)
        y_t = _as_tensor(y, 'Y', self.config.dtype)
        if x_t.ndim != 2 or x_t.shape[1] != self.n_in:
            raise ValueError(f'X must have shape (N, {self.n_in}), got {tuple(x_t.shape)}')
        if y_t.ndim != 2 or y_t.shape[1] != self.n_out:
            raise ValueError(f'Y must have shape (N, {self.n_out}), got {tuple(y_t.shape)}')
        if x_t.shape[0] != y_t.shape[0]:
            raise ValueError(f'X and Y must have the same number of rows, got '
                             f'{x_t.shape[0]} and {y_t.shape[0]}')
        if not torch.isfinite(x_t).all():
            raise ValueError('X contains non-finite values')
        if not torch.isfinite(y_t).all():
            raise ValueError('Y contains non-finite values')
        return x_t, y_t

    def _grown(self, store: torch.Tensor, capacity: int) -> torch.Tensor:
        bigger = torch.empty(capacity, store.shape[1], dtype=store.dtype)
        bigger[:self._count] = store[:self._count]
        return bigger

    def select_training_subset(self) -> torch.Tensor:
        """Indices of the data ``fit`` trains on: all if N <= cap, else the subset rule.

        Returns:
            (M,) int64 indices, M = min(N, max_train_points), in selection order (any
            prefix is itself a farthest-point / random subset).
        """
        n_data, cap = self.num_data, self.config.max_train_points
        if n_data <= cap:
            return torch.arange(n_data)
        generator = torch.Generator().manual_seed(self.config.seed)
        if self.config.subset_rule == 'random':
            return torch.randperm(n_data, generator=generator)[:cap]
        scale = self._x.std(dim=0).clamp_min(1e-12)
        first = int(torch.randint(n_data, (1,), generator=generator))
        return farthest_point_subset(self._x / scale, cap, first)

    # ------------------------------------------------------------------- fit
    def fit(self) -> None:
        """Fit hyperparameters on the (capped) data set and cache the posterior.

        A no-op before any data was added (predictions stay at the prior).
        """
        if self.num_data == 0:
            return
        self.train_indices = self.select_training_subset()
        n_hyper = self.config.hyperparameter_points
        self._fit_hyperparameters(self.train_x[:n_hyper], self.train_y[:n_hyper])
        self._refresh_cache()

    def _fit_hyperparameters(self, x: torch.Tensor, y: torch.Tensor) -> None:
        """Maximise the marginal likelihood in normalised units, store raw-unit values.

        With ``x_n = (x - m) / c`` and ``y_n = y / r`` (c: column std, r: column RMS), an RBF
        kernel with lengthscale ``l_n`` on ``x_n`` is the kernel with ``l = l_n c`` on ``x``
        (stationary: the shift drops out), and a zero-mean GP on ``y_n`` with signal and noise
        variances ``s_n, n_n`` is the GP on ``y`` with ``s = r^2 s_n, n = r^2 n_n``.
        """
        cfg = self.config
        n_data = x.shape[0]
        x_scale = x.std(dim=0) if n_data > 1 else torch.ones(self.n_in, dtype=x.dtype)
        x_scale = torch.where(x_scale > 1e-12, x_scale, torch.ones_like(x_scale))
        y_scale = y.pow(2).mean(dim=0).sqrt()
        y_scale = torch.where(y_scale > 1e-12, y_scale, torch.ones_like(y_scale))
        x_n = ((x - x.mean(dim=0)) / x_scale).unsqueeze(0).expand(self.n_out, -1, -1)
        y_n = (y / y_scale).T.contiguous()

        batch = torch.Size([self.n_out])
        likelihood = gpytorch.likelihoods.GaussianLikelihood(
            batch_shape=batch,
            noise_prior=gpytorch.priors.GammaPrior(*cfg.noise_prior),
            noise_constraint=gpytorch.constraints.GreaterThan(cfg.min_noise))
        model = _BatchIndependentExactGP(x_n, y_n, likelihood, cfg).to(cfg.dtype)
        likelihood = likelihood.to(cfg.dtype)
        if cfg.warm_start and self.lengthscales is not None:
            assert self.outputscale is not None and self.noise is not None
            lengthscale_n = self.lengthscales / x_scale
            outputscale_n = self.outputscale / y_scale ** 2
            noise_n = (self.noise / y_scale ** 2).clamp_min(2.0 * cfg.min_noise)
        else:
            lengthscale_n = torch.full((self.n_out, self.n_in), cfg.initial_lengthscale,
                                       dtype=cfg.dtype)
            outputscale_n = torch.ones(self.n_out, dtype=cfg.dtype)
            noise_n = torch.full((self.n_out,), 0.1, dtype=cfg.dtype)
        model.covar_module.base_kernel.lengthscale = lengthscale_n.unsqueeze(1)
        model.covar_module.outputscale = outputscale_n
        likelihood.noise = noise_n.unsqueeze(1)

        model.train()
        likelihood.train()
        mll = gpytorch.mlls.ExactMarginalLogLikelihood(likelihood, model)
        optimizer = torch.optim.Adam(model.parameters(), lr=cfg.learning_rate)
        with gpytorch.settings.max_cholesky_size(max(cfg.max_train_points, n_data) + 1):
            for _ in range(cfg.training_iterations):
                optimizer.zero_grad()
                loss = -mll(model(x_n), y_n).sum()
                loss.backward()
                optimizer.step()

        with torch.no_grad():
            lengthscale_n = model.covar_module.base_kernel.lengthscale.reshape(
                self.n_out, self.n_in)
            self.lengthscales = (lengthscale_n * x_scale).clone()
            self.outputscale = (model.covar_module.outputscale.reshape(self.n_out)
                                * y_scale ** 2).clone()
            self.noise = (likelihood.noise.reshape(self.n_out) * y_scale ** 2).clone()

    def set_hyperparameters(self, lengthscales: ArrayLike, outputscale: ArrayLike,
                            noise: ArrayLike) -> None:
        """Set raw-unit hyperparameters and condition on all stored data (capped).

        Args:
            lengthscales: (n_out, n_in), > 0.
            outputscale: (n_out,) signal variances, > 0.
            noise: (n_out,) observation noise variances, > 0.
        """
        dtype = self.config.dtype
        values = {'lengthscales': (_as_tensor(lengthscales, 'lengthscales', dtype),
                                   (self.n_out, self.n_in)),
                  'outputscale': (_as_tensor(outputscale, 'outputscale', dtype),
                                  (self.n_out,)),
                  'noise': (_as_tensor(noise, 'noise', dtype), (self.n_out,))}
        for name, (value, shape) in values.items():
            if tuple(value.shape) != shape:
                raise ValueError(f'{name} must have shape {shape}, got {tuple(value.shape)}')
            if not (value > 0).all():
                raise ValueError(f'{name} must be > 0')
        self.lengthscales = values['lengthscales'][0].clone()
        self.outputscale = values['outputscale'][0].clone()
        self.noise = values['noise'][0].clone()
        if self.num_data == 0:
            self.train_indices = None
            self._cache = None
            return
        self.train_indices = self.select_training_subset()
        self._refresh_cache()

    @property
    def active_outputs(self) -> torch.Tensor:
        """(n_out,) bool: output dimensions with a GP posterior (the others are exactly known,
        see ``GPConfig.exact_output_tol``). All True before the first fit."""
        if self._cache is None:
            return torch.ones(self.n_out, dtype=torch.bool)
        return self._cache['active'].clone()

    def _refresh_cache(self) -> None:
        """Cache per active output dim: scaled inputs, ``L^-T``, ``alpha = (K + nI)^-1 y``, the
        low-rank variance bound's eigenpairs, the neighbour bound's factors, and which bound
        each output uses (module docstring).

        A dimension is active unless every stored residual (all data, not only the capped
        training subset) is within ``exact_output_tol`` of zero.
        """
        assert self.lengthscales is not None and self.outputscale is not None
        assert self.noise is not None
        active = (self._y.abs() > self.config.exact_output_tol).any(dim=0)
        x, y = self.train_x, self.train_y[:, active]
        lengthscales = self.lengthscales[active]
        outputscale, noise = self.outputscale[active], self.noise[active]
        x_scaled = x.unsqueeze(0) / lengthscales.unsqueeze(1)  # (n_active, M, n_in)
        k_train = self._rbf(x_scaled, x_scaled, outputscale)
        eye = torch.eye(x.shape[0], dtype=x.dtype)
        k_noisy = k_train + noise[:, None, None] * eye
        chol = _jittered_cholesky(k_noisy)  # (n_out, M, M)
        chol_inv = torch.linalg.solve_triangular(chol, eye.expand_as(chol), upper=False)
        alpha = torch.cholesky_solve(y.T.unsqueeze(-1), chol).squeeze(-1)  # (n_out, M)
        n_points = x.shape[0]
        # Descending; an eigenvalue of K + nI is >= n (K is PSD): clamp round-off below it.
        # The eigendecomposition is of L L^T, the matrix the exact posterior uses (with the
        # jitter, if the Cholesky needed one).
        k_used = chol @ chol.transpose(-1, -2)
        eigenvalues, eigenvectors = torch.linalg.eigh(k_used)
        eigenvalues = torch.maximum(eigenvalues.flip(-1), noise[:, None])
        ranks = variance_ranks(eigenvalues=eigenvalues, noise=noise,
                               tolerance=self.config.variance_rank_tolerance)
        # Row-vector layout: k^T L^-T is one batched (B, M) x (M, M) product, which is several
        # times faster on CPU than L^-1 k with a (M, 1) right-hand side.
        cache = {'active': active, 'lengthscales': lengthscales,
                 'outputscale': outputscale, 'noise': noise,
                 'x_scaled': x_scaled,
                 'chol_inv_t': chol_inv.transpose(-1, -2).contiguous(), 'alpha': alpha,
                 'eigenvalues': eigenvalues, 'eigenvectors': eigenvectors.flip(-1),
                 'ranks': ranks, 'plans': {}, 'hybrid_rank': torch.full_like(ranks, -1),
                 'hybrid_factor': {}}
        # Built aside and published whole at the end: a failure on the way (a neighbourhood
        # matrix no jitter makes positive definite) leaves the previous posterior in place.
        self._pending = cache
        try:
            outputs = torch.arange(int(active.sum()))
            groups, kept, excess = self._low_rank_groups(outputs)
            cache['plans']['low_rank'] = groups
            cache['low_rank'] = {'ranks': ranks, 'kept': kept, 'excess': excess}
            neighbours = min(self.config.variance_neighbours, n_points)
            if 0 < neighbours < n_points and outputs.numel():
                # k(x_i, x_j) falls with the scaled distance: the nearest are the largest
                # entries; the diagonal (s + n) is every row's largest: x_i comes first.
                cache['neighbour_index'] = torch.topk(k_noisy, neighbours, dim=-1).indices
                cache['k_used'] = k_used
                self._choose_hybrid_ranks()
            hybrid_rank = cache['hybrid_rank']
            cache['plans']['chosen'] = (self._plan(hybrid_rank)
                                        if bool((hybrid_rank >= 0).any()) else groups)
        finally:
            self._pending = None
        self._cache = cache

    @property
    def _work(self) -> dict[str, Any]:
        """The posterior being built by ``_refresh_cache``, else the current one."""
        cache = self._pending if self._pending is not None else self._cache
        assert cache is not None
        return cache

    def _hybrid_factor(self, output: int, rank: int) -> torch.Tensor:
        """(M, m, m) ``L_i^-T`` per training point i, ``L_i L_i^T`` the principal submatrix on
        i's neighbourhood S_i of ``E' = K + nI - U_r diag(mu_r - n) U_r^T`` (module
        docstring), jittered further if it must be, which only raises the variance.
        ``K + nI`` is the cached ``L L^T`` (with the jitter, if the Cholesky needed one).
        """
        c = self._work
        index = c['neighbour_index'][output]  # (M, m)
        sub = c['k_used'][output][index.unsqueeze(-1), index.unsqueeze(-2)]  # (M, m, m)
        if rank:
            # Entries of size s less the kept part: E' >= n I, so the round-off of the
            # difference (eps r s) is far below its smallest eigenvalue unless s / n ~ 1e10.
            vectors = c['eigenvectors'][output][:, :rank][index]  # (M, m, r)
            weights = c['eigenvalues'][output][:rank] - c['noise'][output]
            sub = sub - (vectors * weights) @ vectors.transpose(-1, -2)
        chol = _jittered_cholesky(sub)
        eye = torch.eye(sub.shape[-1], dtype=sub.dtype).expand_as(chol)
        chol_inv = torch.linalg.solve_triangular(chol, eye, upper=False)
        return chol_inv.transpose(-1, -2).contiguous()

    def _choose_hybrid_ranks(self) -> None:
        """Per active output, the smallest rank of ``_HYBRID_RANKS`` (below the low-rank
        bound's own) whose hybrid bound's std is within ``hybrid_std_tolerance`` of the
        exact std on every probe state: stored states, and stored states moved by a quarter
        and a whole lengthscale. Outputs where none is stay on the low-rank bound (-1)."""
        c = self._work
        generator = torch.Generator().manual_seed(self.config.seed)
        rows = self._x[torch.randperm(self.num_data, generator=generator)[:64]]
        shift = c['lengthscales'].min(dim=0).values
        probes = torch.cat([rows] + [
            rows + scale * shift * torch.randn(rows.shape, generator=generator,
                                               dtype=rows.dtype) for scale in (0.25, 1.0)])
        with torch.no_grad():
            exact = self._exact_variance(probes)  # (D, P)
        base = c['outputscale'] + (c['noise'] if self.config.include_noise_in_std else 0.0)
        # The exact std, floored at 1e-6 of the prior's against round-off near the data.
        exact_std = torch.maximum(exact, 1e-12 * base[:, None]).sqrt()
        allowed = 1.0 + self.config.hybrid_std_tolerance
        for output in range(exact.shape[0]):
            one = torch.tensor([output])
            for rank in _HYBRID_RANKS:
                if rank + _HYBRID_COST_COLUMNS >= int(c['ranks'][output]):
                    break
                factor = self._hybrid_factor(output, rank)
                group = self._low_rank_group(one, rank, factor_t=factor[None])
                _, std = self._predict_group(group, probes.numpy())
                ratio = torch.from_numpy(std[:, 0]) / exact_std[output]
                if float(ratio.max()) <= allowed:
                    c['hybrid_rank'][output] = rank
                    c['hybrid_factor'][output] = factor
                    break

    def _plan(self, hybrid_rank: torch.Tensor) -> list[dict[str, Any]]:
        """The numpy groups one prediction runs: the low-rank groups of the outputs with
        ``hybrid_rank`` -1, and one hybrid group per rank of the others."""
        outputs = torch.arange(hybrid_rank.numel())
        groups = self._low_rank_groups(outputs[hybrid_rank < 0])[0]
        for rank in sorted(set(hybrid_rank[hybrid_rank >= 0].tolist())):
            members = outputs[hybrid_rank == rank]
            factor_t = torch.stack([self._work['hybrid_factor'][int(o)] for o in members])
            groups.append(self._low_rank_group(members, rank, factor_t=factor_t))
        return groups

    def _low_rank_groups(self, members: torch.Tensor
                         ) -> tuple[list[dict[str, Any]], torch.Tensor, torch.Tensor]:
        """The low-rank prediction's numpy groups for ``members`` (indices into the active
        outputs), with each active output's kept rank and worst-case excess (zero for the
        others).

        Outputs of similar rank share one batched group at the group's largest rank (extra
        pairs only tighten the bound); an output that needs far more pairs than another (a
        signal weaker than its noise) gets its own group, so that the others do not read its
        columns.
        """
        c = self._work
        eigenvalues, noise, ranks = c['eigenvalues'], c['noise'], c['ranks']
        n_points = eigenvalues.shape[-1]
        kept = torch.zeros_like(ranks)
        excess = torch.zeros_like(noise)
        groups = []
        for local in (_rank_groups(ranks[members]) if members.numel() else []):
            group = members[local]
            rank = int(ranks[group].max())
            if 2 * rank >= n_points:
                # Below rank M the discarded part is a second pass over the r columns: from
                # M / 2 on, every pair (one pass, the exact variance) costs no more.
                rank = n_points
            kept[group] = rank
            if rank < n_points:
                tail = eigenvalues[group, rank]
                excess[group] = variance_excess_ratio(tail=tail - noise[group],
                                                      noise=noise[group])
            groups.append(self._low_rank_group(group, rank))
        return groups, kept, excess

    def _exponent_rows(self, outputs: torch.Tensor) -> np.ndarray:
        """(D, n_in + 2, M): log k(q, x_j) = log s - |q~|^2 / 2 - |x~_j|^2 / 2 + q~ . x~_j
        (~: lengthscale-scaled) is one product of [q~, -|q~|^2 / 2, 1] with these rows
        [x~_j; 1; log s - |x~_j|^2 / 2]."""
        c = self._work
        x_scaled, outputscale = c['x_scaled'][outputs], c['outputscale'][outputs]
        n_active, n_points, n_in = x_scaled.shape
        rows = torch.empty(n_active, n_in + 2, n_points, dtype=x_scaled.dtype)
        rows[:, :n_in] = x_scaled.transpose(-1, -2)
        rows[:, n_in] = 1.0
        rows[:, n_in + 1] = outputscale.log()[:, None] - 0.5 * (x_scaled ** 2).sum(-1)
        return rows.numpy()

    def _group_base(self, outputs: torch.Tensor) -> dict[str, Any]:
        """What every group has: outputs, inverse lengthscales, exponent rows, prior variance."""
        c = self._work
        outputscale = c['outputscale'][outputs]
        base = (outputscale + c['noise'][outputs] if self.config.include_noise_in_std
                else outputscale)
        return {'index': c['active'].nonzero().squeeze(-1)[outputs].numpy(),
                'inv_lengthscales': (1.0 / c['lengthscales'][outputs]).numpy(),
                'exponent_rows': self._exponent_rows(outputs), 'base': base.numpy()[:, None]}

    def _low_rank_group(self, outputs: torch.Tensor, rank: int,
                        factor_t: torch.Tensor | None = None) -> dict[str, Any]:
        """One batched low-rank group of outputs at one rank (see ``_low_rank_groups``);
        with ``factor_t`` (D, M, m, m) from ``_hybrid_factor``, the hybrid bound at it."""
        c = self._work
        eigenvalues = c['eigenvalues'][outputs]
        n_points = eigenvalues.shape[-1]
        # var_r = s - sum_{i<=r} (u_i . k)^2 / mu_i - |k_perp|^2 / mu_{r+1}, k_perp = k minus its
        # projection on the kept u_i, computed as that difference (not |k|^2 - sum (u_i . k)^2,
        # which loses |k|^2 / n * eps to cancellation when n << s). Both subtracted terms are
        # >= 0 and together at most s, so the round-off stays at eps * s.
        tail_weight = (1.0 / eigenvalues[:, rank] if rank < n_points
                       else torch.zeros(outputs.numel(), dtype=eigenvalues.dtype))
        # One (1 + r, M) product gives the mean (row 0) and the r projections u_i . k; stored
        # row by row, so that one query's product reads each row contiguously.
        project = torch.cat([c['alpha'][outputs].unsqueeze(-1),
                             c['eigenvectors'][outputs, :, :rank]], dim=-1).transpose(-1, -2)
        group = {**self._group_base(outputs), 'rank': rank,
                 'full_rank': rank == n_points, 'project_t': project.contiguous().numpy(),
                 'kept_weights': (1.0 / eigenvalues[:, :rank]).numpy(),
                 'tail_weight': tail_weight.numpy()[:, None]}
        if factor_t is not None:
            group['neighbours'] = c['neighbour_index'][outputs].numpy()
            group['factor_t'] = factor_t.numpy()
        return group

    @property
    def variance_bound(self) -> dict[str, Any]:
        """The bound each active output's prediction uses: ``rank`` (n_active,) the rank of
        its hybrid bound, -1 for the low-rank bound (at ``variance_rank``'s ``kept``); and
        ``size``, the neighbourhood size m (0: the hybrid bound is off). Empty before the
        first fit."""
        if self._cache is None:
            return {}
        index = self._cache.get('neighbour_index')
        return {'rank': self._cache['hybrid_rank'].clone(),
                'size': 0 if index is None else int(index.shape[-1])}

    @property
    def variance_rank(self) -> dict[str, Any]:
        """The low-rank variance bound of the current posterior, per active output:
        ``ranks`` the rank its tolerance needs, ``kept`` the rank of its group (>= ranks),
        ``excess`` the worst-case variance excess at the kept rank relative to the signal
        variance; and ``points`` M. Empty before the first fit."""
        if self._cache is None:
            return {}
        low = self._cache['low_rank']
        return {'ranks': low['ranks'].clone(), 'kept': low['kept'].clone(),
                'excess': low['excess'].clone(), 'points': int(self._cache['alpha'].shape[-1])}

    @staticmethod
    def _rbf(a_scaled: torch.Tensor, b_scaled: torch.Tensor,
             outputscale: torch.Tensor) -> torch.Tensor:
        """s_d exp(-|a - b|^2 / 2) on lengthscale-scaled inputs.

        Args:
            a_scaled: (D, A, n_in); b_scaled: (D, B, n_in); outputscale: (D,) the s_d.

        Returns:
            (D, A, B).
        """
        sq_dist = ((a_scaled ** 2).sum(-1, keepdim=True)
                   + (b_scaled ** 2).sum(-1).unsqueeze(-2)
                   - 2.0 * a_scaled @ b_scaled.transpose(-1, -2)).clamp_min(0.0)
        return outputscale[:, None, None] * torch.exp(-0.5 * sq_dist)

    # --------------------------------------------------------------- predict
    def predict(self, x: ArrayLike, *, exact: bool = False,
                bound: Literal['chosen', 'low_rank'] = 'chosen'
                ) -> tuple[torch.Tensor, torch.Tensor]:
        """Posterior mean and std of the disturbance.

        Args:
            x: (B, n_in) query states (or (n_in,) for one state).
            exact: the exact variance (one M x M factor per output) instead of a bound, which
                is never below it (module docstring). The mean is the same.
            bound: which bound, if not ``exact``: each output's choice at the last refit
                (``variance_bound``), or the low-rank bound for every output.

        Returns:
            mean: (B, n_out); std: (B, n_out). Before any fit: zeros and ``prior_std``.
        """
        _check_bound(bound)
        x_t = _as_tensor(x, 'x', self.config.dtype)
        if x_t.ndim == 1:
            x_t = x_t.unsqueeze(0)
        if x_t.ndim != 2 or x_t.shape[1] != self.n_in:
            raise ValueError(f'x must have shape (B, {self.n_in}), got {tuple(x_t.shape)}')
        n_query = x_t.shape[0]
        if self._cache is None:
            mean = torch.zeros(n_query, self.n_out, dtype=x_t.dtype)
            return mean, torch.full_like(mean, self.config.prior_std)
        if not exact:
            mean_np, std_np = self._predict_bound(x_t.numpy(), self._cache['plans'][bound])
            return torch.from_numpy(mean_np), torch.from_numpy(std_np)
        c = self._cache
        mean = torch.zeros(n_query, self.n_out, dtype=x_t.dtype)
        std = torch.zeros(n_query, self.n_out, dtype=x_t.dtype)
        if not bool(c['active'].any()):
            return mean, std
        with torch.no_grad():
            mean_a, var = self._exact_variance(x_t, with_mean=True)
            active = c['active']
            if bool(active.all()):
                return mean_a.T.contiguous(), var.clamp_min(0.0).sqrt().T.contiguous()
            mean[:, active] = mean_a.T
            std[:, active] = var.clamp_min(0.0).sqrt().T
        return mean, std

    def _exact_variance(self, x: torch.Tensor, *, with_mean: bool = False) -> Any:
        """Exact posterior variance (D_active, B) at x (B, n_in); with ``with_mean``, the
        pair (mean, variance)."""
        c = self._work
        q_scaled = x.unsqueeze(0) / c['lengthscales'].unsqueeze(1)  # (D, B, n_in)
        k_cross = self._rbf(q_scaled, c['x_scaled'], c['outputscale'])  # (D, B, M)
        v = k_cross @ c['chol_inv_t']  # (D, B, M): rows of (L^-1 k)^T
        var = c['outputscale'].unsqueeze(-1) - (v ** 2).sum(-1)
        if self.config.include_noise_in_std:
            var = var + c['noise'].unsqueeze(-1)
        if not with_mean:
            return var
        return (k_cross * c['alpha'].unsqueeze(1)).sum(-1), var

    def predict_state(self, state: np.ndarray, *,
                      bound: Literal['chosen', 'low_rank'] = 'chosen'
                      ) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`predict` (each output's chosen bound) at ONE state, in numpy: the per-step
        path.

        Args:
            state: (n_in,) float64.
            bound: as :meth:`predict`'s.

        Returns:
            mean: (n_out,); std: (n_out,), equal to ``predict(state)`` to round-off.
        """
        x = np.asarray(state, dtype=np.float64)
        if x.shape != (self.n_in,):
            raise ValueError(f'state must have shape ({self.n_in},), got {x.shape}')
        if self._cache is None:
            return np.zeros(self.n_out), np.full(self.n_out, self.config.prior_std)
        _check_bound(bound)
        mean, std = self._predict_bound(x[None, :], self._cache['plans'][bound])
        return mean[0], std[0]

    def _predict_bound(self, x: np.ndarray, plan: list[dict[str, Any]]
                       ) -> tuple[np.ndarray, np.ndarray]:
        """Mean and std bound, x (B, n_in) float64 -> two (B, n_out) arrays."""
        if len(plan) == 1 and plan[0]['index'].size == self.n_out:
            return self._predict_group(plan[0], x)
        mean = np.zeros((x.shape[0], self.n_out))
        std = np.zeros((x.shape[0], self.n_out))
        for group in plan:
            mean_g, std_g = self._predict_group(group, x)
            mean[:, group['index']] = mean_g
            std[:, group['index']] = std_g
        return mean, std

    def _predict_group(self, group: dict[str, Any], x: np.ndarray
                       ) -> tuple[np.ndarray, np.ndarray]:
        """One group's mean and std bound: two (B, D_group) arrays."""
        n_in = self.n_in
        query = np.empty((group['index'].size, x.shape[0], n_in + 2))
        q_scaled = np.multiply(x[None, :, :], group['inv_lengthscales'][:, None, :],
                               out=query[:, :, :n_in])  # (D, B, n_in)
        query[:, :, n_in] = -0.5 * np.einsum('dbi,dbi->db', q_scaled, q_scaled)
        query[:, :, n_in + 1] = 1.0
        # No clamp of the exponent at 0 (the squared distance's round-off): k may exceed s
        # by a few ulps, which moves the variance by round-off only.
        k_cross = np.exp(query @ group['exponent_rows'])  # (D, B, M)
        hybrid = 'factor_t' in group
        if hybrid:
            nearest = k_cross.argmax(axis=-1)  # (D, B): the nearest training point
        project_t = group['project_t']
        # (D, B, 1 + r): mean, then u_i . k
        projected = (project_t @ k_cross.transpose(0, 2, 1)).transpose(0, 2, 1)
        kept = projected[:, :, 1:]
        var = group['base'] - np.einsum('dbr,dr->db', kept * kept, group['kept_weights'])
        if not group['full_rank']:
            # k_perp = k - U_r (U_r^T k), on the same (by now cached) columns.
            if group['rank']:
                k_cross -= kept @ project_t[:, 1:, :]
            tail = np.einsum('dbm,dbm->db', k_cross, k_cross) * group['tail_weight']
            if hybrid:
                # q^T E'_SS^-1 q on the nearest training point's neighbourhood S, q = k_perp[S].
                outputs = np.arange(nearest.shape[0])[:, None]
                near = np.take_along_axis(k_cross, group['neighbours'][outputs, nearest], -1)
                v = (near[:, :, None, :] @ group['factor_t'][outputs, nearest])[:, :, 0, :]
                np.maximum(tail, np.einsum('dbm,dbm->db', v, v), out=tail)
            var -= tail
        std = np.sqrt(np.maximum(var, 0.0, out=var), out=var)
        return projected[:, :, 0].T.copy(), std.T.copy()

    def bounds(self, x: ArrayLike, k_c: float) -> tuple[torch.Tensor, torch.Tensor]:
        """Disturbance box of eq. (disturb_estimate): ``mean -/+ k_c std``.

        Args:
            x: (B, n_in) query states.
            k_c: confidence multiplier, >= 0 (2 gives ~95 % per dimension).

        Returns:
            lower: (B, n_out); upper: (B, n_out).
        """
        if not (k_c >= 0 and math.isfinite(k_c)):
            raise ValueError(f'k_c must be finite and >= 0, got {k_c}')
        mean, std = self.predict(x)
        return mean - k_c * std, mean + k_c * std

    # ------------------------------------------------------------ checkpoint
    def state_dict(self) -> dict[str, Any]:
        """Data, chosen training subset and raw-unit hyperparameters (tensors only)."""
        return {
            'n_in': self.n_in, 'n_out': self.n_out,
            'x': self._x.clone(), 'y': self._y.clone(),
            'train_indices': None if self.train_indices is None else self.train_indices.clone(),
            'lengthscales': None if self.lengthscales is None else self.lengthscales.clone(),
            'outputscale': None if self.outputscale is None else self.outputscale.clone(),
            'noise': None if self.noise is None else self.noise.clone(),
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore a ``state_dict``; the posterior is rebuilt without refitting."""
        if state['n_in'] != self.n_in or state['n_out'] != self.n_out:
            raise ValueError(f"state_dict is for n_in={state['n_in']}, n_out={state['n_out']}"
                             f', this model has n_in={self.n_in}, n_out={self.n_out}')
        dtype = self.config.dtype
        self._store_x = state['x'].to(dtype).clone()
        self._store_y = state['y'].to(dtype).clone()
        self._count = int(self._store_x.shape[0])
        self._cache = None
        self.train_indices = None
        self.lengthscales = self.outputscale = self.noise = None
        if state['lengthscales'] is not None:
            self.lengthscales = state['lengthscales'].to(dtype).clone()
            self.outputscale = state['outputscale'].to(dtype).clone()
            self.noise = state['noise'].to(dtype).clone()
            if state['train_indices'] is not None:
                self.train_indices = state['train_indices'].clone()
                self._refresh_cache()
