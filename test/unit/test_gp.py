"""DisturbanceGP: equal to GPyTorch's exact posterior, recovers a known disturbance."""
from __future__ import annotations

import math

import gpytorch
from hypothesis import given, settings
from hypothesis import strategies as st
import pytest
import torch

from rcbf_ros.learning.gp import DisturbanceGP, farthest_point_subset, GPConfig

DTYPE = torch.float64
HALF_WIDTH = torch.tensor([3.0, 3.0, math.pi], dtype=DTYPE)  # unicycle arena and heading


def unicycle_slope_disturbance(states: torch.Tensor) -> torch.Tensor:
    """d(x) = g(x) u_d, u_d = -0.1 cos(theta) [1, 0] (ENVIRONMENTS.md, Unicycle): (N, 3)."""
    theta = states[:, 2]
    return torch.stack([-0.1 * torch.cos(theta) ** 2,
                        -0.1 * torch.cos(theta) * torch.sin(theta),
                        torch.zeros_like(theta)], dim=1)


def uniform_states(count: int, generator: torch.Generator) -> torch.Tensor:
    return (2.0 * torch.rand(count, 3, generator=generator, dtype=DTYPE) - 1.0) * HALF_WIDTH


class _ReferenceExactGP(gpytorch.models.ExactGP):
    """A plain single-output GPyTorch model: zero mean, scaled ARD RBF (the reference)."""

    def __init__(self, x, y, likelihood):
        super().__init__(x, y, likelihood)
        self.mean_module = gpytorch.means.ZeroMean()
        self.covar_module = gpytorch.kernels.ScaleKernel(
            gpytorch.kernels.RBFKernel(ard_num_dims=x.shape[1]))

    def forward(self, x):
        return gpytorch.distributions.MultivariateNormal(self.mean_module(x),
                                                         self.covar_module(x))


def gpytorch_posterior(gp: DisturbanceGP, queries: torch.Tensor, dim: int, with_noise: bool):
    likelihood = gpytorch.likelihoods.GaussianLikelihood(
        noise_constraint=gpytorch.constraints.GreaterThan(1e-12)).to(DTYPE)
    model = _ReferenceExactGP(gp.train_x, gp.train_y[:, dim], likelihood).to(DTYPE)
    model.covar_module.base_kernel.lengthscale = gp.lengthscales[dim].reshape(1, -1)
    model.covar_module.outputscale = gp.outputscale[dim]
    likelihood.noise = gp.noise[dim].reshape(1)
    model.eval()
    likelihood.eval()
    with torch.no_grad(), gpytorch.settings.fast_pred_var(False), \
            gpytorch.settings.max_cholesky_size(10_000):
        latent = model(queries)
        dist = likelihood(latent) if with_noise else latent
        return dist.mean, dist.variance.sqrt()


@pytest.fixture(scope='module')
def fitted_slope_gp() -> DisturbanceGP:
    generator = torch.Generator().manual_seed(0)
    states = uniform_states(600, generator)
    residuals = unicycle_slope_disturbance(states) + 0.01 * torch.randn(
        600, 3, generator=generator, dtype=DTYPE)
    gp = DisturbanceGP(3, 3, GPConfig(max_train_points=400))
    gp.add(states, residuals)
    gp.fit()
    return gp


@pytest.mark.parametrize('with_noise', [False, True])
def test_predictions_equal_gpytorch_exact_posterior(fitted_slope_gp, with_noise):
    base = fitted_slope_gp
    # The low-rank bound on every output (within 1e-4 s of the exact variance), and the
    # exact variance.
    gp = DisturbanceGP(3, 3, GPConfig(max_train_points=400, include_noise_in_std=with_noise,
                                      variance_neighbours=0))
    gp.load_state_dict(base.state_dict())
    queries = uniform_states(50, torch.Generator().manual_seed(1))
    assert gp.train_x.shape == (400, 3)
    for mean, std in (gp.predict(queries, bound='low_rank'), gp.predict(queries, exact=True)):
        for dim in range(3):
            ref_mean, ref_std = gpytorch_posterior(gp, queries, dim, with_noise)
            torch.testing.assert_close(mean[:, dim], ref_mean, atol=1e-6, rtol=0)
            torch.testing.assert_close(std[:, dim], ref_std, atol=1e-6, rtol=0)


@pytest.mark.parametrize('with_noise', [False, True])
def test_the_default_bound_contains_the_gpytorch_posterior_box(fitted_slope_gp, with_noise):
    gp = DisturbanceGP(3, 3, GPConfig(max_train_points=400, include_noise_in_std=with_noise))
    gp.load_state_dict(fitted_slope_gp.state_dict())
    queries = uniform_states(50, torch.Generator().manual_seed(1))
    mean, std = gp.predict(queries)
    for dim in range(3):
        ref_mean, ref_std = gpytorch_posterior(gp, queries, dim, with_noise)
        torch.testing.assert_close(mean[:, dim], ref_mean, atol=1e-6, rtol=0)
        assert (std[:, dim] >= ref_std - 1e-6).all()
        # The hybrid bound's tolerance holds on the refit's probe states; these are others.
        assert (std[:, dim] <= 1.05 * ref_std + 1e-6).all()


def test_recovers_unicycle_slope_with_calibrated_bounds(fitted_slope_gp):
    gp = fitted_slope_gp
    held_out = uniform_states(1000, torch.Generator().manual_seed(2))
    truth = unicycle_slope_disturbance(held_out)
    lower, upper = gp.bounds(held_out, k_c=2.0)
    # Each GP's +/- 2 sigma claim is marginal, per dimension (eq. disturb_estimate), so
    # coverage is checked per dimension (the joint box over 3 dims is a union bound away).
    inside = ((truth >= lower) & (truth <= upper)).double().mean(dim=0)
    assert (inside >= 0.95).all(), inside
    mean, std = gp.predict(held_out)
    rmse = (mean - truth).pow(2).mean().sqrt()
    assert rmse < 0.01  # the disturbance amplitude is 0.1, observation noise std 0.01
    # The bounds are informative, not a trivially wide box: well below the amplitude.
    assert std.max() < 0.02
    # Not the near-constant GP of a huge lengthscale: heading matters.
    assert gp.lengthscales[0, 2] < 3.0


def test_prior_before_data():
    gp = DisturbanceGP(3, 2, GPConfig(prior_std=0.7))
    gp.fit()  # no data: stays at the prior
    mean, std = gp.predict(torch.zeros(4, 3, dtype=DTYPE))
    assert torch.equal(mean, torch.zeros(4, 2, dtype=DTYPE))
    assert torch.equal(std, torch.full((4, 2), 0.7, dtype=DTYPE))
    lower, upper = gp.bounds(torch.zeros(4, 3, dtype=DTYPE), 2.0)
    assert torch.equal(upper, torch.full((4, 2), 1.4, dtype=DTYPE))
    assert torch.equal(lower, -upper)


def test_training_set_is_capped_by_farthest_point_rule():
    generator = torch.Generator().manual_seed(3)
    states = uniform_states(900, generator)
    gp = DisturbanceGP(3, 3, GPConfig(max_train_points=64, hyperparameter_points=32,
                                      training_iterations=5, seed=4))
    gp.add(states[:500], unicycle_slope_disturbance(states[:500]))
    gp.add(states[500:], unicycle_slope_disturbance(states[500:]))
    assert gp.num_data == 900
    gp.fit()
    assert gp.train_x.shape == (64, 3)
    assert len(set(gp.train_indices.tolist())) == 64
    # Farthest-point property: each chosen point is the farthest from those chosen before it.
    scaled = states / states.std(dim=0)
    chosen = gp.train_indices
    for i in (1, 10, 63):
        dist_to_chosen = torch.cdist(scaled, scaled[chosen[:i]]).min(dim=1).values
        assert dist_to_chosen[chosen[i]] == pytest.approx(float(dist_to_chosen.max()))
    # Same seed => same subset.
    assert torch.equal(chosen, gp.select_training_subset())


def test_random_subset_rule_is_seeded():
    states = uniform_states(300, torch.Generator().manual_seed(5))
    picks = []
    for seed in (7, 7, 8):
        gp = DisturbanceGP(3, 3, GPConfig(max_train_points=50, subset_rule='random', seed=seed))
        gp.add(states, unicycle_slope_disturbance(states))
        picks.append(gp.select_training_subset())
    assert torch.equal(picks[0], picks[1])
    assert not torch.equal(picks[0], picks[2])


def test_farthest_point_subset_small_example():
    points = torch.tensor([[0.0], [1.0], [10.0], [4.0]])
    assert farthest_point_subset(points, 3, first=0).tolist() == [0, 2, 3]


def _farthest_point_by_definition(points: torch.Tensor, count: int, first: int) -> list[int]:
    """Greedy farthest-point sampling written as its definition: each pick the first point
    of largest squared distance to the chosen set, distances summed over the columns in
    order."""
    chosen = [first]
    best = ((points - points[first]) ** 2).sum(dim=1)
    for _ in range(1, count):
        chosen.append(int(torch.argmax(best)))
        best = torch.minimum(best, ((points - points[chosen[-1]]) ** 2).sum(dim=1))
    return chosen


@settings(max_examples=60, deadline=None)
@given(rows=st.integers(1, 300), columns=st.integers(1, 10), seed=st.integers(0, 2 ** 16),
       integer=st.booleans(), share=st.floats(0.05, 1.0), dtype=st.sampled_from(
           [torch.float64, torch.float32]))
def test_farthest_point_subset_picks_as_its_definition(rows, columns, seed, integer, share,
                                                       dtype):
    """The column-wise pass picks the same points in the same order as the definition, on
    spread data and on integer grids full of ties and duplicate points (a run's repeated
    states), in float64 and float32."""
    generator = torch.Generator().manual_seed(seed)
    points = torch.randn(rows, columns, generator=generator, dtype=torch.float64)
    if integer:
        points = torch.round(points * 2)
    points = points.to(dtype)
    count = max(1, int(share * rows))
    first = int(torch.randint(rows, (1,), generator=generator))
    assert farthest_point_subset(points, count, first).tolist() == \
        _farthest_point_by_definition(points, count, first)


def test_state_dict_round_trip_restores_posterior_without_refit(fitted_slope_gp):
    restored = DisturbanceGP(3, 3, GPConfig(max_train_points=400, training_iterations=0))
    restored.load_state_dict(fitted_slope_gp.state_dict())
    queries = uniform_states(20, torch.Generator().manual_seed(6))
    for a, b in zip(restored.predict(queries), fitted_slope_gp.predict(queries)):
        assert torch.equal(a, b)
    with pytest.raises(ValueError, match='n_in'):
        DisturbanceGP(2, 3).load_state_dict(fitted_slope_gp.state_dict())


def test_version_changes_with_the_posterior_and_not_with_added_data():
    """Callers memoise predictions per version (the replay buffer's memo for the losses)."""
    gp = DisturbanceGP(3, 3, GPConfig(max_train_points=50, training_iterations=2))
    generator = torch.Generator().manual_seed(3)
    states = uniform_states(80, generator)
    versions = [gp.version]
    gp.add(states[:60], unicycle_slope_disturbance(states[:60]))
    versions.append(gp.version)
    gp.fit()
    versions.append(gp.version)
    queries = uniform_states(5, generator)
    before = gp.predict(queries)
    gp.add(states[60:], unicycle_slope_disturbance(states[60:]))
    versions.append(gp.version)
    for a, b in zip(gp.predict(queries), before):  # data alone leaves the predictions
        assert torch.equal(a, b)
    gp.fit()
    versions.append(gp.version)
    restored = DisturbanceGP(3, 3, GPConfig(max_train_points=50))
    start = restored.version
    restored.load_state_dict(gp.state_dict())
    assert versions[0] == versions[1] < versions[2] == versions[3] < versions[4]
    assert restored.version != start


def test_rows_added_one_at_a_time_equal_one_batch_across_storage_growth():
    """The training loop adds one row per step; the stored data (past the storage's first
    growths) and the fitted posterior must equal adding the same rows at once."""
    generator = torch.Generator().manual_seed(7)
    states = uniform_states(2500, generator)
    residuals = unicycle_slope_disturbance(states)
    config = GPConfig(max_train_points=200, training_iterations=5)
    batch, stepwise = DisturbanceGP(3, 3, config), DisturbanceGP(3, 3, config)
    batch.add(states, residuals)
    for i in range(len(states)):
        stepwise.add(states[i:i + 1], residuals[i:i + 1])
        if i == 1499:  # a state_dict taken mid-way holds exactly the rows so far
            assert torch.equal(stepwise.state_dict()['x'], states[:1500])
    assert stepwise.num_data == batch.num_data == 2500
    for key in ('x', 'y'):
        assert torch.equal(stepwise.state_dict()[key], batch.state_dict()[key])
    batch.fit()
    stepwise.fit()
    queries = uniform_states(10, torch.Generator().manual_seed(8))
    for a, b in zip(stepwise.predict(queries), batch.predict(queries)):
        assert torch.equal(a, b)
    restored = DisturbanceGP(3, 3, config)
    restored.load_state_dict(stepwise.state_dict())
    restored.add(states[:3], residuals[:3])  # adding after a restore grows the storage
    assert restored.num_data == 2503
    assert torch.equal(restored.state_dict()['x'][2500:], states[:3])


def test_set_hyperparameters_conditions_on_data():
    states = uniform_states(30, torch.Generator().manual_seed(7))
    gp = DisturbanceGP(3, 1)
    gp.add(states, unicycle_slope_disturbance(states)[:, :1])
    gp.set_hyperparameters(torch.ones(1, 3), torch.tensor([0.01]), torch.tensor([1e-6]))
    # Almost noise-free: the posterior mean interpolates the data.
    mean, std = gp.predict(states)
    torch.testing.assert_close(mean, unicycle_slope_disturbance(states)[:, :1],
                               atol=1e-4, rtol=0)
    with pytest.raises(ValueError, match='noise'):
        gp.set_hyperparameters(torch.ones(1, 3), torch.tensor([0.01]), torch.tensor([0.0]))


@pytest.mark.parametrize(('x', 'y', 'field'), [
    (torch.zeros(5, 2), torch.zeros(5, 3), 'X'),
    (torch.zeros(5, 3), torch.zeros(5, 1), 'Y'),
    (torch.zeros(5, 3), torch.zeros(4, 3), 'same number of rows'),
    (torch.full((5, 3), float('nan')), torch.zeros(5, 3), 'X'),
])
def test_bad_data_is_rejected_naming_the_field(x, y, field):
    with pytest.raises(ValueError, match=field):
        DisturbanceGP(3, 3).add(x, y)


def test_bad_query_and_config_are_rejected():
    with pytest.raises(ValueError, match='x must have shape'):
        DisturbanceGP(3, 3).predict(torch.zeros(2, 4))
    with pytest.raises(ValueError, match='k_c'):
        DisturbanceGP(3, 3).bounds(torch.zeros(2, 3), -1.0)
    with pytest.raises(ValueError, match='max_train_points'):
        GPConfig(max_train_points=0)
    with pytest.raises(ValueError, match='subset_rule'):
        GPConfig(subset_rule='nearest')


def test_warm_start_resumes_from_previous_hyperparameters():
    states = uniform_states(400, torch.Generator().manual_seed(8))
    residuals = unicycle_slope_disturbance(states)
    gp = DisturbanceGP(3, 3, GPConfig(training_iterations=10))
    gp.add(states[:200], residuals[:200])
    gp.fit()
    previous = (gp.lengthscales, gp.outputscale, gp.noise)
    # Zero optimisation steps on more data: the warm start alone must reproduce the previous
    # raw-unit hyperparameters although the normalisation changed with the data.
    resumed = DisturbanceGP(3, 3, GPConfig(training_iterations=0))
    resumed.load_state_dict(gp.state_dict())
    resumed.add(states[200:], residuals[200:])
    resumed.fit()
    for before, after in zip(previous, (resumed.lengthscales, resumed.outputscale,
                                        resumed.noise)):
        torch.testing.assert_close(after, before, rtol=1e-10, atol=0)
    assert resumed.train_x.shape[0] == 400


def test_exactly_known_outputs_get_zero_std_and_leave_the_others_unchanged():
    # Like a position row of Car Following: the nominal model predicts dimension 2 to rounding
    # error, so its residuals are ~1e-13; the other two carry the slope disturbance.
    generator = torch.Generator().manual_seed(3)
    states = uniform_states(300, generator)
    residuals = unicycle_slope_disturbance(states) + 0.01 * torch.randn(
        300, 3, generator=generator, dtype=DTYPE)
    residuals[:, 2] = 1e-13 * torch.randn(300, generator=generator, dtype=DTYPE)
    hyper = (torch.tensor([[1.0, 1.5, 0.8], [1.2, 0.9, 1.1], [1.0, 1.0, 1.0]], dtype=DTYPE),
             torch.tensor([0.01, 0.02, 1e-8], dtype=DTYPE),
             torch.tensor([1e-4, 2e-4, 1e-6], dtype=DTYPE))
    skipping = DisturbanceGP(3, 3)
    every = DisturbanceGP(3, 3, GPConfig(exact_output_tol=0.0))
    for gp in (skipping, every):
        gp.add(states, residuals)
        gp.set_hyperparameters(*hyper)
    assert skipping.active_outputs.tolist() == [True, True, False]
    assert every.active_outputs.tolist() == [True, True, True]
    queries = uniform_states(40, torch.Generator().manual_seed(4))
    mean, std = skipping.predict(queries)
    ref_mean, ref_std = every.predict(queries)
    torch.testing.assert_close(mean[:, :2], ref_mean[:, :2], atol=1e-12, rtol=0)
    torch.testing.assert_close(std[:, :2], ref_std[:, :2], atol=1e-12, rtol=0)
    assert torch.equal(mean[:, 2], torch.zeros(40, dtype=DTYPE))
    assert torch.equal(std[:, 2], torch.zeros(40, dtype=DTYPE))
    # The full GP on that dimension says the same to within its tiny prior std.
    assert ref_std[:, 2].max() <= 1e-4 and ref_mean[:, 2].abs().max() <= 1e-9
    # One residual beyond the tolerance, anywhere in the data, makes it a GP output again.
    skipping.add(states[:1], torch.tensor([[0.0, 0.0, 1e-3]], dtype=DTYPE))
    skipping.set_hyperparameters(*hyper)
    assert skipping.active_outputs.tolist() == [True, True, True]
    assert skipping.predict(queries)[1][:, 2].min() > 0


def test_all_outputs_known_and_a_single_query():
    gp = DisturbanceGP(3, 2)
    gp.add(uniform_states(20, torch.Generator().manual_seed(5)), torch.zeros(20, 2, dtype=DTYPE))
    gp.fit()
    assert gp.is_fitted and not gp.active_outputs.any()
    mean, std = gp.predict(torch.zeros(3, dtype=DTYPE))
    assert mean.shape == std.shape == (1, 2)
    assert not mean.any() and not std.any()


def test_numerically_singular_covariance_is_factored_with_jitter():
    """A long lengthscale, a large signal variance and a tiny noise make K + nI numerically
    singular (a Car Following checkpoint could not be reloaded for that): the factor gets the
    smallest jitter that works, and the posterior still interpolates its data."""
    from rcbf_ros.learning.gp import jittered_cholesky
    x = torch.linspace(0.0, 1.0, 300, dtype=torch.float64).unsqueeze(1)
    y = torch.sin(3.0 * x)
    hyper = (torch.tensor([[0.5]]), torch.tensor([1e3]), torch.tensor([1e-12]))
    k = 1e3 * torch.exp(-0.5 * (x - x.T) ** 2 / 0.25) + 1e-12 * torch.eye(300,
                                                                           dtype=torch.float64)
    assert int(torch.linalg.cholesky_ex(k).info) > 0  # plain Cholesky fails here
    chol = jittered_cholesky(k.unsqueeze(0))[0]
    assert torch.allclose(chol @ chol.T, k, atol=1e-4)
    gp = DisturbanceGP(1, 1, GPConfig(max_train_points=300))
    gp.add(x, y)
    gp.set_hyperparameters(*hyper)
    mean, std = gp.predict(x[::7])
    assert torch.isfinite(std).all()
    assert torch.allclose(mean, y[::7], atol=1e-3)
    with pytest.raises(torch.linalg.LinAlgError, match='output'):
        jittered_cholesky(-torch.eye(3, dtype=torch.float64).unsqueeze(0))
