"""A batch-shared P and q (the RCBF-QP's: expanded views, batch stride 0) are checked, scaled
and differentiated once for the batch: the same solution and gradients as per-sample copies."""
from __future__ import annotations

import pytest
from test_diffqp import rcbf_like_batch
import torch

from rcbf_ros.core.diffqp import solve_qp_batch_full
from rcbf_ros.core.qp import build_rcbf_qp

DT = torch.float64


def _solve_and_differentiate(P, q, G, h, weights):
    solution = solve_qp_batch_full(P, q, G, h)
    ((weights[0] * solution.z).sum() + (weights[1] * solution.lam).sum()).backward()
    return solution


@pytest.mark.parametrize('seed, offset', [(0, 0.5), (1, -1.0), (2, 3.0)])
def test_shared_p_and_q_solve_and_differentiate_as_per_sample_copies(seed, offset):
    P_batch, _, G0, h0 = rcbf_like_batch(64, 5, seed, offset=offset)
    gen = torch.Generator().manual_seed(seed + 10)
    weights = (torch.randn(64, 3, generator=gen, dtype=DT),
               torch.randn(64, G0.shape[1], generator=gen, dtype=DT))
    q_single = 0.05 * torch.randn(3, generator=gen, dtype=DT)

    P_leaf = P_batch[0].clone().requires_grad_(True)
    q_leaf = q_single.clone().requires_grad_(True)
    G_shared, h_shared = G0.clone().requires_grad_(True), h0.clone().requires_grad_(True)
    shared = _solve_and_differentiate(P_leaf.expand(64, 3, 3), q_leaf.expand(64, 3),
                                      G_shared, h_shared, weights)

    P_copies = P_leaf.detach().repeat(64, 1, 1).requires_grad_(True)
    q_copies = q_single.repeat(64, 1).requires_grad_(True)
    G_copies, h_copies = G0.clone().requires_grad_(True), h0.clone().requires_grad_(True)
    copies = _solve_and_differentiate(P_copies, q_copies, G_copies, h_copies, weights)

    assert bool(shared.converged.all()) and bool(copies.converged.all())
    for a, b in ((shared.z, copies.z), (shared.lam, copies.lam), (G_shared.grad, G_copies.grad),
                 (h_shared.grad, h_copies.grad), (P_leaf.grad, P_copies.grad.sum(0)),
                 (q_leaf.grad, q_copies.grad.sum(0))):
        torch.testing.assert_close(a, b, rtol=0, atol=1e-11)


def test_gradcheck_through_a_shared_p_and_q():
    P_batch, _, G, h = rcbf_like_batch(6, 3, 4, offset=0.0)
    P = P_batch[0].clone().requires_grad_(True)
    q = torch.full((3,), 0.1, dtype=DT, requires_grad=True)
    h = h.clone().requires_grad_(True)

    def run(P, q, h):
        return solve_qp_batch_full(P.expand(6, 3, 3), q.expand(6, 3), G, h).z

    assert torch.autograd.gradcheck(run, (P, q, h), eps=1e-7, atol=1e-6)


def test_large_finite_entries_pass_the_check_and_non_finite_ones_are_named():
    P, q, G, h = rcbf_like_batch(8, 3, 5, offset=1.0)
    huge = h.clone()
    huge[:, 0] = 1e308           # the sum of the entries overflows; every entry is finite
    assert solve_qp_batch_full(P, q, G, huge).z.shape == (8, 3)
    for name, index in (('P', 0), ('q', 1), ('G', 2), ('h', 3)):
        for bad in (float('nan'), float('inf'), -float('inf')):
            inputs = [t.clone() for t in (P, q, G, h)]
            inputs[index].view(-1)[3] = bad
            with pytest.raises(ValueError, match=f'{name}: contains NaN or inf'):
                solve_qp_batch_full(*inputs)
    with pytest.raises(ValueError, match='positive definite'):
        solve_qp_batch_full(-P, q, G, h)


def test_rcbf_qp_cost_is_built_shared_and_the_limit_rows_every_time_anew():
    lg_h = torch.randn(4, 2, 2, dtype=DT)
    args = dict(h=torch.ones(4, 2, dtype=DT), lf_h=torch.zeros(4, 2, dtype=DT), lg_h=lg_h,
                rho=torch.zeros(4, 2, dtype=DT), u_rl=torch.zeros(4, 2, dtype=DT), alpha=1.5,
                slack_weight=100.0, input_weight=(1.0, 0.25), u_min=(-1.0, -2.0),
                u_max=(1.0, 2.0))
    qp = build_rcbf_qp(**args)
    assert qp.P.stride(0) == 0 and qp.q.stride(0) == 0
    torch.testing.assert_close(qp.P[2], torch.diag(torch.tensor([2.0, 0.5, 200.0], dtype=DT)))
    assert not qp.q.any()
    again = build_rcbf_qp(**args)
    # The returned rows are the caller's own: writing them leaves the next build alone.
    again.G.zero_()
    again.h.zero_()
    third = build_rcbf_qp(**args)
    assert torch.equal(third.G, qp.G) and torch.equal(third.h, qp.h)
    torch.testing.assert_close(qp.h[:, :2], 1.5 * torch.ones(4, 2, dtype=DT))
    torch.testing.assert_close(qp.h[:, 2:], torch.tensor([[1.0, 2.0, 1.0, 2.0]] * 4, dtype=DT))
