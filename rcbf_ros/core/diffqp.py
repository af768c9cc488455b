"""Batched differentiable QP layer specialised to the small RCBF-QP of the paper.

Solves, for every sample of a minibatch, min 1/2 z^T P z + q^T z s.t. G z <= h (P positive
definite; the standard form of ``rcbf_ros.core.qp``) and differentiates z* and the multipliers
by implicit differentiation of the KKT conditions (OptNet), as the paper's differentiable
safety layer requires. The problems are tiny (3 unknowns, 4-25 rows), so it works by exact
KKT-checked active-set rounds, an interior point method for the samples they leave open, and
closed forms where P is diagonal; non-convergence is reported per sample, never as NaN.

Design notes (the stages, scaling, degenerate points): docs/DESIGN.md#the-differentiable-qp
"""
from __future__ import annotations

import math
from typing import Any, NamedTuple

import torch
from torch import Tensor

from rcbf_ros.core.torch_import import bind_torch

__all__ = ['QPSolution', 'solve_qp_batch', 'solve_qp_batch_full']

bind_torch()  # torch is here: the constraint modules that wait for it get it now

_REGULARISATION = 1e-9
"""delta of the regularised KKT system in scaled units (unit Hessian diagonal, unit rows)."""
_REFINEMENT_STEPS = 5
"""At most this many iterative refinement steps against the unregularised KKT system (each
shrinks the error by about delta / lambda_min(A P^-1 A^T)); fewer once at rounding level."""


class QPSolution(NamedTuple):
    """Solution of a batch of QPs  min 1/2 z^T P z + q^T z  s.t.  G z <= h."""

    z: Tensor
    """(B, nz) primal solution; differentiable in P, q, G, h."""
    lam: Tensor
    """(B, nc) inequality multipliers (>= 0, zero on inactive rows); differentiable."""
    iterations: Tensor
    """(B,) int64 interior point iterations each sample needed."""
    converged: Tensor
    """(B,) bool: the sample met the tolerance (after polishing or by the interior point)."""


def _check_inputs(P: Tensor, q: Tensor, G: Tensor, h: Tensor
                  ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Validate shapes and broadcast shared P, G (2-D) or q, h (1-D) to the batch."""
    named = {'P': P, 'q': q, 'G': G, 'h': h}
    for name, value in named.items():
        if not isinstance(value, Tensor):
            raise TypeError(f'{name}: expected a torch.Tensor, got {type(value).__name__}')
        if not value.is_floating_point():
            raise TypeError(f'{name}: expected a floating point tensor, got {value.dtype}')
    expected_dims = {'P': 3, 'q': 2, 'G': 3, 'h': 2}
    for name, value in named.items():
        if value.dim() not in (expected_dims[name], expected_dims[name] - 1):
            raise ValueError(f'{name}: expected {expected_dims[name]} dims (batched) or '
                             f'{expected_dims[name] - 1} (shared), got shape {tuple(value.shape)}')
    batched = [v.shape[0] for n, v in named.items() if v.dim() == expected_dims[n]]
    if not batched:
        raise ValueError('P, q, G, h: at least one must carry the batch dimension')
    batch = max(batched)
    for name, value in named.items():
        if value.dim() == expected_dims[name] and value.shape[0] != batch:
            raise ValueError(f'{name}: batch size {value.shape[0]} != {batch}')
    P = P.expand(batch, *P.shape[-2:]) if P.dim() == 2 else P
    q = q.expand(batch, q.shape[-1]) if q.dim() == 1 else q
    G = G.expand(batch, *G.shape[-2:]) if G.dim() == 2 else G
    h = h.expand(batch, h.shape[-1]) if h.dim() == 1 else h
    nz, nc = q.shape[-1], h.shape[-1]
    if P.shape[-2:] != (nz, nz):
        raise ValueError(f'P: expected (B, {nz}, {nz}) to match q: (B, {nz}), got '
                         f'{tuple(P.shape)}')
    if G.shape[-2:] != (nc, nz):
        raise ValueError(f'G: expected (B, {nc}, {nz}) to match h: (B, {nc}) and q, got '
                         f'{tuple(G.shape)}')
    if nc == 0:
        raise ValueError('G, h: need at least one inequality constraint')
    # One synchronising check for the common case: a sum of entries is finite unless an entry
    # is not (or finite entries overflow it: the exact test below then decides), and P's
    # diagonal must be > 0 (a NaN fails that too). A batch-shared P or q (2-D / 1-D input, or
    # expanded) is checked once.
    parts = [_distinct(value.detach()) for value in (P, q, G, h)]
    diag = torch.diagonal(parts[0], dim1=-2, dim2=-1)
    *sums, smallest = torch.stack([*(part.sum() for part in parts), diag.amin()]).tolist()
    if not (all(math.isfinite(total) for total in sums) and smallest > 0):
        for name, part in zip(('P', 'q', 'G', 'h'), parts):
            if not bool(torch.isfinite(part).all()):
                raise ValueError(f'{name}: contains NaN or inf')
        if not bool((diag > 0).all()):
            raise ValueError('P: must be positive definite (found a diagonal entry <= 0)')
    return P, q, G, h


def _shared(value: Tensor) -> bool:
    """Whether every sample of the batched ``value`` is the same memory (an expanded view,
    batch stride 0), so that its per-sample work can be done once."""
    return value.shape[0] > 1 and value.stride(0) == 0


def _distinct(value: Tensor) -> Tensor:
    """``value`` with a batch-shared leading dimension (:func:`_shared`) cut to one sample."""
    return value[:1] if _shared(value) else value


def _schur(P: Tensor, G: Tensor, weights: Tensor) -> Tensor:
    """P + G^T diag(weights) G.  P: (B, n, n), G: (B, m, n), weights: (B, m) -> (B, n, n)."""
    return P + torch.matmul(G.mT, weights.unsqueeze(-1) * G)


def _cholesky(M: Tensor) -> Tensor:
    """Batched Cholesky factor of SPD M: (B, n, n), with diagonal jitter where it fails."""
    factor, info = torch.linalg.cholesky_ex(M)
    if bool((info > 0).any()):
        failed = info > 0
        scale = torch.diagonal(M, dim1=-2, dim2=-1).abs().amax(-1).clamp_min(1.0)
        eye = torch.eye(M.shape[-1], dtype=M.dtype, device=M.device)
        jitter = (1e-12 * scale)[:, None, None] * eye
        for _ in range(6):
            retry, info_retry = torch.linalg.cholesky_ex(M + jitter)
            factor = torch.where(failed[:, None, None], retry, factor)
            failed = failed & (info_retry > 0)
            if not bool(failed.any()):
                break
            jitter = jitter * 1e3
    return factor


def _chol_solve(factor: Tensor, rhs: Tensor) -> Tensor:
    """Solve (L L^T) x = rhs.  factor: (B, n, n), rhs: (B, n) -> (B, n)."""
    return torch.cholesky_solve(rhs.unsqueeze(-1), factor).squeeze(-1)


def _matvec(A: Tensor, x: Tensor) -> Tensor:
    """A x for A: (B, m, n), x: (B, n) -> (B, m)."""
    return torch.matmul(A, x.unsqueeze(-1)).squeeze(-1)


def _rmatvec(A: Tensor, y: Tensor) -> Tensor:
    """A^T y for A: (B, m, n), y: (B, m) -> (B, n)."""
    return torch.matmul(y.unsqueeze(-2), A).squeeze(-2)


def _step_to_boundary(s: Tensor, lam: Tensor, ds: Tensor, dlam: Tensor) -> Tensor:
    """Largest a in [0, 1] keeping s + a ds >= 0 and lam + a dlam >= 0.  (B, m) x 4 -> (B,).

    NaN anywhere in a sample's step gives NaN (a non-finite step is detected by the caller).
    """
    value = torch.cat([s, lam], dim=-1)
    step = torch.cat([ds, dlam], dim=-1)
    ratio = torch.where(step < 0, -value / step, 1.0).amin(-1).clamp(max=1.0)
    return torch.where(torch.isnan(step).any(-1), torch.nan, ratio)


def _interior_point(P: Tensor, q: Tensor, G: Tensor, h: Tensor, tol: float, max_iter: int,
                    start: tuple[Tensor, Tensor, Tensor] | None = None
                    ) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """Batched Mehrotra predictor-corrector on the scaled problem.

    start: optional (z, s, lam) to continue from (s, lam > 0).
    Returns z: (B, n), s: (B, m), lam: (B, m), iterations: (B,), converged: (B,).
    """
    batch, m, _ = G.shape
    if start is not None:
        z, s, lam = start
    else:
        # Start (CVXOPT's rule): z0 = argmin 1/2 z'Pz + q'z + 1/2 ||G z - h||^2, then shift the
        # slack s0 = h - G z0 and the multiplier estimate lam0 = G z0 - h into the positive
        # orthant.
        ones = torch.ones_like(h)
        z = _chol_solve(_cholesky(_schur(P, G, ones)), -q + _rmatvec(G, h))
        s = h - _matvec(G, z)
        lam = -s
        s_low = -s.amin(-1, keepdim=True)
        s = torch.where(s_low >= 0, s + 1.0 + s_low, s)
        lam_low = -lam.amin(-1, keepdim=True)
        lam = torch.where(lam_low >= 0, lam + 1.0 + lam_low, lam)
        s = s.clamp_min(1e-8)
        lam = lam.clamp_min(1e-8)
        # Centring shift (Nocedal & Wright, sec. 14.2 start heuristic): balances the products
        # s_i lam_i; without it Mehrotra's method stalls on a few badly centred samples.
        gap = (s * lam).sum(-1, keepdim=True)
        s, lam = (s + 0.5 * gap / lam.sum(-1, keepdim=True),
                  lam + 0.5 * gap / s.sum(-1, keepdim=True))

    z_out, s_out, lam_out = torch.empty_like(z), torch.empty_like(s), torch.empty_like(lam)
    iterations = torch.full((batch,), max_iter, dtype=torch.int64, device=q.device)
    converged = torch.zeros(batch, dtype=torch.bool, device=q.device)
    # Working set: only samples still iterating; finished ones are written out and dropped, so
    # the tail of slow samples costs what a small batch costs.
    index = torch.arange(batch, device=q.device)
    # Constant parts of the stopping scales, computed once (and shrunk with the working set).
    q_size = q.abs().amax(-1)
    h_size = h.abs().amax(-1)
    work = [P, q, G, h, q_size, h_size, z, s, lam]
    for iteration in range(max_iter + 1):
        P_w, q_w, G_w, h_w, q_size_w, h_size_w, z, s, lam = work
        # Relative stopping test: residuals against the size of the terms they balance.
        Pz, Gt_lam, Gz = _matvec(P_w, z), _rmatvec(G_w, lam), _matvec(G_w, z)
        r_dual = Pz + q_w + Gt_lam
        r_primal = Gz + s - h_w
        s_lam = s * lam
        gap = s_lam.sum(-1)
        scale_dual = 1.0 + torch.maximum(torch.maximum(Pz.abs().amax(-1), q_size_w),
                                         Gt_lam.abs().amax(-1))
        scale_primal = 1.0 + torch.maximum(Gz.abs().amax(-1), h_size_w)
        scale_gap = 1.0 + (z * (Pz + q_w)).sum(-1).abs()
        done = ((r_dual.abs().amax(-1) <= tol * scale_dual)
                & (r_primal.abs().amax(-1) <= tol * scale_primal)
                & (gap <= tol * scale_gap))
        if iteration == max_iter:
            done = torch.ones_like(done)
        if bool(done.any()):
            finished = index[done]
            z_out[finished], s_out[finished], lam_out[finished] = z[done], s[done], lam[done]
            if iteration < max_iter:
                iterations[finished] = iteration
                converged[finished] = True
            keep = ~done
            if not bool(keep.any()):
                break
            index = index[keep]
            work = [x[keep] for x in work]
            P_w, q_w, G_w, h_w, q_size_w, h_size_w, z, s, lam = work
            r_dual, r_primal, s_lam, gap = r_dual[keep], r_primal[keep], s_lam[keep], gap[keep]
        mu = gap / m
        weights = lam / s
        factor = _cholesky(_schur(P_w, G_w, weights))
        # Newton step on the reduced system; ds, dlam recovered from the eliminated rows:
        #   ds = -r_primal - G dz,   dlam = (-r_comp - lam o ds) / s.
        dz = _chol_solve(factor, _rmatvec(G_w, lam - weights * r_primal) - r_dual)
        ds = -r_primal - _matvec(G_w, dz)
        dlam = -lam - weights * ds
        alpha_aff = _step_to_boundary(s, lam, ds, dlam).unsqueeze(-1)
        mu_aff = ((s + alpha_aff * ds) * (lam + alpha_aff * dlam)).mean(-1)
        sigma = (mu_aff / mu).clamp(0.0, 1.0) ** 3
        # Corrector with the second order term ds_aff o dlam_aff and centring sigma mu.
        r_comp = s_lam + ds * dlam - (sigma * mu).unsqueeze(-1)
        dz = _chol_solve(factor, _rmatvec(G_w, (r_comp - lam * r_primal) / s) - r_dual)
        ds = -r_primal - _matvec(G_w, dz)
        dlam = (-r_comp - lam * ds) / s
        alpha = 0.99 * _step_to_boundary(s, lam, ds, dlam).unsqueeze(-1)
        z_new, s_new, lam_new = z + alpha * dz, s + alpha * ds, lam + alpha * dlam
        if not bool(torch.isfinite(alpha).all()):
            # An infeasible sample drives lam to infinity: keep its last finite iterate (it is
            # then reported as not converged) instead of letting NaN in.
            finite = torch.isfinite(alpha)
            z_new = torch.where(finite, z_new, z)
            s_new = torch.where(finite, s_new, s)
            lam_new = torch.where(finite, lam_new, lam)
        work[6], work[7], work[8] = z_new, s_new.clamp_min(1e-300), lam_new.clamp_min(1e-300)
    z, s, lam = z_out, s_out, lam_out
    return z, s, lam, iterations, converged


def _kkt_solve(P: Tensor, G: Tensor, active: Tensor, rhs_z: Tensor, rhs_nu: Tensor
               ) -> tuple[Tensor, Tensor]:
    """Solve the active-set KKT system, iteratively refined, via nz x nz Cholesky.

        [P        G^T D_a] [x ]   [rhs_z ]        D_a = diag(active),
        [D_a G   -(I-D_a)] [nu] = [rhs_nu]        (inactive rows: nu_i = -rhs_nu_i = 0)

    Each refinement step solves the system with -delta I added on the active block, whose
    elimination nu = (G_a x - rhs_nu) / delta leaves (P + G_a^T G_a / delta) x = ...

    P: (B, n, n), G: (B, m, n), active: (B, m) bool, rhs_z: (B, n), rhs_nu: (B, m) (zero on
    inactive rows). Returns x: (B, n), nu: (B, m) (zero on inactive rows).
    """
    delta = _REGULARISATION
    mask = active.to(P.dtype)
    Ga = mask.unsqueeze(-1) * G
    factor = _cholesky(P + torch.matmul(Ga.mT, Ga) / delta)

    def regularised_solve(res_z: Tensor, res_nu: Tensor) -> tuple[Tensor, Tensor]:
        x = _chol_solve(factor, res_z + _rmatvec(Ga, res_nu) / delta)
        return x, (_matvec(Ga, x) - res_nu) / delta

    x, nu = regularised_solve(rhs_z, rhs_nu)
    rhs_size = torch.maximum(rhs_z.abs().amax(-1), rhs_nu.abs().amax(-1))
    for _ in range(_REFINEMENT_STEPS):
        Gt_nu = _rmatvec(Ga, nu)
        res_z = rhs_z - _matvec(P, x) - Gt_nu
        res_nu = rhs_nu - _matvec(Ga, x)
        # Stop once the unregularised residual is at rounding level for every sample.
        size = 1.0 + torch.maximum(rhs_size, Gt_nu.abs().amax(-1))
        residual = torch.maximum(res_z.abs().amax(-1), res_nu.abs().amax(-1))
        if bool((residual <= 1e-14 * size).all()):
            break
        dx, dnu = regularised_solve(res_z, res_nu)
        x, nu = x + dx, nu + dnu
    return x, nu * mask


def _kkt_solve_one_row(diagonal: Tensor, G: Tensor, active: Tensor, rhs_z: Tensor,
                       rhs_nu: Tensor) -> tuple[Tensor, Tensor]:
    """:func:`_kkt_solve` in closed form for diagonal P and at most one active row per sample.

    With P = diag(d) and the single active row a: x = (rhs_z - a nu) / d and a x = rhs_nu give
    nu = (a (rhs_z / d) - rhs_nu) / (a (a / d)); without an active row x = rhs_z / d, nu = 0.
    No regularisation; one step of iterative refinement on the row's residual (large row norms
    against a small diagonal otherwise leave it above the rounding level the general solve's
    refinement reaches). A zero row yields a non-finite x, which the callers' acceptance test
    rejects.

    diagonal: (B, n) > 0, G: (B, m, n), active: (B, m) bool with at most one True per sample,
    rhs_z: (B, n), rhs_nu: (B, m). Returns x: (B, n), nu: (B, m) (zero on inactive rows).
    """
    mask = active.to(G.dtype)
    row = _rmatvec(G, mask)
    has_row = active.any(-1, keepdim=True)
    x_free = rhs_z / diagonal
    scaled = row / diagonal
    gram = (row * scaled).sum(-1, keepdim=True)
    target = (rhs_nu * mask).sum(-1, keepdim=True)

    def correction(x: Tensor) -> Tensor:
        """(a x - rhs_nu) / gram: the multiplier that moves x onto the row."""
        return torch.where(has_row, ((row * x).sum(-1, keepdim=True) - target) / gram, 0.0)

    nu = correction(x_free)
    x = x_free - scaled * nu
    # One refinement step on the row's own residual (what the rounding of gram and of x
    # left), as in the two-row form.
    step = correction(x)
    return x - scaled * step, (nu + step) * mask


_TWO_ROW_CONDITION = 1e-6
"""The two-row closed form is taken where det M / (M_11 M_22), the squared sine of the angle
between the two rows (in the metric P^-1), exceeds this; below, the rows are close to dependent
(LICQ nearly fails) and the regularised general solve decides."""


def _kkt_solve_two_rows(diagonal: Tensor, G: Tensor, active: Tensor, rhs_z: Tensor,
                        rhs_nu: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """:func:`_kkt_solve` in closed form for diagonal P and at most two active rows per sample.

    With P = D = diag(d) and the active rows A (up to two), x = D^-1 (rhs_z - A^T nu) and
    A x = rhs_nu give the 2 x 2 system M nu = A D^-1 rhs_z - rhs_nu, M = A D^-1 A^T, solved by
    its explicit inverse and one step of iterative refinement on the rows' residual (to the
    rounding level the general solve's refinement reaches); a missing row is a unit row of
    M with a zero right-hand side (its multiplier 0). No regularisation is needed where M is
    well conditioned; elsewhere, and where the result is not finite, ``ok`` is False and the
    caller solves those samples with :func:`_kkt_solve`.

    diagonal: (B, n) > 0, G: (B, m, n), active: (B, m) bool with at most two True per sample,
    rhs_z: (B, n), rhs_nu: (B, m). Returns x: (B, n), nu: (B, m) (zero on inactive rows), ok:
    (B,) bool.
    """
    n = G.shape[-1]
    picked = torch.topk(active.to(G.dtype), min(2, active.shape[-1]), dim=-1).indices
    on = active.gather(1, picked)
    if picked.shape[-1] == 1:
        picked, on = torch.cat([picked, picked], dim=1), torch.cat([on, torch.zeros_like(on)],
                                                                   dim=1)
    present = on.to(G.dtype)
    rows = G.gather(1, picked.unsqueeze(-1).expand(-1, -1, n)) * present.unsqueeze(-1)
    scaled = rows / diagonal.unsqueeze(1)                      # A D^-1: (B, 2, n)
    gram = torch.matmul(scaled, rows.mT) + torch.diag_embed(1.0 - present)
    free = rhs_z / diagonal
    right = _matvec(rows, free) - rhs_nu.gather(1, picked) * present
    a, b, c = gram[:, 0, 0], gram[:, 0, 1], gram[:, 1, 1]
    det = a * c - b * b
    inverse = torch.stack([torch.stack([c, -b], -1), torch.stack([-b, a], -1)], -2) / det[:, None,
                                                                                          None]
    nu = _matvec(inverse, right)
    x = free - _rmatvec(scaled, nu)
    # One refinement step on the rows' own residual A x - rhs_nu (what the rounding of M and of
    # x left): nu += M^-1 (A x - rhs_nu), x -= D^-1 A^T (that change).
    step = _matvec(inverse, _matvec(rows, x) - rhs_nu.gather(1, picked) * present)
    nu = nu + step
    x = x - _rmatvec(scaled, step)
    ok = ((det > _TWO_ROW_CONDITION * a * c) & torch.isfinite(x).all(-1)
          & torch.isfinite(nu).all(-1))
    nu_full = torch.zeros_like(rhs_nu).scatter_add_(1, picked, nu * present)
    return x, nu_full, ok


def _kkt_solve_diagonal(P: Tensor, diagonal: Tensor, G: Tensor, active: Tensor,
                        rhs_z: Tensor, rhs_nu: Tensor) -> tuple[Tensor, Tensor]:
    """:func:`_kkt_solve` for diagonal P: the closed forms where a sample has at most two
    active rows (:func:`_kkt_solve_two_rows`; the one-row form where no sample has more), the
    general solve for the others and where a closed form is rejected."""
    count = active.sum(-1)
    if not bool((count > 2).any()):
        if not bool((count > 1).any()):
            x, nu = _kkt_solve_one_row(diagonal, G, active, rhs_z, rhs_nu)
            ok = torch.isfinite(x).all(-1)
        else:
            x, nu, ok = _kkt_solve_two_rows(diagonal, G, active, rhs_z, rhs_nu)
        if bool(ok.all()):
            return x, nu
        rest = (~ok).nonzero().squeeze(-1)
    else:
        x, nu = torch.empty_like(rhs_z), torch.empty_like(rhs_nu)
        small = (count <= 2).nonzero().squeeze(-1)
        rest = (count > 2).nonzero().squeeze(-1)
        if small.numel():
            x_s, nu_s, ok_s = _kkt_solve_two_rows(diagonal[small], G[small], active[small],
                                                  rhs_z[small], rhs_nu[small])
            x[small], nu[small] = x_s, nu_s
            rest = torch.cat([rest, small[~ok_s]])
    x[rest], nu[rest] = _kkt_solve(P[rest], G[rest], active[rest], rhs_z[rest], rhs_nu[rest])
    return x, nu


def _active_set_rounds(P: Tensor, q: Tensor, G: Tensor, h: Tensor, tol: float, rounds: int,
                       seed: Tensor | None = None, diagonal: Tensor | None = None
                       ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Primal active-set rounds, each result accepted only where the KKT conditions hold.

    Starting from ``seed`` (the interior point's lam > s) or the empty set, a round solves the
    equality-constrained QP of the current set exactly (:func:`_kkt_solve`) and accepts the
    samples whose solution is primal feasible with nu >= 0: stationarity holds by construction,
    so that is the KKT point, i.e. the unique solution, and no guess can be accepted wrongly.
    For the others the set is corrected: rows with a negative multiplier leave, the single most
    violated row enters (rows have unit norm in the scaled problem, so violations compare), and
    a full set (nz rows) first drops the row chosen by Goldfarb-Idnani's ratio test. In the
    RCBF-QP usually zero, one or two rows are active, and the empty start settles most of a
    batch in one to three rounds (the first is the unconstrained minimiser -P^-1 q).

    P: (B, n, n), q: (B, n), G: (B, m, n) (unit rows), h: (B, m), seed: (B, m) bool or None.
    diagonal: (B, n) the diagonal of P where P is known to be diagonal (the unconstrained
    minimiser is then -q / diagonal and the second round's single row has a closed form,
    :func:`_kkt_solve_one_row`), else None.
    Returns z: (B, n), lam: (B, m), active: (B, m), ok: (B,) (z, lam, active valid where ok).
    """
    batch, _, n = G.shape
    z_out = torch.zeros_like(q)
    lam_out = torch.zeros_like(h)
    active_out = torch.zeros_like(h, dtype=torch.bool)
    ok_out = torch.zeros(batch, dtype=torch.bool, device=h.device)
    # Working set: samples not accepted yet (accepted ones are written out and dropped).
    index = torch.arange(batch, device=h.device)
    feas_tol = tol * (1.0 + h.abs().amax(-1, keepdim=True))
    first = 0
    if seed is None:
        # Round one, the unconstrained minimiser: no multiplier to check, no row to drop.
        z = -q / diagonal if diagonal is not None else _chol_solve(_cholesky(P), -q)
        violation = _matvec(G, z) - h
        ok = (violation <= feas_tol).all(-1) & torch.isfinite(z).all(-1)
        z_out = torch.where(ok.unsqueeze(-1), z, z_out)
        ok_out = ok
        keep = ~ok
        if rounds == 1 or not bool(keep.any()):
            return z_out, lam_out, active_out, ok_out
        index = index[keep]
        P, q, G, h, feas_tol = P[keep], q[keep], G[keep], h[keep], feas_tol[keep]
        if diagonal is not None:
            diagonal = diagonal[keep]
        violation = violation[keep]
        # The most violated row enters.
        active = (torch.zeros_like(h, dtype=torch.bool).scatter_(
            -1, violation.argmax(-1, keepdim=True), True) & (violation > feas_tol))
        first = 1
    else:
        active = seed.clone()
    for round_ in range(first, rounds):
        if round_ == 1 and seed is None and diagonal is not None:
            # From the empty set the second round holds at most the one added row.
            z, lam = _kkt_solve_one_row(diagonal, G, active, -q, h * active)
        elif diagonal is not None:
            z, lam = _kkt_solve_diagonal(P, diagonal, G, active, -q, h * active)
        else:
            z, lam = _kkt_solve(P, G, active, -q, h * active)
        violation = _matvec(G, z) - h
        dual_tol = tol * (1.0 + lam.abs().amax(-1, keepdim=True))
        ok = ((violation <= feas_tol).all(-1) & (lam >= -dual_tol).all(-1)
              & torch.isfinite(z).all(-1))
        if round_ == 0:
            # The working set is still the whole batch: select instead of scattering.
            ok_column = ok.unsqueeze(-1)
            z_out = torch.where(ok_column, z, z_out)
            lam_out = torch.where(ok_column, lam.clamp_min(0.0), lam_out)
            active_out = active & ok_column
            ok_out = ok
        else:
            done = index[ok]
            z_out[done], lam_out[done] = z[ok], lam[ok].clamp_min(0.0)
            active_out[done], ok_out[done] = active[ok], True
        keep = ~ok
        if round_ == rounds - 1 or not bool(keep.any()):
            break
        index = index[keep]
        P, q, G, h, feas_tol = P[keep], q[keep], G[keep], h[keep], feas_tol[keep]
        if diagonal is not None:
            diagonal = diagonal[keep]
        z, lam, active, violation = z[keep], lam[keep], active[keep], violation[keep]
        worst = violation.argmax(-1, keepdim=True)
        add = (torch.zeros_like(active).scatter_(-1, worst, True)
               & (violation > feas_tol) & ~active)
        full = (active.sum(-1, keepdim=True) >= n) & add.any(-1, keepdim=True)
        if bool(full.any()):
            # Goldfarb-Idnani's ratio test picks the row that leaves: write the new row as
            # g_p = A^T r (the KKT solve with rhs (g_p, 0) returns r as its multiplier for a
            # full set), then drop argmin_{r_j > 0} lam_j / r_j.
            g_new = G.gather(1, worst.unsqueeze(-1).expand(-1, 1, n)).squeeze(1)
            _, r = _kkt_solve(P, G, active, g_new, torch.zeros_like(h))
            ratio = torch.where(active & (r > 0), lam / r.clamp_min(1e-300), torch.inf)
            fallback = torch.where(active, lam, torch.inf)
            ratio = torch.where(torch.isinf(ratio).all(-1, keepdim=True), fallback, ratio)
            weakest = ratio.argmin(-1, keepdim=True)
            drop = torch.zeros_like(active).scatter_(-1, weakest, True) & full
        else:
            drop = torch.zeros_like(active)
        active = (active & (lam >= 0) & ~drop) | add
    return z_out, lam_out, active_out, ok_out


_GUESS_ROUNDS = 10
"""Active-set rounds from the empty set before any interior point iteration."""
_SEEDED_ROUNDS = 3
"""Active-set rounds seeded by the interior point's active set, after each interior point
stage."""
_STAGE_ITERATIONS = (6,)
"""Interior point iterations before an intermediate seeded active-set attempt; the last stage
runs to the tolerance (or max_iter)."""


def _solve_scaled(P: Tensor, q: Tensor, G: Tensor, h: Tensor, tol: float, max_iter: int,
                  polish: bool, diagonal: Tensor | None = None
                  ) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """Forward pass on the scaled problem: z, lam, iterations, converged, active (see module).

    Each step works only on the samples the previous ones left open:

    1. active-set rounds from the empty set (:func:`_active_set_rounds`), exact where accepted;
    2. interior point stages (a few iterations, then to ``tol``), each followed by active-set
       rounds seeded with the interior point's active set (the polish);
    3. where the polish never succeeds, the interior point iterate itself.

    With ``polish=False`` only the interior point runs (for testing and comparison).
    ``diagonal``: (B, n) the diagonal of P where P is diagonal (see :func:`_active_set_rounds`).
    """
    batch, m, _ = G.shape
    iterations = torch.zeros(batch, dtype=torch.int64, device=q.device)
    if polish:
        z, lam, active, converged = _active_set_rounds(P, q, G, h, tol, _GUESS_ROUNDS,
                                                       diagonal=diagonal)
        if bool(converged.all()):
            return z, lam, iterations, converged, active
        todo = (~converged).nonzero().squeeze(-1)
    else:
        z, lam = torch.zeros_like(q), torch.zeros_like(h)
        active = torch.zeros_like(h, dtype=torch.bool)
        converged = torch.zeros(batch, dtype=torch.bool, device=q.device)
        todo = torch.arange(batch, device=q.device)
    stages = (*_STAGE_ITERATIONS, max_iter) if polish else (max_iter,)
    start = None
    for stage, stage_iterations in enumerate(stages):
        if todo.numel() == 0:
            break
        P_t, q_t, G_t, h_t = P[todo], q[todo], G[todo], h[todo]
        last = stage == len(stages) - 1
        budget = stage_iterations if not last else max(max_iter - int(iterations.max()), 1)
        z_i, s_i, lam_i, it_i, conv_i = _interior_point(P_t, q_t, G_t, h_t, tol, budget,
                                                        start=start)
        iterations[todo] += it_i
        ok = torch.zeros_like(conv_i)
        if polish:
            z_g, lam_g, active_g, ok = _active_set_rounds(P_t, q_t, G_t, h_t, tol,
                                                          _SEEDED_ROUNDS, seed=lam_i > s_i)
            done = todo[ok]
            z[done], lam[done], active[done] = z_g[ok], lam_g[ok], active_g[ok]
            converged[done] = True
        rest = ~ok
        if last:
            left = todo[rest]
            z[left], lam[left], active[left] = z_i[rest], lam_i[rest], (lam_i > s_i)[rest]
            converged[left] = conv_i[rest]
            break
        todo = todo[rest]
        start = (z_i[rest], s_i[rest], lam_i[rest])
    return z, lam, iterations, converged, active


def _diagonal_of(P: Tensor) -> Tensor | None:
    """(B, n) detached diagonal of P: (B, n, n) if every off-diagonal entry is zero, else None.

    Diagonal P (the RCBF-QP's) lets the solver skip factorisations: the unconstrained minimiser,
    single-row KKT systems and the backward pass of samples without active rows have closed
    forms. A batch-shared P (:func:`_shared`) is examined once."""
    detached = P.detach()
    shared = _shared(detached)
    distinct = detached[:1] if shared else detached
    diagonal = torch.diagonal(distinct, dim1=-2, dim2=-1)
    if not torch.equal(distinct, torch.diag_embed(diagonal)):
        return None
    return diagonal.expand(P.shape[0], -1) if shared else diagonal


class _QPLayer(torch.autograd.Function):
    """autograd.Function on the scaled problem; see the module docstring.

    The forward takes ``ctx`` itself (no ``setup_context``): ``apply`` then skips binding the
    arguments to the signature, a per-call cost comparable to the whole solve of a batch
    without active rows."""

    @staticmethod
    def forward(ctx: Any, P: Tensor, q: Tensor, G: Tensor, h: Tensor, tol: float, max_iter: int,
                polish: bool, diagonal: Tensor | None
                ) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
        z, lam, iterations, converged, active = _solve_scaled(P, q, G, h, tol, max_iter, polish,
                                                              diagonal)
        ctx.mark_non_differentiable(iterations, converged, active)
        ctx.save_for_backward(P, G, z, lam, active, diagonal)
        return z, lam, iterations, converged, active

    @staticmethod
    def backward(ctx: Any, grad_z: Tensor | None, grad_lam: Tensor | None, *_: Any
                 ) -> tuple[Tensor | None, ...]:
        P, G, z, lam, active, diagonal = ctx.saved_tensors
        if grad_z is None:
            grad_z = torch.zeros_like(z)
        mask = active.to(z.dtype)
        grad_lam = torch.zeros_like(lam) if grad_lam is None else grad_lam * mask
        lam = lam * mask
        # Adjoint of the active-set KKT system K [dz; dnu] = -[dP z + dq + dG^T lam; dG_A z - dh_A]
        # (K is symmetric): K [b_z; b_nu] = [grad_z; grad_lam_A].
        if diagonal is None:
            b_z, b_nu = _kkt_solve(P, G, active, grad_z, grad_lam)
        else:
            # Diagonal P: without active rows K is P itself (b_z = grad_z / diagonal, b_nu = 0),
            # with one or two a closed form; the KKT solve only where a sample has more (or a
            # closed form is rejected).
            b_z, b_nu = _kkt_solve_diagonal(P, diagonal, G, active, grad_z, grad_lam)
        # Only the gradients autograd asks for (the RCBF-QP's P and q are constants).
        need_P, need_q, need_G = ctx.needs_input_grad[:3]
        grad_q = -b_z if need_q else None
        grad_P = -b_z.unsqueeze(-1) * z.unsqueeze(-2) if need_P else None
        grad_G = (-(lam.unsqueeze(-1) * b_z.unsqueeze(-2) + b_nu.unsqueeze(-1) * z.unsqueeze(-2))
                  if need_G else None)
        grad_h = b_nu
        return grad_P, grad_q, grad_G, grad_h, None, None, None, None


def solve_qp_batch_full(P: Tensor, q: Tensor, G: Tensor, h: Tensor, *, tol: float = 1e-9,
                        max_iter: int = 50, polish: bool = True) -> QPSolution:
    """Solve and differentiate  min 1/2 z^T P z + q^T z  s.t.  G z <= h  for a whole batch.

    Args:
        P: (B, nz, nz) symmetric positive definite (or (nz, nz) shared). Only its symmetric part
            (P + P^T) / 2 is used, so dL/dP is symmetric.
        q: (B, nz) (or (nz,) shared).
        G: (B, nc, nz) (or (nc, nz) shared); for the RCBF-QP nz = n_u + 1.
        h: (B, nc) (or (nc,) shared).
        tol: relative tolerance on the KKT residuals (and on the polished point's feasibility).
        max_iter: interior point iteration cap.
        polish: identify the active set and re-solve its equality KKT system exactly.

    Returns:
        QPSolution(z (B, nz), lam (B, nc), iterations (B,), converged (B,)) in the dtype of q;
        z and lam are differentiable w.r.t. P, q, G, h. Internally float64.
    """
    if tol <= 0:
        raise ValueError(f'tol: must be > 0, got {tol}')
    if max_iter < 1:
        raise ValueError(f'max_iter: must be >= 1, got {max_iter}')
    P, q, G, h = _check_inputs(P, q, G, h)
    out_dtype = q.dtype
    batch, nz = q.shape
    # A batch-shared P (as the RCBF-QP's; also q) is symmetrised and scaled once, then
    # expanded again: the same values as per sample.
    P, q = _distinct(P), _distinct(q)
    P, q, G, h = (x.to(torch.float64) for x in (P, q, G, h))
    P = 0.5 * (P + P.mT)
    # Detached equilibration (exact for gradients, see module docstring):
    # z = E y with E = diag(P)^-1/2, rows of G E scaled by R = 1 / ||(G E)_i||.
    col = torch.diagonal(P.detach(), dim1=-2, dim2=-1).rsqrt()
    P_s = (col.unsqueeze(-1) * P * col.unsqueeze(-2)).expand(batch, nz, nz)
    q_s = (col * q).expand(batch, nz)
    G_cols = G * col.unsqueeze(-2)
    row_norm = torch.linalg.vector_norm(G_cols.detach(), dim=-1)
    row = torch.where(row_norm > 0, 1.0 / row_norm.clamp_min(1e-300), torch.ones_like(row_norm))
    G_s = row.unsqueeze(-1) * G_cols
    h_s = row * h
    y, lam_s, iterations, converged, _ = _QPLayer.apply(P_s, q_s, G_s, h_s, tol, max_iter,
                                                        polish, _diagonal_of(P_s))
    z = col * y
    lam = row * lam_s
    return QPSolution(z.to(out_dtype), lam.to(out_dtype), iterations, converged)


def solve_qp_batch(P: Tensor, q: Tensor, G: Tensor, h: Tensor, *, tol: float = 1e-9,
                   max_iter: int = 50) -> Tensor:
    """z* (B, nz) of  min 1/2 z^T P z + q^T z  s.t.  G z <= h; see :func:`solve_qp_batch_full`."""
    return solve_qp_batch_full(P, q, G, h, tol=tol, max_iter=max_iter).z
