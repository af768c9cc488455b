"""The batched differentiable QP (rcbf_ros.core.diffqp) against independent solvers and math.

Instances have the RCBF-QP's structure (rcbf_ros.core.qp): z = [u_S (2), eps], P = 2 diag(1, 1, l),
barrier rows [-L_g h_i, -1] z <= b_i, actuator rows +-e_j. Regimes are told apart by the
solution itself (which rows are active, how large the slack is) so that every regime is
exercised: nothing active, actuator limits active, a large slack (conflicting barriers),
several rows active at once.
"""
from __future__ import annotations

import itertools

import numpy as np
import pytest
import torch

from rcbf_ros.core.diffqp import QPSolution, solve_qp_batch, solve_qp_batch_full

DT = torch.float64
SLACK_WEIGHT = 1.0e3


def rcbf_like_batch(batch: int, n_barriers: int, seed: int, *, offset: float,
                    u_limit: float = 2.5, slack_weight: float = SLACK_WEIGHT
                    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """B random RCBF-QPs: K barrier rows + 4 actuator rows, rhs ~ offset + N(0, 1)."""
    gen = torch.Generator().manual_seed(seed)
    lg_h = torch.randn(batch, n_barriers, 2, generator=gen, dtype=DT) * 1.5
    rhs = offset + torch.randn(batch, n_barriers, generator=gen, dtype=DT)
    u_rl = (torch.rand(batch, 2, generator=gen, dtype=DT) * 2 - 1) * 2.0
    eye = torch.eye(2, dtype=DT)
    limit_rows = torch.cat([torch.cat([eye, -eye]), torch.zeros(4, 1, dtype=DT)], dim=1)
    G = torch.cat([torch.cat([-lg_h, -torch.ones(batch, n_barriers, 1, dtype=DT)], dim=2),
                   limit_rows.expand(batch, -1, -1)], dim=1)
    h = torch.cat([rhs, u_limit - u_rl, u_limit + u_rl], dim=1)
    P = torch.diag(torch.tensor([2.0, 2.0, 2.0 * slack_weight], dtype=DT)).expand(batch, 3, 3)
    q = torch.zeros(batch, 3, dtype=DT) + 0.05 * torch.randn(batch, 3, generator=gen, dtype=DT)
    return P.contiguous(), q, G, h


def enumerate_active_sets(P: np.ndarray, q: np.ndarray, G: np.ndarray, h: np.ndarray
                          ) -> np.ndarray:
    """Exact reference: the KKT point among all active sets of at most nz rows (numpy)."""
    batch, nc, nz = G.shape
    best_z, best_obj = np.zeros((batch, nz)), np.full(batch, np.inf)
    for k in range(nz + 1):
        for rows in itertools.combinations(range(nc), k):
            A, b = G[:, list(rows)], h[:, list(rows)]
            kkt = np.zeros((batch, nz + k, nz + k))
            kkt[:, :nz, :nz], kkt[:, :nz, nz:], kkt[:, nz:, :nz] = P, A.transpose(0, 2, 1), A
            regular = np.abs(np.linalg.det(kkt)) > 1e-12
            kkt[~regular] = np.eye(nz + k)
            sol = np.linalg.solve(kkt, np.concatenate([-q, b], 1)[..., None])[..., 0]
            z, nu = sol[:, :nz], sol[:, nz:]
            violation = (np.einsum('bcn,bn->bc', G, z) - h).max(-1)
            feasible = violation <= 1e-9 * (1 + np.abs(h).max(-1))
            dual = (nu >= -1e-9 * (1 + np.abs(nu).max(-1, initial=0))[:, None]).all(-1)
            obj = 0.5 * np.einsum('bi,bij,bj->b', z, P, z) + (q * z).sum(-1)
            take = regular & feasible & dual & (obj < best_obj)
            best_z[take], best_obj[take] = z[take], obj[take]
    best_z[~np.isfinite(best_obj)] = np.nan  # no KKT point within tolerance (ill-conditioned)
    return best_z


def pool() -> tuple[torch.Tensor, ...]:
    """A mixed batch covering all regimes (mild to severe barrier demands)."""
    parts = [rcbf_like_batch(64, 6, seed, offset=offset)
             for seed, offset in enumerate((2.0, 0.0, -2.0, -5.0, -9.0))]
    # Tight actuator limits (proposals partly outside them): limit rows active.
    parts += [rcbf_like_batch(64, 6, 10 + seed, offset=offset, u_limit=1.2)
              for seed, offset in enumerate((3.0, -0.5))]
    return tuple(torch.cat(items) for items in zip(*parts))


def regimes(P, q, G, h, sol: QPSolution) -> dict[str, torch.Tensor]:
    """Boolean masks (B,) per regime, from the solution."""
    lam_scale = 1.0 + sol.lam.abs().amax(-1, keepdim=True)
    active = sol.lam > 1e-8 * lam_scale
    n_barriers = G.shape[1] - 4
    limit_active = active[:, n_barriers:].any(-1)
    slack = sol.z[:, -1]
    return {
        'none': ~active.any(-1),
        'actuator_limit': limit_active & (slack.abs() < 1e-2),
        'slack': slack > 0.1,
        'several': active.sum(-1) >= 2,
    }


def well_separated(G, h, sol: QPSolution, margin: float = 1e-3) -> torch.Tensor:
    """(B,) samples whose active set is stable under small perturbations."""
    slack_rows = h - torch.einsum('bcn,bn->bc', G, sol.z)
    active = slack_rows < 1e-9 * (1 + h.abs())
    ok_active = torch.where(active, sol.lam > margin, torch.ones_like(active))
    ok_inactive = torch.where(active, torch.ones_like(active), slack_rows > margin)
    independent = active.sum(-1) <= G.shape[-1]
    return ok_active.all(-1) & ok_inactive.all(-1) & independent


@pytest.fixture(scope='module')
def mixed():
    P, q, G, h = pool()
    sol = solve_qp_batch_full(P, q, G, h)
    return P, q, G, h, sol


def test_every_regime_is_present(mixed):
    P, q, G, h, sol = mixed
    assert bool(sol.converged.all())
    for name, mask in regimes(P, q, G, h, sol).items():
        assert int(mask.sum()) >= 5, name


def test_kkt_residuals_vanish(mixed):
    P, q, G, h, sol = mixed
    z, lam = sol.z, sol.lam
    stationarity = torch.einsum('bij,bj->bi', P, z) + q + torch.einsum('bcn,bc->bn', G, lam)
    scale = 1.0 + lam.abs().amax(-1)
    assert float((stationarity.abs().amax(-1) / scale).max()) < 1e-9
    violation = torch.einsum('bcn,bn->bc', G, z) - h
    assert float(violation.max()) < 1e-9
    assert float(lam.min()) >= 0.0
    assert float((lam * violation).abs().max()) < 1e-8


def test_solutions_match_qpth(mixed):
    from qpth.qp import QPFunction
    P, q, G, h, sol = mixed
    empty = torch.empty(0, dtype=DT)
    z_ref = QPFunction(verbose=-1, eps=1e-13, maxIter=100)(P, q, G, h, empty, empty)
    assert float((z_ref - sol.z).abs().max()) < 1e-6


def test_solutions_match_proxsuite(mixed):
    import proxsuite
    P, q, G, h, sol = mixed
    for b in range(q.shape[0]):
        solver = proxsuite.proxqp.dense.QP(3, 0, h.shape[1])
        solver.settings.eps_abs = 1e-11
        solver.settings.eps_rel = 0.0
        solver.init(P[b].numpy(), q[b].numpy(), None, None, G[b].numpy(),
                    np.full(h.shape[1], -1e20), h[b].numpy())
        solver.solve()
        assert np.abs(np.asarray(solver.results.x) - sol.z[b].numpy()).max() < 1e-6, b


def test_solutions_match_cvxpy(mixed):
    import cvxpy as cp
    P, q, G, h, sol = mixed
    for b in range(0, q.shape[0], 7):
        z = cp.Variable(3)
        problem = cp.Problem(cp.Minimize(0.5 * cp.quad_form(z, P[b].numpy()) + q[b].numpy() @ z),
                             [G[b].numpy() @ z <= h[b].numpy()])
        problem.solve(solver=cp.CLARABEL, tol_gap_abs=1e-12, tol_gap_rel=1e-12,
                      tol_feas=1e-12)
        assert np.abs(z.value - sol.z[b].numpy()).max() < 1e-6, b


def test_interior_point_alone_matches_qpth(mixed):
    """polish=False: the bare interior point (the fallback path) to its tolerance."""
    from qpth.qp import QPFunction
    P, q, G, h, _ = mixed
    sol = solve_qp_batch_full(P, q, G, h, polish=False, tol=1e-10)
    assert bool(sol.converged.all())
    assert int(sol.iterations.min()) > 0
    empty = torch.empty(0, dtype=DT)
    z_ref = QPFunction(verbose=-1, eps=1e-13, maxIter=100)(P, q, G, h, empty, empty)
    assert float((z_ref - sol.z).abs().max()) < 1e-6


@pytest.mark.parametrize('guess_rounds', [None, 1])
def test_hard_samples_are_exact(monkeypatch, guess_rounds):
    """Conflicting barriers (three active rows, multipliers ~1e7), solved by the active-set
    rounds (default) and, with the rounds cut to the unconstrained one, by the interior point
    + seeded polish route: both must return the exact KKT point."""
    from rcbf_ros.core import diffqp
    if guess_rounds is not None:
        monkeypatch.setattr(diffqp, '_GUESS_ROUNDS', guess_rounds)
    P, q, G, h = rcbf_like_batch(128, 10, 21, offset=-20.0, slack_weight=1e6)
    sol = solve_qp_batch_full(P, q, G, h)
    assert bool(sol.converged.all())
    if guess_rounds == 1:
        assert bool((sol.iterations > 0).all())
    # qpth, proxsuite and Clarabel all stall on these: compare against exhaustive
    # active-set enumeration instead.
    z_ref = enumerate_active_sets(*(x.numpy() for x in (P, q, G, h)))
    assert not np.isnan(z_ref).any()
    assert np.abs(z_ref - sol.z.numpy()).max() < 1e-6 * (1 + np.abs(z_ref).max())


@pytest.mark.parametrize('slack_weight, u_limit, offset, seed', [
    (1e6, 0.5, -5.0, 1), (1e6, 0.5, 0.0, 2), (1e6, 2.5, -5.0, 3), (1e3, 0.5, -1.0, 4),
])
def test_stiff_slack_and_tight_limits_against_enumeration(slack_weight, u_limit, offset, seed):
    """l up to 1e6 with tight limits: relative error <= 1e-6 against exhaustive enumeration,
    and relative KKT residuals near zero everywhere (also where the enumeration, at its fixed
    tolerances, finds no KKT point)."""
    P, q, G, h = rcbf_like_batch(128, 6, 100 + seed, offset=offset, slack_weight=slack_weight,
                                 u_limit=u_limit)
    sol = solve_qp_batch_full(P, q, G, h)
    assert bool(sol.converged.all())
    z_ref = enumerate_active_sets(*(x.numpy() for x in (P, q, G, h)))
    found = ~np.isnan(z_ref).any(-1)
    assert found.mean() > 0.9
    rel = np.abs(z_ref - sol.z.numpy()).max(-1) / (1 + np.abs(z_ref).max(-1))
    assert rel[found].max() < 1e-6
    lam_size = 1 + sol.lam.abs().amax(-1)
    stationarity = (torch.einsum('bij,bj->bi', P, sol.z) + q
                    + torch.einsum('bcn,bc->bn', G, sol.lam)).abs().amax(-1) / lam_size
    slack_rows = torch.einsum('bcn,bn->bc', G, sol.z) - h
    assert float(stationarity.max()) < 1e-7
    assert float(slack_rows.max()) < 1e-8 * (1 + float(h.abs().max()))
    assert float(((sol.lam * slack_rows).abs().amax(-1) / lam_size).max()) < 1e-7


def test_solution_without_active_rows_is_unconstrained_minimiser():
    P, q, G, h = rcbf_like_batch(32, 5, 3, offset=50.0)
    z = solve_qp_batch(P, q, G, h)
    torch.testing.assert_close(z, -torch.linalg.solve(P, q), atol=1e-12, rtol=0)


def _pick(mask: torch.Tensor, count: int) -> torch.Tensor:
    index = mask.nonzero().squeeze(-1)
    assert index.numel() >= count
    return index[:count]


@pytest.mark.parametrize('regime', ['none', 'actuator_limit', 'slack', 'several'])
def test_gradcheck_in_each_regime(mixed, regime):
    P, q, G, h, sol = mixed
    mask = regimes(P, q, G, h, sol)[regime] & well_separated(G, h, sol)
    idx = _pick(mask, 3)
    inputs = tuple(x[idx].clone().requires_grad_(True) for x in (P, q, G, h))

    def z_and_lam(P_, q_, G_, h_):
        out = solve_qp_batch_full(P_, q_, G_, h_, tol=1e-12)
        return out.z, out.lam

    assert torch.autograd.gradcheck(z_and_lam, inputs, eps=1e-6, atol=1e-5, rtol=1e-4)


def test_gradients_match_qpth(mixed):
    from qpth.qp import QPFunction
    P, q, G, h, sol = mixed
    idx = _pick(well_separated(G, h, sol), 64)
    weights = torch.randn(64, 3, generator=torch.Generator().manual_seed(7), dtype=DT)
    empty = torch.empty(0, dtype=DT)
    grads = []
    for solve in (lambda *a: solve_qp_batch(*a),
                  lambda *a: QPFunction(verbose=-1, eps=1e-13, maxIter=100)(*a, empty, empty)):
        leaves = [x[idx].clone().requires_grad_(True) for x in (P, q, G, h)]
        (solve(*leaves) * weights).sum().backward()
        grads.append([leaf.grad for leaf in leaves])
    for name, ours, ref in zip('PqGh', *grads):
        # qpth returns the symmetric part for P, as we do.
        assert float((ours - ref).abs().max()) < 1e-6 * (1 + float(ref.abs().max())), name


def test_gradients_match_cvxpylayers(mixed):
    import cvxpy as cp
    from cvxpylayers.torch import CvxpyLayer
    P, q, G, h, sol = mixed
    idx = _pick(well_separated(G, h, sol), 16)
    nc = h.shape[1]
    z = cp.Variable(3)
    q_p, G_p, h_p = cp.Parameter(3), cp.Parameter((nc, 3)), cp.Parameter(nc)
    problem = cp.Problem(cp.Minimize(0.5 * cp.quad_form(z, P[0].numpy()) + q_p @ z),
                         [G_p @ z <= h_p])
    layer = CvxpyLayer(problem, parameters=[q_p, G_p, h_p], variables=[z])
    # diffcp (conic reformulation); SCS at tight tolerances is its accurate backend here.
    args = {'solve_method': 'SCS', 'eps_abs': 1e-11, 'eps_rel': 1e-11, 'max_iters': 200000,
            'mode': 'dense'}
    weights = torch.randn(16, 3, generator=torch.Generator().manual_seed(8), dtype=DT)
    grads = []
    for solve in (lambda q_, G_, h_: solve_qp_batch(P[idx], q_, G_, h_),
                  lambda q_, G_, h_: layer(q_, G_, h_, solver_args=args)[0]):
        leaves = [x[idx].clone().requires_grad_(True) for x in (q, G, h)]
        (solve(*leaves) * weights).sum().backward()
        grads.append([leaf.grad for leaf in leaves])
    for name, ours, ref in zip('qGh', *grads):
        assert float((ours - ref).abs().max()) < 1e-6 * (1 + float(ref.abs().max())), name


def test_closed_form_single_barrier():
    """min |u|^2 + l eps^2 s.t. a^T u + eps >= c (c > 0): u = a c / D, eps = c / (l D),
    D = |a|^2 + 1/l;  du/da = c (I / D - 2 a a^T / D^2),  du/dc = a / D."""
    l_weight = 50.0
    a = torch.tensor([[0.7, -1.3]], dtype=DT, requires_grad=True)
    c = torch.tensor([1.9], dtype=DT, requires_grad=True)
    P = torch.diag(torch.tensor([2.0, 2.0, 2.0 * l_weight], dtype=DT))
    q = torch.zeros(1, 3, dtype=DT)

    def safe_input(a_, c_):
        G = torch.cat([-a_, -torch.ones(1, 1, dtype=DT)], dim=1).unsqueeze(0)
        return solve_qp_batch(P, q, G, -c_.unsqueeze(0))

    z = safe_input(a, c)[0]
    a0, c0 = a.detach()[0], c.detach()[0]
    D = a0 @ a0 + 1.0 / l_weight
    torch.testing.assert_close(z[:2], a0 * c0 / D, atol=1e-12, rtol=0)
    torch.testing.assert_close(z[2], c0 / (l_weight * D), atol=1e-12, rtol=0)
    jac_a, jac_c = torch.autograd.functional.jacobian(safe_input, (a, c))
    expected_a = c0 * (torch.eye(2, dtype=DT) / D - 2 * torch.outer(a0, a0) / D ** 2)
    torch.testing.assert_close(jac_a[0, :2, 0, :], expected_a, atol=1e-10, rtol=0)
    torch.testing.assert_close(jac_c[0, :2, 0], a0 / D, atol=1e-10, rtol=0)


def test_degenerate_rows_give_finite_values_and_gradients():
    """Duplicated barrier rows (LICQ fails) and a weakly active row: no NaN anywhere."""
    P, q, G, h = rcbf_like_batch(16, 3, 11, offset=-3.0)
    G = torch.cat([G, G[:, :1]], dim=1)
    h = torch.cat([h, h[:, :1]], dim=1)
    h[:, 1] = torch.einsum('bn,bn->b', G[:, 1], solve_qp_batch(P, q, G, h))
    G.requires_grad_(True)
    h.requires_grad_(True)
    sol = solve_qp_batch_full(P, q, G, h)
    (sol.z.sum() + sol.lam.sum()).backward()
    assert bool(sol.converged.all())
    for value in (sol.z, sol.lam, G.grad, h.grad):
        assert bool(torch.isfinite(value).all())


def test_infeasible_sample_is_reported_not_nan():
    P = torch.eye(2, dtype=DT).expand(3, 2, 2)
    q = torch.zeros(3, 2, dtype=DT)
    G = torch.tensor([[1.0, 0.0], [-1.0, 0.0]], dtype=DT).expand(3, 2, 2)
    h = torch.tensor([[1.0, 1.0], [-1.0, -1.0], [0.5, 0.5]], dtype=DT)  # row 1: x <= -1, x >= 1
    sol = solve_qp_batch_full(P, q, G, h, max_iter=30)
    assert sol.converged.tolist() == [True, False, True]
    assert bool(torch.isfinite(sol.z[[0, 2]]).all())


def test_shared_matrices_broadcast_and_float32_roundtrip():
    P, q, G, h = rcbf_like_batch(8, 4, 5, offset=-1.0)
    z_batched = solve_qp_batch(P, q, G, h)
    z_shared = solve_qp_batch(P[0], q, G, h)
    z_shared_g = solve_qp_batch(P, q, G[0], h)
    torch.testing.assert_close(z_shared_g, solve_qp_batch(P, q, G[0].expand(8, -1, -1), h),
                               atol=1e-12, rtol=0)
    torch.testing.assert_close(z_shared, z_batched, atol=1e-12, rtol=0)
    z32 = solve_qp_batch(P.float(), q.float(), G.float(), h.float())
    assert z32.dtype == torch.float32
    torch.testing.assert_close(z32.double(), z_batched, atol=1e-5, rtol=0)
    assert z_shared.dtype == DT


@pytest.mark.parametrize('field, args', [
    ('P', (torch.eye(3, dtype=DT)[None], torch.zeros(1, 2, dtype=DT),
           torch.zeros(1, 4, 2, dtype=DT), torch.ones(1, 4, dtype=DT))),
    ('G', (torch.eye(3, dtype=DT)[None], torch.zeros(1, 3, dtype=DT),
           torch.zeros(1, 4, 2, dtype=DT), torch.ones(1, 4, dtype=DT))),
    ('h', (torch.eye(3, dtype=DT)[None], torch.zeros(1, 3, dtype=DT),
           torch.zeros(1, 4, 3, dtype=DT), torch.full((1, 4), float('nan'), dtype=DT))),
    ('P', (-torch.eye(3, dtype=DT)[None], torch.zeros(1, 3, dtype=DT),
           torch.zeros(1, 4, 3, dtype=DT), torch.ones(1, 4, dtype=DT))),
])
def test_bad_input_names_the_field(field, args):
    with pytest.raises((ValueError, TypeError), match=rf'^{field}:'):
        solve_qp_batch(*args)
