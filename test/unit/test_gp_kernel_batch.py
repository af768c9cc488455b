"""The kernel of a batch of states on the GEMM path (``gp_bounds.kernel_batch``) against the
kernel from the squared differences, and the prediction it feeds against one state's."""
from __future__ import annotations

from hypothesis import given, HealthCheck, settings
from hypothesis import strategies as st
import numpy as np
from test_gp_projection import DTYPE, EPS, queries, random_gp
import torch

from rcbf_ros.learning import gp_bounds


def direct_kernel(plan: dict, x: np.ndarray) -> np.ndarray:
    """(D, B, M) k / s from the squared differences, one output and state at a time."""
    points = plan['points_t'].T  # (M, n_in)
    return np.stack([np.stack([np.exp((w * (row - points) ** 2).sum(-1)) for row in x])
                     for w in plan['neg_half_w']])


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 10_000), points=st.integers(2, 90), n_in=st.integers(1, 4),
       lengthscale=st.floats(0.05, 3.0), offset=st.floats(-1e3, 1e3),
       spread=st.floats(0.0, 3.0))
def test_the_batch_kernel_is_the_squared_differences_kernel_to_round_off(
        seed, points, n_in, lengthscale, offset, spread):
    """Within eps times the expansion's terms about the training points' mean, whatever the
    inputs' offset from the origin: at the training points, near them and far outside."""
    gp = random_gp(seed=seed, points=points, n_in=n_in, lengthscale=lengthscale,
                   noise_ratio=1e-3, spread=spread)
    shift = torch.full((n_in,), offset, dtype=DTYPE)
    gp.add(gp.train_x + shift, gp.train_y)  # the same data moved away from the origin
    gp.train_indices = torch.arange(points, 2 * points)
    gp._refresh_cache()
    assert gp._cache is not None
    plan = gp._cache['plans']['chosen']
    q = (queries(gp, seed) + 0.0).numpy()
    k = gp_bounds.kernel_batch(plan, q)
    reference = direct_kernel(plan, q)
    centre = gp.train_x.mean(dim=0).numpy()
    w = np.abs(plan['neg_half_w'])[:, None, None, :]  # (D, 1, 1, n_in)
    terms = (w * ((q - centre)[None, :, None, :] ** 2
                  + (plan['points_t'].T - centre)[None, None, :, :] ** 2)).sum(-1)
    allowed = 16.0 * EPS * (n_in + 2) * (1.0 + terms) * reference
    assert k.shape == reference.shape
    assert (np.abs(k - reference) <= allowed + 1e-300).all()
    assert (k <= 1.0).all()


def test_a_batch_on_the_gemm_path_predicts_as_each_state_alone():
    """From ``GEMM_BATCH`` states on the kernel is one product; each state's mean and std
    equal its prediction alone (the squared differences) to round-off, on every bound."""
    gp = random_gp(seed=3, points=80, n_in=3, lengthscale=0.4, noise_ratio=1e-4,
                   neighbours=16)
    q = queries(gp, 3, count=gp_bounds.GEMM_BATCH * 4)
    for bound in ('chosen', 'low_rank'):
        mean, std = gp.predict(q, bound=bound)
        for row in range(q.shape[0]):
            alone_mean, alone_std = gp.predict(q[row:row + 1], bound=bound)
            torch.testing.assert_close(alone_mean[0], mean[row], rtol=1e-9, atol=1e-12)
            torch.testing.assert_close(alone_std[0], std[row], rtol=1e-9, atol=1e-12)
