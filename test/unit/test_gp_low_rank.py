"""DisturbanceGP's low-rank variance bound (``predict(..., bound='low_rank')``): never below the
exact variance, within its stated worst-case excess, exact at full rank, and the one-state
numpy path equal to ``predict``. The GPs here have the hybrid bound off
(``variance_neighbours=0``); test_gp_hybrid.py tests that one, test_gp_projection.py the
projection bound and the choice."""
from __future__ import annotations

import math

from hypothesis import given, HealthCheck, settings
from hypothesis import strategies as st
import numpy as np
import pytest
import torch

from rcbf_ros.learning.gp import DisturbanceGP, GPConfig, variance_excess_ratio, variance_ranks
from rcbf_ros.learning.gp_bounds import rank_groups

DTYPE = torch.float64
EPS = float(torch.finfo(DTYPE).eps)


def conditioned_gp(*, seed: int, points: int, n_in: int, lengthscale: float, noise_ratio: float,
                   tolerance: float, include_noise: bool = False) -> DisturbanceGP:
    """A GP on random data with set hyperparameters (no fit): output 0 smooth, output 1 a
    different signal and scale, output 2 exactly zero (no posterior)."""
    generator = torch.Generator().manual_seed(seed)
    x = 2.0 * torch.rand(points, n_in, generator=generator, dtype=DTYPE) - 1.0
    y = torch.stack([torch.sin(3.0 * x[:, 0]), 5.0 * torch.cos(2.0 * x.sum(-1)),
                     torch.zeros(points, dtype=DTYPE)], dim=1)
    gp = DisturbanceGP(n_in, 3, GPConfig(variance_rank_tolerance=tolerance,
                                         include_noise_in_std=include_noise,
                                         variance_neighbours=0))
    gp.add(x, y)
    outputscale = torch.tensor([1.0, 25.0, 1.0], dtype=DTYPE)
    gp.set_hyperparameters(torch.full((3, n_in), lengthscale, dtype=DTYPE), outputscale,
                           noise_ratio * outputscale)
    return gp


def round_off(gp: DisturbanceGP) -> torch.Tensor:
    """(3,) the variance round-off scale of either evaluation: eps M s (1 + s / n) per output
    (the solve's condition number is about M s / n; s itself is rounded)."""
    points = max(gp.train_x.shape[0], 16)
    assert gp.outputscale is not None and gp.noise is not None
    return 64.0 * EPS * points * gp.outputscale * (1.0 + gp.outputscale / gp.noise)


def queries(gp: DisturbanceGP, seed: int, count: int = 200) -> torch.Tensor:
    """Half near the data (perturbed training inputs), half anywhere in a wider box."""
    generator = torch.Generator().manual_seed(seed + 1)
    near = gp.train_x[torch.randint(gp.train_x.shape[0], (count // 2,), generator=generator)]
    near = near + 0.02 * torch.randn(near.shape, generator=generator, dtype=DTYPE)
    far = 3.0 * torch.rand(count - count // 2, gp.n_in, generator=generator, dtype=DTYPE) - 1.5
    return torch.cat([near, far])


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 10_000), points=st.integers(2, 80), n_in=st.integers(1, 4),
       lengthscale=st.floats(0.1, 3.0), noise_ratio=st.floats(1e-5, 10.0),
       tolerance=st.sampled_from([0.0, 1e-8, 1e-6, 1e-4, 1e-2, 0.5]),
       include_noise=st.booleans())
def test_low_rank_variance_is_never_below_the_exact_one_and_within_its_excess(
        seed, points, n_in, lengthscale, noise_ratio, tolerance, include_noise):
    gp = conditioned_gp(seed=seed, points=points, n_in=n_in, lengthscale=lengthscale,
                        noise_ratio=noise_ratio, tolerance=tolerance,
                        include_noise=include_noise)
    q = queries(gp, seed)
    mean_exact, std_exact = gp.predict(q, exact=True)
    mean_low, std_low = gp.predict(q, bound='low_rank')
    torch.testing.assert_close(mean_low, mean_exact, atol=1e-9, rtol=1e-9)
    assert gp.outputscale is not None
    excess = (std_low ** 2 - std_exact ** 2)[:, :2]
    slack = round_off(gp)[:2]
    assert (excess >= -slack).all(), (excess / gp.outputscale[:2]).min()
    bound = gp.variance_rank
    assert (bound['ranks'] <= bound['kept']).all() and (bound['kept'] <= points).all()
    assert (excess <= bound['excess'] * gp.outputscale[:2] + slack).all()
    assert (bound['excess'] <= tolerance).all()
    assert not std_low[:, 2].any() and not mean_low[:, 2].any()


@pytest.mark.parametrize('include_noise', [False, True])
def test_full_rank_is_the_exact_variance_to_round_off(include_noise):
    gp = conditioned_gp(seed=3, points=120, n_in=3, lengthscale=0.7, noise_ratio=1e-2,
                        tolerance=0.0, include_noise=include_noise)
    assert (gp.variance_rank['kept'] == 120).all()
    assert not gp.variance_rank['excess'].any()
    q = queries(gp, 3)
    mean_exact, std_exact = gp.predict(q, exact=True)
    mean_low, std_low = gp.predict(q, bound='low_rank')
    assert gp.outputscale is not None
    relative = (std_low ** 2 - std_exact ** 2)[:, :2].abs() / gp.outputscale[:2]
    assert relative.max() < 1e-12
    torch.testing.assert_close(mean_low, mean_exact, atol=1e-12, rtol=0)


def test_a_looser_tolerance_keeps_fewer_pairs_and_the_box_still_contains_the_exact_one():
    generator = torch.Generator().manual_seed(0)
    states = (2.0 * torch.rand(600, 3, generator=generator, dtype=DTYPE) - 1.0) * 3.0
    truth = torch.stack([-0.1 * torch.cos(states[:, 2]) ** 2,
                         -0.1 * torch.cos(states[:, 2]) * torch.sin(states[:, 2])], dim=1)
    observed = truth + 0.01 * torch.randn(600, 2, generator=generator, dtype=DTYPE)
    exact = DisturbanceGP(3, 2, GPConfig(max_train_points=400, variance_rank_tolerance=0.0,
                                         variance_neighbours=0))
    exact.add(states, observed)
    exact.fit()
    held_out = (2.0 * torch.rand(2000, 3, generator=generator, dtype=DTYPE) - 1.0) * 3.0
    truth_out = torch.stack([-0.1 * torch.cos(held_out[:, 2]) ** 2,
                             -0.1 * torch.cos(held_out[:, 2]) * torch.sin(held_out[:, 2])], 1)
    lower_e, upper_e = exact.bounds(held_out, 2.0)
    inside_exact = ((truth_out >= lower_e) & (truth_out <= upper_e)).float().mean()
    ranks = []
    for tolerance in (1e-6, 1e-4, 1e-2):
        gp = DisturbanceGP(3, 2, GPConfig(max_train_points=400, training_iterations=0,
                                          variance_rank_tolerance=tolerance,
                                          variance_neighbours=0))
        gp.load_state_dict(exact.state_dict())  # same data and hyperparameters
        ranks.append(int(gp.variance_rank['kept'].max()))
        lower, upper = gp.bounds(held_out, 2.0)
        slack = 1e-9
        assert (lower <= lower_e + slack).all() and (upper >= upper_e - slack).all()
        inside = ((truth_out >= lower) & (truth_out <= upper)).float().mean()
        assert inside >= inside_exact
    assert 400 > ranks[0] >= ranks[1] >= ranks[2]


def test_predict_state_equals_predict_and_before_a_fit_the_prior():
    gp = conditioned_gp(seed=5, points=60, n_in=2, lengthscale=0.5, noise_ratio=1e-3,
                        tolerance=1e-4)
    for row in queries(gp, 5, count=10):
        mean, std = gp.predict_state(row.numpy())
        ref_mean, ref_std = gp.predict(row)
        np.testing.assert_allclose(mean, ref_mean[0].numpy(), atol=1e-12, rtol=0)
        np.testing.assert_allclose(std, ref_std[0].numpy(), atol=1e-12, rtol=0)
    prior = DisturbanceGP(2, 3, GPConfig(prior_std=0.3))
    mean, std = prior.predict_state(np.zeros(2))
    assert not mean.any() and (std == 0.3).all()
    with pytest.raises(ValueError, match=r'state must have shape \(2,\)'):
        gp.predict_state(np.zeros(3))


def test_excess_ratio_is_the_maximum_over_the_discarded_range():
    noise = torch.tensor([1e-3, 0.1, 1.0, 4.0], dtype=DTYPE)
    for tail in (0.0, 1e-4, 0.05, 1.0, 30.0):
        a = torch.full_like(noise, tail)
        grid = torch.linspace(0.0, 1.0, 20_001, dtype=DTYPE)[:, None] * a
        brute = (grid * (a - grid) / ((grid + noise) * (a + noise))).max(dim=0).values
        torch.testing.assert_close(variance_excess_ratio(tail=a, noise=noise), brute,
                                   atol=1e-8, rtol=1e-6)
    assert not variance_excess_ratio(tail=torch.tensor([-1.0]), noise=torch.ones(1)).any()
    eigenvalues = torch.tensor([[9.0, 3.0, 1.2, 1.01, 1.0]], dtype=DTYPE)
    ones = torch.ones(1, dtype=DTYPE)
    assert variance_ranks(eigenvalues=eigenvalues, noise=ones, tolerance=0.0).item() == 4
    assert variance_ranks(eigenvalues=eigenvalues, noise=ones, tolerance=1e-3).item() == 3
    assert variance_ranks(eigenvalues=eigenvalues, noise=ones, tolerance=0.99).item() == 0


@pytest.mark.parametrize('value', [-1e-3, 1.0, math.nan])
def test_bad_tolerance_is_rejected_naming_the_field(value):
    with pytest.raises(ValueError, match='variance_rank_tolerance'):
        GPConfig(variance_rank_tolerance=value)


def test_outputs_of_far_apart_ranks_are_predicted_in_separate_groups():
    groups = rank_groups(torch.tensor([56, 331, 50, 60]))
    assert [g.tolist() for g in groups] == [[0, 2, 3], [1]]
    assert [g.tolist() for g in rank_groups(torch.tensor([46, 55, 53]))] == [[0, 1, 2]]
    # A strong signal (few pairs) next to one weaker than its noise (many pairs).
    generator = torch.Generator().manual_seed(2)
    x = 2.0 * torch.rand(150, 2, generator=generator, dtype=DTYPE) - 1.0
    y = torch.stack([torch.sin(3.0 * x[:, 0]), 0.1 * torch.cos(2.0 * x[:, 1]),
                     torch.zeros(150, dtype=DTYPE)], dim=1)
    gp = DisturbanceGP(2, 3, GPConfig(variance_rank_tolerance=1e-4, variance_neighbours=0))
    gp.add(x, y)
    gp.set_hyperparameters(torch.tensor([[2.0, 2.0], [0.05, 0.05], [1.0, 1.0]], dtype=DTYPE),
                           torch.tensor([1.0, 0.01, 1.0], dtype=DTYPE),
                           torch.tensor([1e-2, 0.04, 1.0], dtype=DTYPE))
    kept = gp.variance_rank['kept']
    assert kept[1] > 2 * kept[0] + 32  # two groups
    q = queries(gp, 2)
    _, std_exact = gp.predict(q, exact=True)
    mean, std = gp.predict(q, bound='low_rank')
    assert ((std ** 2 - std_exact ** 2)[:, :2] >= -round_off(gp)[:2]).all()
    for row, row_mean, row_std in zip(q[:5], mean[:5], std[:5]):
        one_mean, one_std = gp.predict_state(row.numpy(), bound='low_rank')
        np.testing.assert_allclose(one_mean, row_mean.numpy(), atol=1e-12, rtol=0)
        # Batch and single products round differently: equal to the variance's round-off.
        assert (np.abs(one_std ** 2 - row_std.numpy() ** 2) <= round_off(gp).numpy()).all()


def test_a_noise_far_below_the_signal_costs_no_accuracy_near_the_data():
    # noise / s = 1e-7 (as learned on Unicycle and Car Following): |k|^2 / n is ~1e8 s, so a
    # variance formed as a difference of such terms would lose everything near the data.
    gp = conditioned_gp(seed=11, points=300, n_in=2, lengthscale=1.0, noise_ratio=1e-7,
                        tolerance=1e-4)
    assert (gp.variance_rank['kept'] < 300).all()
    q = queries(gp, 11, count=400)
    _, std_exact = gp.predict(q, exact=True)
    assert gp.outputscale is not None
    for bound in ('low_rank', 'chosen'):
        _, std_low = gp.predict(q, bound=bound)
        excess = (std_low ** 2 - std_exact ** 2)[:, :2] / gp.outputscale[:2]
        assert excess.min() >= -1e-10, bound
        assert (std_low[:, :2] >= 0.999 * std_exact[:, :2]).all(), bound


def test_the_learners_proposal_carries_the_gp_estimate_at_the_state(tmp_path):
    from rcbf_ros.learning.sac import SACConfig
    from rcbf_ros.training.agent import LearnerConfig
    from rcbf_ros.training.build import build_run, RunConfig
    run = RunConfig(system='car_following', episodes=1, max_steps=100, record_bag=False,
                    out_dir=str(tmp_path / 'run'),
                    learner=LearnerConfig(mode='baseline', seed=0, start_steps=10,
                                          update_after=10 ** 6, gp_refit_interval=10 ** 6,
                                          sac=SACConfig(hidden_sizes=(16, 16))))
    env, _, learner, _ = build_run(run)
    obs, info = env.reset(seed=0)
    generator = torch.Generator().manual_seed(0)
    states = torch.as_tensor(info['state']) + 0.1 * torch.randn(
        80, len(info['state']), generator=generator, dtype=DTYPE)
    residuals = torch.zeros_like(states)
    residuals[:, 1::2] = 0.1 * torch.sin(states[:, ::2])  # velocities' rows: a posterior each
    learner.gp.add(states, residuals)
    learner.gp.fit()
    proposal = learner.propose(obs, info['state'])
    mean, std = learner.disturbance(torch.as_tensor(info['state']).unsqueeze(0))
    np.testing.assert_allclose(proposal.disturbance_mean, mean[0].numpy(), atol=1e-12, rtol=0)
    np.testing.assert_allclose(proposal.disturbance_std, std[0].numpy(), atol=1e-12, rtol=1e-9)
    assert proposal.disturbance_std[1::2].all() and not proposal.disturbance_std[::2].any()
