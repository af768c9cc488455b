"""Gaussian-process model of the unknown disturbance (paper: "Disturbance Estimation").

One independent exact GP (zero mean, ARD RBF kernel) per output dimension of the nominal
model's residuals y = x_dot_hat - f(x) - g(x) u, fitted with GPyTorch and predicted in closed
form from cached factors; the disturbance box of eq. (disturb_estimate) is
``mean +/- k_c std`` (``bounds``). ``predict`` evaluates a variance bound chosen at the refit,
never below the exact variance; outputs the nominal model predicts exactly get no posterior;
the training set is subsampled so that fit and predict cost stay bounded as data grows.

Design notes: docs/DESIGN.md#the-gp-model; the variance bounds: docs/GP_BOUNDS.md
"""
from __future__ import annotations

from dataclasses import dataclass
import math
from typing import Any, Literal

import gpytorch
import numpy as np
import torch

from rcbf_ros.learning import gp_bounds
from rcbf_ros.learning.gp_bounds import (  # noqa: F401  (public API of this module)
    jittered_cholesky,
    variance_excess_ratio,
    variance_ranks,
)

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
    """Worst-case excess of the low-rank variance bound over the exact variance, relative to
    the output's signal variance (``gp_bounds``); it never predicts less than the exact
    variance. 0: keep every eigenpair (the exact variance, to round-off, at the exact cost)."""
    variance_neighbours: int = 32
    """Neighbourhood size m of the hybrid variance bound (``gp_bounds``), one of the bounds
    a refit chooses from. 0 (or m >= M): no hybrid bound."""
    bound_std_tolerance: float = 0.01
    """Largest relative excess of the projection or hybrid bound's std over the exact std, on
    every probe state of a refit, for an output to use it (``gp_bounds``, "The choice"); a
    tightness criterion only, as every bound is never below the exact variance."""
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
        if not self.bound_std_tolerance >= 0:
            raise ValueError(
                f'bound_std_tolerance must be >= 0, got {self.bound_std_tolerance}')


def _check_bound(bound: str) -> None:
    """Refuse a ``bound`` argument of ``predict``/``predict_state`` that names no bound."""
    if bound not in ('chosen', 'low_rank'):
        raise ValueError(f"bound must be 'chosen' or 'low_rank', got {bound!r}")


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
    is largest (the first such point on a tie).

    Each pass over the N points runs column by column, in numpy, on preallocated rows: the
    squared distance summed over the columns in order, as ``((points - c) ** 2).sum(dim=1)``
    sums them, without its (N, n_in) temporaries. At the N of a long run (200,000 points of
    up to 10 columns), that keeps the pass in cache and takes a refit's selection from about
    a minute to a few seconds.

    Args:
        points: (N, n_in).
        count: number of points to choose, <= N.
        first: index of the first chosen point.

    Returns:
        (count,) int64 indices into ``points``, in the order chosen.
    """
    n_points = points.shape[0]
    if count > n_points:  # pragma: no cover - guarded by the caller
        raise ValueError('count exceeds the number of points')
    columns = points.detach().T.contiguous().numpy()  # (n_in, N)
    chosen = np.empty(count, dtype=np.int64)
    chosen[0] = first
    min_sq_dist, sq_dist, term = np.empty((3, n_points), dtype=columns.dtype)

    def distances_to(index: int, out: np.ndarray) -> np.ndarray:
        np.subtract(columns[0], columns[0, index], out=out)
        np.square(out, out=out)
        for column in columns[1:]:
            np.subtract(column, column[index], out=term)
            np.square(term, out=term)
            out += term
        return out

    distances_to(first, min_sq_dist)
    for i in range(1, count):
        nxt = int(np.argmax(min_sq_dist))
        chosen[i] = nxt
        np.minimum(min_sq_dist, distances_to(nxt, sq_dist), out=min_sq_dist)
    return torch.from_numpy(chosen)


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
        eigenpairs of ``K + nI``, the neighbourhoods, each output's chosen variance bound and the
        numpy groups ``predict`` runs (``gp_bounds``).

        A dimension is active unless every stored residual (all data, not only the capped
        training subset) is within ``exact_output_tol`` of zero. The posterior is built aside
        and published whole at the end: a failure on the way (a neighbourhood matrix no jitter
        makes positive definite) leaves the previous one in place.
        """
        assert self.lengthscales is not None and self.outputscale is not None
        assert self.noise is not None
        cfg = self.config
        active = (self._y.abs() > cfg.exact_output_tol).any(dim=0)
        x, y = self.train_x, self.train_y[:, active]
        lengthscales = self.lengthscales[active]
        outputscale, noise = self.outputscale[active], self.noise[active]
        x_scaled = x.unsqueeze(0) / lengthscales.unsqueeze(1)  # (n_active, M, n_in)
        k_train = gp_bounds.rbf(x_scaled, x_scaled, outputscale)
        eye = torch.eye(x.shape[0], dtype=x.dtype)
        k_noisy = k_train + noise[:, None, None] * eye
        chol = jittered_cholesky(k_noisy)  # (n_out, M, M)
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
                               tolerance=cfg.variance_rank_tolerance)
        # Row-vector layout: k^T L^-T is one batched (B, M) x (M, M) product, which is several
        # times faster on CPU than L^-1 k with a (M, 1) right-hand side.
        cache: dict[str, Any] = {
            'active': active, 'lengthscales': lengthscales, 'outputscale': outputscale,
            'noise': noise, 'x_scaled': x_scaled, 'points': x,
            'chol_inv_t': chol_inv.transpose(-1, -2).contiguous(), 'alpha': alpha,
            'eigenvalues': eigenvalues, 'eigenvectors': eigenvectors.flip(-1), 'ranks': ranks,
            'plans': {}}
        include_noise = cfg.include_noise_in_std
        outputs = torch.arange(int(active.sum()))
        parts, kept, excess = gp_bounds.low_rank_parts(cache, outputs)
        cache['plans']['low_rank'] = gp_bounds.make_plan(cache, parts, include_noise)
        cache['low_rank'] = {'ranks': ranks, 'kept': kept, 'excess': excess}
        neighbours = min(cfg.variance_neighbours, n_points)
        if 0 < neighbours < n_points and outputs.numel():
            # k(x_i, x_j) falls with the scaled distance: the nearest are the largest
            # entries; the diagonal (s + n) is every row's largest: x_i comes first.
            cache['neighbour_index'] = torch.topk(k_noisy, neighbours, dim=-1).indices
            cache['k_used'] = k_used
        probes = self._probe_states(lengthscales) if outputs.numel() else x[:0]
        gp_bounds.choose_bounds(cache, probes, include_noise=include_noise,
                                tolerance=cfg.bound_std_tolerance)
        cache['plans']['chosen'] = (
            cache['plans']['low_rank'] if all(kind == 'low_rank' for kind in cache['bound_kind'])
            else gp_bounds.make_plan(cache, gp_bounds.chosen_parts(cache), include_noise))
        self._cache = cache

    def _probe_states(self, lengthscales: torch.Tensor) -> torch.Tensor:
        """The states a refit checks the chosen bounds' tightness on: 64 stored states, and
        the same moved by a quarter and a whole (smallest) lengthscale in random directions."""
        generator = torch.Generator().manual_seed(self.config.seed)
        rows = self._x[torch.randperm(self.num_data, generator=generator)[:64]]
        shift = lengthscales.min(dim=0).values
        return torch.cat([rows] + [
            rows + scale * shift * torch.randn(rows.shape, generator=generator,
                                               dtype=rows.dtype) for scale in (0.25, 1.0)])

    @property
    def variance_bound(self) -> dict[str, Any]:
        """The bound each active output's prediction uses (``gp_bounds``, "The choice"):
        ``bound`` its name ('projection', 'shared_projection', 'low_rank' or 'hybrid') and
        ``rank`` (n_active,) its rank; ``size``, the hybrid bound's neighbourhood size m (0:
        the hybrid bound is off); ``shared``, the size R of the shared projection's basis (0:
        none). Empty before the first fit."""
        if self._cache is None:
            return {}
        index = self._cache.get('neighbour_index')
        shared = self._cache.get('shared')
        return {'bound': tuple(self._cache['bound_kind']),
                'rank': self._cache['bound_rank'].clone(),
                'size': 0 if index is None else int(index.shape[-1]),
                'shared': 0 if shared is None else int(shared['basis'].shape[-1])}

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
            k_cross = gp_bounds.cross_kernel(c, x_t)  # (D, B, M)
            mean_a = (k_cross * c['alpha'].unsqueeze(1)).sum(-1)
            var = gp_bounds.exact_variance(c, k_cross, self.config.include_noise_in_std)
            active = c['active']
            if bool(active.all()):
                return mean_a.T.contiguous(), var.clamp_min(0.0).sqrt().T.contiguous()
            mean[:, active] = mean_a.T
            std[:, active] = var.clamp_min(0.0).sqrt().T
        return mean, std

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
        mean, std = self._predict_bound(x[None, :], self._cache['plans'][bound])[:, 0]
        return mean, std

    def _predict_bound(self, x: np.ndarray, plan: dict[str, Any]) -> np.ndarray:
        """Mean and std bound at x (B, n_in) float64: (2, B, n_out), [0] the mean, each
        (B, n_out) contiguous."""
        result = gp_bounds.predict_plan(plan, x).transpose(2, 1, 0)  # (2, B, D_active + 1)
        return result[:, :, :-1].copy() if plan['identity'] else result.take(plan['take'], 2)

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
