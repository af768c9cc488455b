"""The diagonal-Hessian shortcuts of rcbf_ros.core.diffqp against its general path.

The RCBF-QP's P is diagonal; the solver then skips factorisations (the unconstrained minimiser,
single-row KKT systems, the backward pass of samples without or with one active row). Solutions,
multipliers, active sets and gradients must equal the general path's, also on degenerate
batches (duplicated rows, weakly active rows, zero rows, infeasible samples) where the shortcuts
must give way to the general path.
"""
from __future__ import annotations

from hypothesis import example, given, settings
from hypothesis import strategies as st
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
    """The RCBF batches take the diagonal path, also the single-row round and backward; the
    general solve only for samples with more than two active rows."""
    calls = {'one_row': 0, 'two_rows': 0, 'kkt': 0, 'kkt_rows': 0}
    one_row, two_rows, kkt = (diffqp._kkt_solve_one_row, diffqp._kkt_solve_two_rows,
                              diffqp._kkt_solve)

    def count_one_row(*args):
        calls['one_row'] += 1
        return one_row(*args)

    def count_two_rows(*args):
        calls['two_rows'] += 1
        return two_rows(*args)

    def count_kkt(*args):
        calls['kkt'] += 1
        calls['kkt_rows'] += int(args[2].shape[0])
        return kkt(*args)

    monkeypatch.setattr(diffqp, '_kkt_solve_one_row', count_one_row)
    monkeypatch.setattr(diffqp, '_kkt_solve_two_rows', count_two_rows)
    monkeypatch.setattr(diffqp, '_kkt_solve', count_kkt)
    P, q, G, h = rcbf_like_batch(64, 6, 3, offset=0.0)
    h = h.clone().requires_grad_(True)
    sol = solve_qp_batch_full(P, q, G, h)
    assert calls['one_row'] == 1
    calls.update(one_row=0, two_rows=0, kkt=0, kkt_rows=0)
    sol.z.sum().backward()
    count = (sol.lam > 0).sum(-1)
    assert bool((count == 2).any()) and bool((count > 2).any())
    # The samples with two rows in closed form, only those with three by the general solve.
    assert calls == {'one_row': 0, 'two_rows': 1, 'kkt': 1, 'kkt_rows': int((count > 2).sum())}


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


def _residuals(diagonal, G, active, rhs_z, rhs_nu, x, nu):
    """Relative KKT residuals of (x, nu): stationarity D x + G_A^T nu = rhs_z and the active
    rows G_A x = rhs_nu, each against the size of its terms."""
    mask = active.to(G.dtype)
    gt_nu = torch.einsum('bmn,bm->bn', G * mask.unsqueeze(-1), nu)
    stationarity = (diagonal * x + gt_nu - rhs_z).abs().amax(-1) / (
        1.0 + torch.maximum((diagonal * x).abs().amax(-1), gt_nu.abs().amax(-1)))
    gx = torch.einsum('bmn,bn->bm', G, x)
    rows = ((gx - rhs_nu) * mask).abs().amax(-1) / (1.0 + (gx * mask).abs().amax(-1))
    return torch.maximum(stationarity, rows)


def test_two_row_closed_form_equals_the_kkt_solve_and_declines_dependent_rows():
    gen = torch.Generator().manual_seed(5)
    batch, m, n = 40, 6, 3
    diagonal = torch.rand(batch, n, generator=gen, dtype=DT) + 0.5
    G = torch.randn(batch, m, n, generator=gen, dtype=DT)
    active = torch.zeros(batch, m, dtype=torch.bool)
    for b in range(batch):
        active[b, torch.randperm(m, generator=gen)[:b % 3]] = True  # 0, 1 or 2 rows
    rows = torch.tensor([0, 1])
    G[30:33, 1] = G[30:33, 0] * 2.0         # dependent pairs: LICQ fails
    G[33:36, 1] = G[33:36, 0] + 1e-6 * torch.randn(3, n, generator=gen, dtype=DT)
    # Rows at an angle of about 1e-2: taken, with M's condition ~1e4 left to the refinement.
    G[36:, 1] = 1.7 * G[36:, 0] + 1e-2 * torch.randn(4, n, generator=gen, dtype=DT)
    active[30:] = False
    active[30:, rows] = True
    rhs_z = torch.randn(batch, n, generator=gen, dtype=DT)
    rhs_nu = torch.randn(batch, m, generator=gen, dtype=DT) * active
    x, nu, ok = diffqp._kkt_solve_two_rows(diagonal, G, active, rhs_z, rhs_nu)
    x_ref, nu_ref = diffqp._kkt_solve(torch.diag_embed(diagonal), G, active, rhs_z, rhs_nu)
    assert not bool(ok[30:36].any()) and bool(ok[:30].all()) and bool(ok[36:].all())
    torch.testing.assert_close(x[ok], x_ref[ok], atol=1e-12, rtol=1e-12)
    torch.testing.assert_close(nu[ok], nu_ref[ok], atol=1e-12, rtol=1e-12)
    assert not bool(nu[~active].any())
    residual = _residuals(diagonal, G, active, rhs_z, rhs_nu, x, nu)
    assert float(residual[ok].max()) < 1e-13
    # Through the dispatcher every sample gets the general solve's answer.
    x, nu = diffqp._kkt_solve_diagonal(torch.diag_embed(diagonal), diagonal, G, active, rhs_z,
                                       rhs_nu)
    torch.testing.assert_close(x, x_ref, atol=1e-12, rtol=1e-12)
    torch.testing.assert_close(nu, nu_ref, atol=1e-12, rtol=1e-12)


@settings(max_examples=200, deadline=None)
@given(seed=st.integers(0, 2 ** 31 - 1), log_diagonal=st.floats(-3.0, 3.0),
       log_row=st.floats(-3.0, 3.0), log_angle=st.floats(-9.0, 0.0),
       log_rhs=st.floats(-6.0, 6.0), rows=st.integers(0, 3))
# One active row of norm ~1e2 against a diagonal ~1e-2.5: the one-row closed form without
# its refinement step left residuals 4-8x the general solve's.
@example(seed=180825698, log_diagonal=-2.473173649909195, log_row=2.188685160443521,
         log_angle=-7.124901754204492, log_rhs=4.174159574497422, rows=1)
@example(seed=351391812, log_diagonal=-2.2911077148698, log_row=2.113758493405605,
         log_angle=-6.2425025613111, log_rhs=2.8785188364836802, rows=1)
def test_diagonal_kkt_solve_holds_the_kkt_conditions_on_hostile_inputs(
        seed, log_diagonal, log_row, log_angle, log_rhs, rows):
    """Spread diagonals, row norms and right-hand sides, a second row at a tiny angle to the
    first: where the two-row closed form is taken its answer satisfies the KKT system to
    rounding, and every answer at least as well as the general solve's."""
    gen = torch.Generator().manual_seed(seed)
    batch, m, n = 8, 5, 3
    diagonal = 10.0 ** (log_diagonal * torch.rand(batch, n, generator=gen, dtype=DT))
    G = torch.randn(batch, m, n, generator=gen, dtype=DT)
    G = G / torch.linalg.vector_norm(G, dim=-1, keepdim=True) * 10.0 ** (
        log_row * torch.rand(batch, m, 1, generator=gen, dtype=DT))
    G[:, 1] = G[:, 0] * 1.7 + 10.0 ** log_angle * torch.randn(batch, n, generator=gen,
                                                                dtype=DT)
    active = torch.zeros(batch, m, dtype=torch.bool)
    active[:, :rows] = True
    rhs_z = torch.randn(batch, n, generator=gen, dtype=DT) * 10.0 ** log_rhs
    rhs_nu = torch.randn(batch, m, generator=gen, dtype=DT) * 10.0 ** log_rhs * active
    P = torch.diag_embed(diagonal)
    x, nu = diffqp._kkt_solve_diagonal(P, diagonal, G, active, rhs_z, rhs_nu)
    x_ref, nu_ref = diffqp._kkt_solve(P, G, active, rhs_z, rhs_nu)
    assert bool(torch.isfinite(x).all()) and bool(torch.isfinite(nu).all())
    assert not bool(nu[~active].any())
    # The KKT conditions define the answer: the dispatcher's holds them at least as well as
    # the general solve's (declined samples are the general solve's own, on part of the batch).
    dispatched = _residuals(diagonal, G, active, rhs_z, rhs_nu, x, nu)
    general = _residuals(diagonal, G, active, rhs_z, rhs_nu, x_ref, nu_ref)
    assert bool((dispatched <= 1e-11 + 2.0 * general).all())
    if rows <= 2:
        x_two, nu_two, ok = diffqp._kkt_solve_two_rows(diagonal, G, active, rhs_z, rhs_nu)
        residual = _residuals(diagonal, G, active, rhs_z, rhs_nu, x_two, nu_two)
        assert bool((residual[ok] < 1e-11).all())
        assert not bool(nu_two[~active].any())
    else:
        torch.testing.assert_close(x, x_ref, atol=0, rtol=0)
        torch.testing.assert_close(nu, nu_ref, atol=0, rtol=0)


def test_general_hessian_takes_the_general_path():
    P, q, G, h = rcbf_like_batch(8, 3, 2, offset=-2.0)
    assert diffqp._diagonal_of(P) is not None
    P = P.clone()
    P[:, 0, 1] = P[:, 1, 0] = 0.1
    assert diffqp._diagonal_of(P) is None
    z = solve_qp_batch(P, q, G, h)
    assert bool(torch.isfinite(z).all())
