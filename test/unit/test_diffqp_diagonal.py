"""The diagonal-Hessian shortcuts of rcbf_ros.core.diffqp against its general path.

The RCBF-QP's P is diagonal; the solver then skips factorisations (the unconstrained minimiser,
single-row KKT systems, the backward pass of samples without or with one active row). Solutions,
multipliers, active sets and gradients must equal the general path's, also on degenerate
batches (duplicated rows, weakly active rows, zero rows, infeasible samples) where the shortcuts
must give way to the general path.
"""
from __future__ import annotations

import pytest
from test_diffqp import pool, rcbf_like_batch
import torch

from rcbf_ros.core import diffqp
from rcbf_ros.core.diffqp import solve_qp_batch, solve_qp_batch_full

DT = torch.float64


def degenerate_batch() -> tuple[torch.Tensor, ...]:
    """Duplicated rows (LICQ fails), a weakly active row, a zero row, an infeasible sample."""
    P, q, G, h = rcbf_like_batch(24, 3, 7, offset=-3.0)
    G = torch.cat([G, G[:, :1], torch.zeros_like(G[:, :1])], dim=1)
    h = torch.cat([h, h[:, :1], torch.ones_like(h[:, :1])], dim=1)
    h[:, 1] = torch.einsum('bn,bn->b', G[:, 1], solve_qp_batch(P, q, G, h))
    h[5, -1] = -1.0  # 0 <= -1: infeasible
    return P, q, G, h


def both_paths(monkeypatch, P, q, G, h):
    """(solution, gradients of P, q, G, h) with the shortcuts and with the general path."""
    out = []
    for general in (False, True):
        if general:
            monkeypatch.setattr(diffqp, '_diagonal_of', lambda P: None)
        inputs = [x.clone().requires_grad_(True) for x in (P, q, G, h)]
        sol = solve_qp_batch_full(*inputs, max_iter=30)
        weights = torch.linspace(-1.0, 2.0, sol.z.shape[-1], dtype=DT)
        finite = torch.isfinite(sol.z).all(-1, keepdim=True)
        loss = (torch.where(finite, sol.z, 0.0) * weights).sum() + sol.lam.sum()
        out.append((sol, torch.autograd.grad(loss, inputs)))
    return out


@pytest.mark.parametrize('make', [pool, degenerate_batch])
def test_shortcuts_equal_the_general_path(monkeypatch, make):
    P, q, G, h = make()
    (fast, fast_grads), (general, general_grads) = both_paths(monkeypatch, P, q, G, h)
    assert torch.equal(fast.converged, general.converged)
    ok = general.converged
    torch.testing.assert_close(fast.z[ok], general.z[ok], atol=1e-12, rtol=1e-12)
    torch.testing.assert_close(fast.lam[ok], general.lam[ok], atol=1e-10, rtol=1e-12)
    for fast_grad, general_grad in zip(fast_grads, general_grads):
        assert bool(torch.isfinite(fast_grad).all())
        torch.testing.assert_close(fast_grad, general_grad, atol=1e-9, rtol=1e-9)


def test_pool_is_solved_through_the_shortcuts(monkeypatch):
    """The RCBF batches take the diagonal path, also the single-row round and backward."""
    calls = {'one_row': 0, 'kkt': 0}
    one_row, kkt = diffqp._kkt_solve_one_row, diffqp._kkt_solve

    def count_one_row(*args):
        calls['one_row'] += 1
        return one_row(*args)

    def count_kkt(*args):
        calls['kkt'] += 1
        return kkt(*args)

    monkeypatch.setattr(diffqp, '_kkt_solve_one_row', count_one_row)
    monkeypatch.setattr(diffqp, '_kkt_solve', count_kkt)
    P, q, G, h = rcbf_like_batch(64, 6, 3, offset=0.0)
    h = h.clone().requires_grad_(True)
    sol = solve_qp_batch_full(P, q, G, h)
    assert calls['one_row'] == 1
    calls.update(one_row=0, kkt=0)
    sol.z.sum().backward()
    assert bool((sol.lam > 0).sum(-1).gt(1).any())
    assert calls == {'one_row': 0, 'kkt': 1}  # several active rows somewhere: general solve


def test_one_row_closed_form_equals_the_kkt_solve():
    gen = torch.Generator().manual_seed(4)
    batch, m, n = 32, 6, 3
    diagonal = torch.rand(batch, n, generator=gen, dtype=DT) + 0.5
    G = torch.randn(batch, m, n, generator=gen, dtype=DT)
    active = torch.zeros(batch, m, dtype=torch.bool)
    active[torch.arange(batch), torch.randint(m, (batch,), generator=gen)] = True
    active[:4] = False  # samples without an active row
    rhs_z = torch.randn(batch, n, generator=gen, dtype=DT)
    rhs_nu = torch.randn(batch, m, generator=gen, dtype=DT) * active
    x, nu = diffqp._kkt_solve_one_row(diagonal, G, active, rhs_z, rhs_nu)
    x_ref, nu_ref = diffqp._kkt_solve(torch.diag_embed(diagonal), G, active, rhs_z, rhs_nu)
    torch.testing.assert_close(x, x_ref, atol=1e-12, rtol=1e-12)
    torch.testing.assert_close(nu, nu_ref, atol=1e-12, rtol=1e-12)
    zero_row = G.clone()
    zero_row[active] = 0.0
    x, _ = diffqp._kkt_solve_one_row(diagonal, zero_row, active, rhs_z, rhs_nu + active)
    assert not bool(torch.isfinite(x[4:]).any())  # rejected by the callers' acceptance test
    assert bool(torch.isfinite(x[:4]).all())


def test_general_hessian_takes_the_general_path():
    P, q, G, h = rcbf_like_batch(8, 3, 2, offset=-2.0)
    assert diffqp._diagonal_of(P) is not None
    P = P.clone()
    P[:, 0, 1] = P[:, 1, 0] = 0.1
    assert diffqp._diagonal_of(P) is None
    z = solve_qp_batch(P, q, G, h)
    assert bool(torch.isfinite(z).all())
