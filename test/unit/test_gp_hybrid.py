"""DisturbanceGP's hybrid variance bound (low rank plus a neighbourhood): never below the exact
variance at any rank and neighbourhood size, on random GPs (near-duplicate inputs, noise far
below the signal, queries far from the data) and on GPs fitted to each system's residuals;
the per-output choice, and the one-state path equal to ``predict``."""
from __future__ import annotations

from hypothesis import given, HealthCheck, settings
from hypothesis import strategies as st
import numpy as np
import pytest
import torch

from rcbf_ros.learning import gp_bounds
from rcbf_ros.learning.gp import DisturbanceGP, GPConfig
from rcbf_ros.learning.gp_bounds import HYBRID_RANKS

DTYPE = torch.float64
EPS = float(torch.finfo(DTYPE).eps)


def random_gp(*, seed: int, points: int, n_in: int, lengthscale: float, noise_ratio: float,
              neighbours: int, duplicates: int = 0, include_noise: bool = False,
              ) -> DisturbanceGP:
    """A GP on random data with set hyperparameters: output 0 smooth, output 1 a different
    signal and scale, output 2 exactly zero. ``duplicates`` inputs repeat others to 1e-9."""
    generator = torch.Generator().manual_seed(seed)
    x = 2.0 * torch.rand(points, n_in, generator=generator, dtype=DTYPE) - 1.0
    if duplicates:
        source = torch.randint(points, (duplicates,), generator=generator)
        x[-duplicates:] = x[source] + 1e-9 * torch.randn(duplicates, n_in, generator=generator,
                                                         dtype=DTYPE)
    y = torch.stack([torch.sin(3.0 * x[:, 0]), 5.0 * torch.cos(2.0 * x.sum(-1)),
                     torch.zeros(points, dtype=DTYPE)], dim=1)
    gp = DisturbanceGP(n_in, 3, GPConfig(variance_neighbours=neighbours,
                                         include_noise_in_std=include_noise))
    gp.add(x, y)
    outputscale = torch.tensor([1.0, 25.0, 1.0], dtype=DTYPE)
    gp.set_hyperparameters(torch.full((3, n_in), lengthscale, dtype=DTYPE), outputscale,
                           noise_ratio * outputscale)
    return gp


def queries(gp: DisturbanceGP, seed: int, count: int = 120) -> torch.Tensor:
    """Training inputs exactly, training inputs moved a little, and states far from the data."""
    generator = torch.Generator().manual_seed(seed + 1)
    train = gp.train_x
    at = train[torch.randint(train.shape[0], (count // 3,), generator=generator)]
    near = at + 0.05 * torch.randn(at.shape, generator=generator, dtype=DTYPE)
    far = 8.0 * torch.rand(count - 2 * (count // 3), gp.n_in, generator=generator,
                           dtype=DTYPE) - 4.0
    return torch.cat([at, near, far])


def round_off(gp: DisturbanceGP) -> np.ndarray:
    """(n_active,) the variance round-off of either evaluation, eps M s (1 + s / n)."""
    active = gp.active_outputs
    assert gp.outputscale is not None and gp.noise is not None
    s, n = gp.outputscale[active], gp.noise[active]
    return (64.0 * EPS * max(gp.train_x.shape[0], 16) * s * (1.0 + s / n)).numpy()


def hybrid_variance(gp: DisturbanceGP, q: torch.Tensor, rank: int) -> np.ndarray:
    """(B, n_active) the hybrid bound's variance at ``rank`` on every active output."""
    c = gp._cache
    assert c is not None
    outputs = torch.arange(int(gp.active_outputs.sum()))
    factor = torch.stack([gp_bounds.hybrid_factor(c, int(o), rank) for o in outputs])
    plan = gp_bounds.make_plan(c, [('hybrid', outputs, rank, factor)],
                               gp.config.include_noise_in_std)
    std = gp_bounds.predict_plan(plan, q.numpy())[:-1, :, 1]
    return std.T ** 2


def exact_variance(gp: DisturbanceGP, q: torch.Tensor) -> np.ndarray:
    _, std = gp.predict(q, exact=True)
    return (std ** 2)[:, gp.active_outputs].numpy()


@settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 10_000), points=st.integers(3, 90), n_in=st.integers(1, 4),
       lengthscale=st.floats(0.05, 3.0), noise_ratio=st.floats(1e-7, 10.0),
       neighbours=st.integers(1, 40), duplicates=st.integers(0, 2),
       include_noise=st.booleans())
def test_the_hybrid_bound_is_never_below_the_exact_variance(
        seed, points, n_in, lengthscale, noise_ratio, neighbours, duplicates, include_noise):
    gp = random_gp(seed=seed, points=points, n_in=n_in, lengthscale=lengthscale,
                   noise_ratio=noise_ratio, neighbours=neighbours, duplicates=duplicates,
                   include_noise=include_noise)
    if neighbours >= points:
        assert gp.variance_bound['size'] == 0
        assert 'hybrid' not in gp.variance_bound['bound']
        return
    q = queries(gp, seed)
    exact = exact_variance(gp, q)
    slack = round_off(gp)
    for rank in [r for r in HYBRID_RANKS if r < points]:
        excess = hybrid_variance(gp, q, rank) - exact
        assert (excess >= -slack).all(), (rank, (excess / slack).min())
    # Far from the data both are the prior variance.
    far = q[-(q.shape[0] - 2 * (q.shape[0] // 3)):]
    outside = (torch.cdist(far / lengthscale, gp.train_x / lengthscale).min(-1).values > 9.0)
    if outside.any():
        _, std = gp.predict(far[outside])
        prior = gp.outputscale + (gp.noise if include_noise else 0.0)
        torch.testing.assert_close(std[:, :2] ** 2, prior[:2].expand(int(outside.sum()), 2),
                                   atol=1e-12, rtol=1e-12)
    _, std_default = gp.predict(q)
    assert ((std_default[:, :2] ** 2).numpy() - exact >= -slack).all()
    assert not std_default[:, 2].any()


def test_with_no_low_rank_part_it_is_the_variance_given_the_neighbourhood_alone():
    gp = random_gp(seed=4, points=60, n_in=2, lengthscale=0.3, noise_ratio=1e-3, neighbours=8)
    q = queries(gp, 4, count=30)
    variance = hybrid_variance(gp, q, 0)
    c = gp._cache
    assert c is not None
    k = gp_bounds.cross_kernel(c, q)  # (D, B, M)
    for output in range(2):
        nearest = k[output].argmax(-1)
        for b in range(q.shape[0]):
            subset = c['neighbour_index'][output, nearest[b]]
            sub = gp.train_x[subset]
            sub_gp = DisturbanceGP(2, 1, GPConfig(variance_neighbours=0))
            sub_gp.add(sub, torch.ones(subset.numel(), 1, dtype=DTYPE))
            sub_gp.set_hyperparameters(c['lengthscales'][output:output + 1],
                                       c['outputscale'][output:output + 1],
                                       c['noise'][output:output + 1])
            _, std = sub_gp.predict(q[b], exact=True)
            assert variance[b, output] == pytest.approx(float(std[0, 0]) ** 2, rel=1e-9,
                                                        abs=1e-12)


def test_a_noise_dominated_short_lengthscale_output_takes_the_neighbourhood():
    # Noise near the signal and a short lengthscale: the low-rank bound needs nearly every
    # pair, while the neighbourhood carries the posterior.
    gp = random_gp(seed=7, points=300, n_in=3, lengthscale=0.1, noise_ratio=0.5,
                   neighbours=32)
    bound = gp.variance_bound
    assert bound['size'] == 32
    assert (gp.variance_rank['ranks'] == 300).all()
    assert bound['bound'] == ('hybrid', 'hybrid') and (bound['rank'] == 0).all()
    q = queries(gp, 7)
    exact = exact_variance(gp, q)
    _, std = gp.predict(q)
    variance = (std ** 2)[:, :2].numpy()
    assert (variance - exact >= -round_off(gp)).all()
    assert (np.sqrt(variance / exact) <= 1.0 + 0.05).all()
    for row, mean_row, std_row in zip(q[:10], *gp.predict(q[:10])):
        one_mean, one_std = gp.predict_state(row.numpy())
        np.testing.assert_allclose(one_mean, mean_row.numpy(), atol=1e-12, rtol=0)
        np.testing.assert_allclose(one_std, std_row.numpy(), atol=1e-12, rtol=1e-9)
    # The low-rank bound stays available on every output, in both paths.
    low_mean, low = gp.predict(q, bound='low_rank')
    assert ((low ** 2)[:, :2].numpy() - exact >= -round_off(gp)).all()
    for row, mean_row, std_row in zip(q[:5], low_mean[:5], low[:5]):
        one_mean, one_std = gp.predict_state(row.numpy(), bound='low_rank')
        np.testing.assert_allclose(one_mean, mean_row.numpy(), atol=1e-12, rtol=0)
        np.testing.assert_allclose(one_std, std_row.numpy(), atol=1e-12, rtol=1e-9)


def test_a_smooth_output_takes_no_neighbourhood_and_the_hybrid_can_be_turned_off():
    smooth = random_gp(seed=8, points=200, n_in=2, lengthscale=2.0, noise_ratio=1e-4,
                       neighbours=16)
    assert 'hybrid' not in smooth.variance_bound['bound']
    off = random_gp(seed=7, points=300, n_in=3, lengthscale=0.1, noise_ratio=0.5,
                    neighbours=0)
    assert off.variance_bound['size'] == 0
    assert off.variance_bound['bound'] == ('low_rank', 'low_rank')
    q = queries(off, 1)
    torch.testing.assert_close(off.predict(q), off.predict(q, bound='low_rank'))
    assert DisturbanceGP(2, 1).variance_bound == {}


@pytest.mark.parametrize('field, value', [('variance_neighbours', -1),
                                          ('bound_std_tolerance', -0.1),
                                          ('bound_std_tolerance', float('nan'))])
def test_bad_hybrid_settings_are_rejected_naming_the_field(field, value):
    with pytest.raises(ValueError, match=field):
        GPConfig(**{field: value})


def test_an_unknown_bound_is_rejected_naming_it():
    gp = random_gp(seed=1, points=20, n_in=2, lengthscale=0.5, noise_ratio=0.1, neighbours=4)
    with pytest.raises(ValueError, match="bound must be 'chosen' or 'low_rank'"):
        gp.predict(torch.zeros(1, 2, dtype=DTYPE), bound='exact')  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="bound must be 'chosen' or 'low_rank'"):
        gp.predict_state(np.zeros(2), bound='exact')  # type: ignore[arg-type]


@pytest.mark.parametrize('system', ['unicycle', 'pvtol', 'car_following'])
def test_on_each_systems_residuals_every_bound_contains_the_exact_box(system, tmp_path):
    from rcbf_ros.learning.sac import SACConfig
    from rcbf_ros.training.agent import LearnerConfig
    from rcbf_ros.training.build import build_run, RunConfig
    run = RunConfig(system=system, episodes=1, max_steps=10 ** 6, record_bag=False,
                    out_dir=str(tmp_path / 'run'),
                    learner=LearnerConfig(mode='baseline', seed=0, start_steps=10 ** 6,
                                          update_after=10 ** 6, gp_refit_interval=10 ** 6,
                                          sac=SACConfig(hidden_sizes=(8, 8))))
    env, _, learner, _ = build_run(run)
    rng = np.random.default_rng(0)
    obs, info = env.reset(seed=0)
    states, residuals = [], []
    model = learner.system
    for _ in range(240):
        u = rng.uniform(learner.sac.u_low.numpy(), learner.sac.u_high.numpy())
        obs, _, terminated, truncated, next_info = env.step(u)
        x = torch.as_tensor(np.asarray(info['state'], dtype=np.float64)).unsqueeze(0)
        nominal = model.f(x) + (model.g(x) @ torch.as_tensor(u).reshape(1, -1, 1)).squeeze(-1)
        residuals.append(((torch.as_tensor(next_info['state']) - x[0]) / env.dt
                          - nominal[0]).numpy())
        states.append(x[0].numpy())
        info = next_info
        if terminated or truncated:
            obs, info = env.reset()
    gp = DisturbanceGP(len(states[0]), len(residuals[0]),
                       GPConfig(max_train_points=160, hyperparameter_points=80,
                                training_iterations=15, variance_neighbours=16))
    gp.add(np.stack(states), np.stack(residuals))
    gp.fit()
    q = torch.cat([queries(gp, 3), torch.as_tensor(np.stack(states[::3]))])
    exact = exact_variance(gp, q)
    slack = round_off(gp)
    for rank in [r for r in HYBRID_RANKS if r < 160]:
        assert (hybrid_variance(gp, q, rank) - exact >= -slack).all(), rank
    for bound in ('chosen', 'low_rank'):
        _, std = gp.predict(q, bound=bound)
        assert ((std ** 2)[:, gp.active_outputs].numpy() - exact >= -slack).all(), bound


def test_a_refit_that_fails_on_the_way_leaves_the_previous_posterior(monkeypatch):
    gp = random_gp(seed=7, points=120, n_in=3, lengthscale=0.1, noise_ratio=0.5,
                   neighbours=16)
    q = queries(gp, 2, count=12)
    before, version = gp.predict(q), gp.version
    state_before = gp.predict_state(q[0].numpy())

    def no_factor(*args: object, **kwargs: object) -> None:
        raise torch.linalg.LinAlgError('not positive definite')

    monkeypatch.setattr(gp_bounds, 'hybrid_factor', no_factor)
    with pytest.raises(torch.linalg.LinAlgError):
        gp.set_hyperparameters(gp.lengthscales * 2.0, gp.outputscale, gp.noise)
    assert gp.version == version
    for now, then in zip(gp.predict(q), before):
        torch.testing.assert_close(now, then, rtol=0, atol=0)
    for now, then in zip(gp.predict_state(q[0].numpy()), state_before):
        np.testing.assert_array_equal(now, then)
