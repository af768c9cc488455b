"""Variance bounds of ``DisturbanceGP``: their math, the per-output choice at a refit, and the
numpy evaluation that one prediction runs.

The exact posterior variance ``s - k^T (K + nI)^-1 k`` reads one M x M factor per output and
query, most of a per-step action's cost. Each bound here (low rank, projection, a projection on
a basis shared by alike outputs, low rank plus a neighbourhood) subtracts a term that the
identity ``2 w.k - w^T (K + nI) w <= k^T (K + nI)^-1 k`` keeps below the exact one, so it is
never below the exact variance at any state, and the box ``mean +/- k_c std`` built on it holds
the exact box. At each refit every output takes the bound that reads the fewest numbers within
its tolerance. The derivations, error bounds and the choice: docs/GP_BOUNDS.md.
"""
from __future__ import annotations

from typing import Any

import numpy as np
import torch

HYBRID_RANKS = (0, 8, 16, 32, 64, 128, 256)
"""Ranks the hybrid bound is tried at, smallest (cheapest) first."""
HYBRID_COST_ROWS = 16
"""The hybrid bound's neighbourhood term costs a query about as much as this many rows of M
numbers (gathers of its factor and of k_perp on the neighbourhood)."""
PROJECTION_RANK_STEP = 8
"""The projection bound's rank is a multiple of this (or M); so is a shared basis's size."""
SHARED_COST_ROWS = 16
"""A shared projection's two more products (basis, then each output's vectors) cost a query
about as much as this many rows of M numbers."""
GEMM_BATCH = 16
"""From this many states on, ``predict_plan`` forms the kernel as one product per output
(``kernel_batch``); below, from the squared differences, exact to the last bits, as the
per-step prediction of one state always does."""


def variance_excess_ratio(*, tail: torch.Tensor, noise: torch.Tensor) -> torch.Tensor:
    """Worst-case excess of the low-rank variance bound over the exact variance, relative to
    the signal variance: ``rho(a) = max_{0<=l<=a} l (a - l) / ((l + n)(a + n))``, elementwise.

    Args:
        tail: the largest discarded eigenvalue of ``K + n I`` minus ``n`` (``a``); <= 0 gives 0.
        noise: the noise variance ``n`` (> 0), broadcast against ``tail``.

    The maximiser is ``l* = sqrt(n^2 + a n) - n``; rho grows with ``a`` from 0 (about
    ``a^2 / (4 n^2)`` for ``a << n``) towards 1.
    """
    a = tail.clamp_min(0.0)
    best = torch.sqrt(noise * noise + a * noise) - noise
    return best * (a - best) / ((best + noise) * (a + noise))


def variance_ranks(*, eigenvalues: torch.Tensor, noise: torch.Tensor,
                   tolerance: float) -> torch.Tensor:
    """Per output, the fewest leading eigenpairs whose low-rank bound is within ``tolerance``.

    Args:
        eigenvalues: (D, M) of ``K_d + n_d I``, descending.
        noise: (D,) the ``n_d``.
        tolerance: largest allowed :func:`variance_excess_ratio` (0: all M).

    Returns:
        (D,) int64 ranks r_d in [0, M]: the ratio at tail ``mu_{r+1} - n`` is <= tolerance.
    """
    ratio = variance_excess_ratio(tail=eigenvalues - noise[:, None], noise=noise[:, None])
    # rho grows with the tail eigenvalue, which falls with r: the rank is the count above.
    return (ratio > tolerance).sum(dim=-1)


def rank_groups(ranks: torch.Tensor) -> list[torch.Tensor]:
    """Outputs (indices into ``ranks``, ascending within a group) batched together: in order of
    rank, a new group starts where the rank exceeds twice the group's smallest plus 32 (one
    more group costs about as much as that many extra columns)."""
    groups: list[list[int]] = []
    smallest = 0
    for output in torch.argsort(ranks, stable=True).tolist():
        rank = int(ranks[output])
        if not groups or rank > 2 * smallest + 32:
            groups.append([])
            smallest = rank
        groups[-1].append(output)
    return [torch.tensor(sorted(group), dtype=torch.int64) for group in groups]


def bound_cost(kind: str, rank: int, points: int) -> int:
    """Rows of M numbers one query reads for a bound (the mean's row included): the measure
    the refit's choice minimises.

    Args:
        kind: 'projection', 'low_rank' or 'hybrid'.
        rank: the bound's rank.
        points: M.
    """
    if kind == 'projection':
        return rank + 1
    if kind == 'low_rank':
        return points + 1 if 2 * rank >= points else 2 * rank + 1
    if kind == 'hybrid':
        return 2 * rank + 1 + HYBRID_COST_ROWS
    raise ValueError(f'unknown bound kind {kind!r}')


Part = tuple[str, torch.Tensor, int, 'torch.Tensor | None']
"""One batch of outputs on one bound: (kind, outputs (indices into the active outputs), rank,
the hybrid bound's neighbourhood factors (D, M, m, m) or None)."""


def _part_arrays(c: dict[str, Any], kind: str, outputs: torch.Tensor, rank: int,
                 factor_t: torch.Tensor | None) -> dict[str, Any]:
    """What one part's evaluation reads besides the kernel (``predict_plan``); the projection
    and the neighbourhood (the hybrid bound at rank 0) read the kernel over s, ``k / s``."""
    eigenvalues = c['eigenvalues'][outputs]
    outputscale = c['outputscale'][outputs]
    alpha = c['alpha'][outputs].unsqueeze(-1)  # (D, M, 1)
    vectors = c['eigenvectors'][outputs, :, :rank]
    if kind == 'projection':
        # Columns s [alpha, u_1 / sqrt(mu_1), ...], (M, 1 + r): the row vector k / s times
        # them gives the mean and, contiguous, the terms whose squares the bound subtracts.
        scaled = vectors * eigenvalues[:, :rank].rsqrt().unsqueeze(-2)
        project = torch.cat([alpha, scaled], dim=-1) * outputscale[:, None, None]
        return {'kind': kind, 'rank': rank, 'project': project.contiguous().numpy()}
    if kind == 'shared_projection':
        # k / s times [V, s_1 alpha_1, ..., s_D alpha_D] (M x (R + D)): on the basis, and
        # output d's mean in column R + d; the former times each output's s q_i / sqrt(lambda_i)
        # (zero columns up to the part's largest rank): the terms.
        shared = c['shared']
        width = max(vectors.shape[-1] for vectors in shared['vectors'])
        terms = torch.stack([torch.nn.functional.pad(vectors, (0, width - vectors.shape[-1]))
                             for vectors in shared['vectors']]) * outputscale[:, None, None]
        means = (alpha[:, :, 0] * outputscale[:, None]).T
        size, count = shared['basis'].shape[-1], outputs.numel()
        return {'kind': kind, 'rank': rank, 'size': size,
                'basis': torch.cat([shared['basis'], means], dim=-1).contiguous().numpy(),
                'vectors': terms.contiguous().numpy(), 'diagonal': np.arange(count),
                # Of one state's (D, 1, R + D) product: output d's mean at [d, 0, R + d].
                'mean_index': np.arange(count) * (size + count + 1) + size}
    neighbourhood = {} if factor_t is None else {
        'neighbours': c['neighbour_index'][outputs].numpy(),
        'outputs': np.arange(outputs.numel())[:, None]}
    if kind == 'hybrid' and rank == 0:
        assert factor_t is not None
        return {'kind': 'neighbourhood', 'rank': 0, **neighbourhood,
                'project': (alpha * outputscale[:, None, None]).contiguous().numpy(),
                'factor_t': (factor_t * outputscale[:, None, None, None]).numpy()}
    # The low-rank bound, and the hybrid one above rank 0, on k itself:
    # var_r = s - sum_{i<=r} (u_i . k)^2 / mu_i - |k_perp|^2 / mu_{r+1}, k_perp = k minus its
    # projection on the kept u_i, computed as that difference (not |k|^2 - sum (u_i . k)^2,
    # which loses |k|^2 / n * eps to cancellation when n << s). Both subtracted terms are
    # >= 0 and together at most s, so the round-off stays at eps * s. One (1 + r, M) product
    # gives the mean (row 0) and the r projections u_i . k; stored row by row, so that one
    # query's product reads each row contiguously.
    n_points = eigenvalues.shape[-1]
    tail_weight = (1.0 / eigenvalues[:, rank] if rank < n_points
                   else torch.zeros(outputs.numel(), dtype=eigenvalues.dtype))
    project_t = torch.cat([alpha, vectors], dim=-1).transpose(-1, -2)
    part = {'kind': kind, 'rank': rank, 'full_rank': rank == n_points,
            'project_t': project_t.contiguous().numpy(),
            'kept_weights': (1.0 / eigenvalues[:, :rank]).numpy(),
            'tail_weight': tail_weight.numpy()[:, None],
            'outputscale': outputscale.numpy()[:, None, None]}
    if kind == 'hybrid':
        assert factor_t is not None
        part.update(neighbourhood, factor_t=factor_t.numpy())
    return part


def make_plan(c: dict[str, Any], parts: list[Part], include_noise: bool) -> dict[str, Any]:
    """The arrays one prediction on ``parts`` reads: the training inputs and every covered
    output's inverse squared lengthscales (the kernel of all outputs in one product), and per
    part its bound's rows.

    Args:
        c: the posterior's factors (``DisturbanceGP._cache``, or the one a refit builds).
        parts: the outputs' bounds; each active output in at most one part.
        include_noise: whether the prior variance includes the noise.

    Returns:
        The plan for ``predict_plan``; ``index`` (D,) the output dimensions of its rows.
    """
    order = (torch.cat([part[1] for part in parts]) if parts
             else torch.zeros(0, dtype=torch.int64))
    outputscale = c['outputscale'][order]
    base = (outputscale + c['noise'][order] if include_noise else outputscale).numpy()[:, None]
    index = c['active'].nonzero().squeeze(-1)[order].numpy()
    # The rows of a (n_out, B, 2) prediction in ``predict_plan``'s (D + 1, B, 2): an output
    # without a posterior takes the last, zero, row.
    take = np.full(c['active'].numel(), index.size)
    take[index] = np.arange(index.size)
    neg_half_w = -0.5 / c['lengthscales'][order] ** 2  # (D, n_in)
    plan = {'index': index, 'take': take,
            'identity': bool(index.size == take.size and (take == np.arange(take.size)).all()),
            'points_t': c['points'].T.contiguous().numpy(),
            'neg_half_w': neg_half_w.numpy(), 'parts': [],
            **_kernel_factors(c['points'], neg_half_w)}
    start = 0
    for kind, outputs, rank, factor_t in parts:
        end = start + outputs.numel()
        part = _part_arrays(c, kind, outputs, rank, factor_t)
        part.update(rows=slice(start, end), base=base[start:end])
        plan['parts'].append(part)
        start = end
    return plan


def _kernel_factors(points: torch.Tensor, neg_half_w: torch.Tensor) -> dict[str, np.ndarray]:
    """``kernel_batch``'s centre c (n_in,), the training points' mean, and right-hand factors
    ``[-2 w_d p'_j; sum_i w_di p'_ji^2; 1]`` (D, n_in + 2, M), p' = p - c."""
    centre = points.mean(dim=0)
    centred = (points - centre).T  # (n_in, M)
    weighted = neg_half_w[:, :, None] * centred  # (D, n_in, M)
    columns = torch.cat([-2.0 * weighted, (weighted * centred).sum(dim=1, keepdim=True),
                         torch.ones_like(weighted[:, :1])], dim=1)
    return {'centre': centre.numpy(), 'kernel_columns': columns.contiguous().numpy()}


def kernel_batch(plan: dict[str, Any], x: np.ndarray) -> np.ndarray:
    """``k / s`` (D, B, M) at x (B, n_in) as one (B, n_in + 2) x (n_in + 2, M) product per
    output, on BLAS's GEMM path: for a batch of ``GEMM_BATCH`` states or more several times
    cheaper than forming the B n_in M squared differences and then B small products.

    ``log(k_d / s_d) = sum_i w_di (x_i - p_ji)^2 = [x', 1, sum_i w_di x'_i^2]
    [-2 w_d p'_j; sum_i w_di p'_ji^2; 1]`` (w = -1/2 l^-2) on inputs less the training
    points' mean c (x' = x - c, p' = p - c: ``_kernel_factors``). The expansion's terms
    cancel: log(k / s) carries an absolute round-off of about eps sum_i |w_di| (x'_i^2 +
    p'_ji^2) (eps the float64 epsilon) besides the differences'. Where k_j is not negligible
    x lies near p_j, so that this is bounded by the training points' spread about c in
    lengthscales, whatever the query (a relative error of k of at most 3e-12 on a Car Following
    GP whose inputs spread over 60 lengthscales; ``exact_variance``'s ``rbf`` expands without
    a centre). The squared distance is clamped at 0 (log(k / s) <= 0) as ``rbf`` clamps
    it."""
    centred = x - plan['centre']  # (B, n_in)
    neg_half_w = plan['neg_half_w']  # (D, n_in)
    n_rows, n_in = neg_half_w.shape
    rows = np.empty((n_rows, x.shape[0], n_in + 2))
    rows[:, :, :n_in] = centred
    rows[:, :, n_in] = 1.0
    np.matmul(neg_half_w, (centred * centred).T, out=rows[:, :, n_in + 1])
    k_all = rows @ plan['kernel_columns']  # (D, B, M): log(k / s)
    np.minimum(k_all, 0.0, out=k_all)
    np.exp(k_all, out=k_all)
    return k_all


def low_rank_parts(c: dict[str, Any], members: torch.Tensor
                   ) -> tuple[list[Part], torch.Tensor, torch.Tensor]:
    """The low-rank bound's parts for ``members`` (indices into the active outputs, at
    ``c['ranks']``), with each active output's kept rank and worst-case excess (zero for the
    others).

    Outputs of similar rank share one batched part at the part's largest rank (extra pairs
    only tighten the bound); an output that needs far more pairs than another (a signal weaker
    than its noise) gets its own part, so that the others do not read its columns.
    """
    eigenvalues, noise, ranks = c['eigenvalues'], c['noise'], c['ranks']
    n_points = eigenvalues.shape[-1]
    kept = torch.zeros_like(ranks)
    excess = torch.zeros_like(noise)
    parts: list[Part] = []
    for local in (rank_groups(ranks[members]) if members.numel() else []):
        group = members[local]
        rank = int(ranks[group].max())
        if 2 * rank >= n_points:
            # Below rank M the discarded part is a second pass over the r columns: from
            # M / 2 on, every pair (one pass, the exact variance) costs no more.
            rank = n_points
        kept[group] = rank
        if rank < n_points:
            tail = eigenvalues[group, rank]
            excess[group] = variance_excess_ratio(tail=tail - noise[group], noise=noise[group])
        parts.append(('low_rank', group, rank, None))
    return parts, kept, excess


def hybrid_factor(c: dict[str, Any], output: int, rank: int) -> torch.Tensor:
    """(M, m, m) ``L_i^-T`` per training point i, ``L_i L_i^T`` the principal submatrix on
    i's neighbourhood S_i of ``E' = K + nI - U_r diag(mu_r - n) U_r^T`` (module docstring),
    jittered further if it must be, which only raises the variance. ``K + nI`` is the cached
    ``L L^T`` (with the jitter, if the Cholesky needed one)."""
    index = c['neighbour_index'][output]  # (M, m)
    sub = c['k_used'][output][index.unsqueeze(-1), index.unsqueeze(-2)]  # (M, m, m)
    if rank:
        # Entries of size s less the kept part: E' >= n I, so the round-off of the
        # difference (eps r s) is far below its smallest eigenvalue unless s / n ~ 1e10.
        vectors = c['eigenvectors'][output][:, :rank][index]  # (M, m, r)
        weights = c['eigenvalues'][output][:rank] - c['noise'][output]
        sub = sub - (vectors * weights) @ vectors.transpose(-1, -2)
    chol = jittered_cholesky(sub)
    eye = torch.eye(sub.shape[-1], dtype=sub.dtype).expand_as(chol)
    chol_inv = torch.linalg.solve_triangular(chol, eye, upper=False)
    return chol_inv.transpose(-1, -2).contiguous()


def predict_plan(plan: dict[str, Any], x: np.ndarray) -> np.ndarray:
    """Mean and std bound of the plan's outputs at x (B, n_in) float64: (D + 1, B, 2), the
    rows in the order of ``plan['index']`` and a last row of zeros (``plan['take']`` picks an
    (n_out, B, 2) prediction out of it); [..., 0] the mean, [..., 1] the std.

    The kernel over s is ``exp(-1/2 sum_i (x_i - x_ji)^2 / l_i^2)``: below ``GEMM_BATCH``
    states from the squared differences themselves (no expansion whose terms cancel), every
    output's in one product with the inverse squared lengthscales; from it on as one product
    per output on the GEMM path (``kernel_batch``); then each part's rows (module docstring,
    last paragraph: written for few numpy calls).
    """
    if x.shape[0] >= GEMM_BATCH:
        k_all = kernel_batch(plan, x)
    else:
        diff = plan['points_t'] - x[:, :, None]  # (B, n_in, M)
        np.square(diff, out=diff)
        k_all = (plan['neg_half_w'] @ diff).transpose(1, 0, 2)  # (D, B, M): log(k / s)
        np.exp(k_all, out=k_all)
    n_rows, n_batch = k_all.shape[:2]
    parts = plan['parts']
    if len(parts) == 1 and parts[0]['kind'] == 'projection' and parts[0]['rank']:
        # One projection part: its product's first two columns become the mean and the std.
        part = parts[0]
        result = np.zeros((n_rows + 1, n_batch, part['project'].shape[-1]))
        projected = np.matmul(k_all, part['project'], out=result[:-1])  # (D, B, 1 + r)
        _projection_variance(part, projected, projected[:, :, 1])
        std = projected[:, :, 1]
        np.sqrt(np.maximum(std, 0.0, out=std), out=std)
        return result[:, :, :2]
    result = np.zeros((n_rows + 1, n_batch, 2))
    for part in parts:
        rows = part['rows']
        kind = part['kind']
        if kind == 'projection':
            projected = k_all[rows] @ part['project']  # (D, B, 1 + r)
            result[rows, :, 0] = projected[:, :, 0]
            _projection_variance(part, projected, result[rows, :, 1])
        elif kind == 'neighbourhood':
            _neighbourhood(part, k_all[rows], result[rows])
        elif kind == 'shared_projection':
            _shared_projection(part, k_all[rows], result[rows])
        else:
            _low_rank(part, k_all[rows] * part['outputscale'], result[rows])
    std = result[:-1, :, 1]
    np.sqrt(np.maximum(std, 0.0, out=std), out=std)
    return result


def _projection_variance(part: dict[str, Any], projected: np.ndarray, out: np.ndarray
                         ) -> None:
    """s - sum_i z_i^2 from a projection part's product (D, B, 1 + r) into out (D, B)."""
    terms = projected[:, :, None, 1:]  # (D, B, 1, r), each row contiguous
    squares = terms @ terms.transpose(0, 1, 3, 2)  # (D, B, 1, 1)
    np.subtract(part['base'], squares[:, :, 0, 0], out=out)


def _shared_projection(part: dict[str, Any], k_part: np.ndarray, result: np.ndarray) -> None:
    """The projection bound on a shared basis, on k / s (D, B, M): the mean and the variance
    into result (D, B, 2)."""
    n_rows, n_batch, n_points = k_part.shape
    size, diagonal = part['size'], part['diagonal']
    on_basis = (k_part.reshape(-1, n_points) @ part['basis']).reshape(n_rows, n_batch, -1)
    if n_batch == 1:  # the diagonal by flat index: a cheaper gather than two index arrays
        result[:, 0, 0] = on_basis.take(part['mean_index'])
    else:
        result[:, :, 0] = on_basis[diagonal, :, size + diagonal]
    terms = (on_basis[:, :, :size] @ part['vectors'])[:, :, None, :]  # (D, B, 1, r)
    squares = terms @ terms.transpose(0, 1, 3, 2)
    np.subtract(part['base'], squares[:, :, 0, 0], out=result[:, :, 1])


def _batch_index(count: int) -> np.ndarray:
    """(count, 1): the query index of a (D, B, m) gather."""
    index = _BATCH_INDEX.get(count)
    if index is None:
        index = _BATCH_INDEX.setdefault(count, np.arange(count)[:, None])
    return index


_BATCH_INDEX: dict[int, np.ndarray] = {}


def _neighbourhood(part: dict[str, Any], k_part: np.ndarray, result: np.ndarray) -> None:
    """The hybrid bound at rank 0 on k / s (D, B, M): the variance given the nearest training
    point's neighbourhood S alone, s - k_S^T A_SS^-1 k_S; the mean and the variance into
    result (D, B, 2)."""
    result[:, :, 0] = (k_part @ part['project'])[:, :, 0]
    if k_part.shape[1] == 1:
        # One state: plain indexing per output (views, not gathers), as the batch below.
        for output, k_row in enumerate(k_part[:, 0]):
            nearest = int(k_row.argmax())
            v = k_row.take(part['neighbours'][output, nearest]) @ part['factor_t'][output, nearest]
            result[output, 0, 1] = part['base'][output, 0] - v @ v
        return
    outputs = part['outputs']  # (D, 1)
    nearest = k_part.argmax(axis=-1)  # (D, B)
    near = k_part[outputs[:, :, None], _batch_index(k_part.shape[1]),
                  part['neighbours'][outputs, nearest]]  # (D, B, m)
    v = near[:, :, None, :] @ part['factor_t'][outputs, nearest]  # (D, B, 1, m)
    term = v @ v.transpose(0, 1, 3, 2)
    np.subtract(part['base'], term[:, :, 0, 0], out=result[:, :, 1])


def _low_rank(part: dict[str, Any], k_cross: np.ndarray, result: np.ndarray) -> None:
    """The low-rank bound, or the hybrid one at rank > 0, on k (D, B, M); the mean and the
    variance into result (D, B, 2)."""
    hybrid = part['kind'] == 'hybrid'
    if hybrid:
        nearest = k_cross.argmax(axis=-1)  # (D, B): the nearest training point
    project_t = part['project_t']
    # (D, B, 1 + r): mean, then u_i . k
    projected = (project_t @ k_cross.transpose(0, 2, 1)).transpose(0, 2, 1)
    result[:, :, 0] = projected[:, :, 0]
    kept = projected[:, :, 1:]
    var = np.subtract(part['base'],
                      np.einsum('dbr,dr->db', kept * kept, part['kept_weights']),
                      out=result[:, :, 1])
    if part['full_rank']:
        return
    # k_perp = k - U_r (U_r^T k), on the same (by now cached) columns.
    if part['rank']:
        k_cross -= kept @ project_t[:, 1:, :]
    tail = np.einsum('dbm,dbm->db', k_cross, k_cross) * part['tail_weight']
    if hybrid:
        # q^T E'_SS^-1 q on the nearest training point's neighbourhood S, q = k_perp[S].
        outputs = part['outputs']  # (D, 1)
        near = k_cross[outputs[:, :, None], np.arange(k_cross.shape[1])[:, None],
                       part['neighbours'][outputs, nearest]]  # (D, B, m)
        v = (near[:, :, None, :] @ part['factor_t'][outputs, nearest])[:, :, 0, :]
        np.maximum(tail, np.einsum('dbm,dbm->db', v, v), out=tail)
    var -= tail


def projection_rank(projections: torch.Tensor, eigenvalues: torch.Tensor, base: torch.Tensor,
                    exact_std: torch.Tensor, allowed: float) -> int:
    """The projection bound's rank for one output: the smallest multiple of
    ``PROJECTION_RANK_STEP`` (or M) from which on its std is within ``allowed`` times
    ``exact_std`` on every probe.

    Args:
        projections: (P, M) ``u_i . k`` at the P probes, on every eigenvector.
        eigenvalues: (M,) the ``mu_i``.
        base: the prior variance (0-d).
        exact_std: (P,) the exact std at the probes.
        allowed: 1 + the tolerance.

    Returns:
        The rank r in [0, M]; M + 1 if not even every eigenpair passes (round-off).
    """
    n_points = eigenvalues.shape[-1]
    subtracted = torch.cumsum(projections ** 2 / eigenvalues, dim=-1)  # (P, M): rank 1..M
    variance = torch.cat([torch.zeros_like(subtracted[:, :1]), subtracted], dim=-1)
    variance = (base - variance).clamp_min(0.0)  # (P, M + 1): rank 0..M
    # The variance falls with the rank: the bound passes from the last failing rank on.
    passes = (variance.sqrt() <= allowed * exact_std[:, None]).all(dim=0)
    failing = (~passes).nonzero()
    if not failing.numel():
        return 0
    smallest = int(failing[-1]) + 1
    if smallest > n_points:
        return n_points + 1
    step = PROJECTION_RANK_STEP
    return min(n_points, -(-smallest // step) * step)


def rbf(a_scaled: torch.Tensor, b_scaled: torch.Tensor, outputscale: torch.Tensor
        ) -> torch.Tensor:
    """s_d exp(-|a - b|^2 / 2) on lengthscale-scaled inputs.

    Args:
        a_scaled: (D, A, n_in); b_scaled: (D, B, n_in); outputscale: (D,) the s_d.

    Returns:
        (D, A, B).
    """
    sq_dist = ((a_scaled ** 2).sum(-1, keepdim=True)
               + (b_scaled ** 2).sum(-1).unsqueeze(-2)
               - 2.0 * a_scaled @ b_scaled.transpose(-1, -2)).clamp_min(0.0)
    return outputscale[:, None, None] * torch.exp(-0.5 * sq_dist)


def cross_kernel(c: dict[str, Any], x: torch.Tensor) -> torch.Tensor:
    """(D_active, B, M) k_d(x_b, X) at x (B, n_in)."""
    q_scaled = x.unsqueeze(0) / c['lengthscales'].unsqueeze(1)  # (D, B, n_in)
    return rbf(q_scaled, c['x_scaled'], c['outputscale'])


def exact_variance(c: dict[str, Any], k_cross: torch.Tensor, include_noise: bool
                   ) -> torch.Tensor:
    """Exact posterior variance (D_active, B) from ``cross_kernel``'s k: one M x M factor per
    output."""
    v = k_cross @ c['chol_inv_t']  # (D, B, M): rows of (L^-1 k)^T
    var = c['outputscale'].unsqueeze(-1) - (v ** 2).sum(-1)
    return var + c['noise'].unsqueeze(-1) if include_noise else var


def choose_bounds(c: dict[str, Any], probes: torch.Tensor, *, include_noise: bool,
                  tolerance: float) -> None:
    """Each active output's bound (module docstring, "The choice"), into ``c``:
    ``bound_kind`` (a name per active output), ``bound_rank`` (its rank) and
    ``hybrid_factor`` (the neighbourhood factors of the outputs on the hybrid bound).

    Args:
        c: the posterior under construction, with its low-rank bound (``c['low_rank']``) and,
            if the hybrid bound is on, ``neighbour_index`` and ``k_used``.
        probes: (P, n_in) the probe states.
        include_noise: whether the std includes the noise.
        tolerance: the largest relative excess of a probed bound's std over the exact std.
    """
    kept = c['low_rank']['kept']
    n_active, n_points = c['alpha'].shape
    kinds = ['low_rank'] * n_active
    ranks = kept.clone()
    factors: dict[int, torch.Tensor] = {}
    c.update(bound_kind=kinds, bound_rank=ranks, hybrid_factor=factors)
    if not n_active:
        return
    with torch.no_grad():
        k_probe = cross_kernel(c, probes)  # (D, P, M)
        exact = exact_variance(c, k_probe, include_noise)  # (D, P)
    base = c['outputscale'] + c['noise'] if include_noise else c['outputscale']
    # The exact std, floored at 1e-6 of the prior's against round-off near the data.
    exact_std = torch.maximum(exact, 1e-12 * base[:, None]).sqrt()
    allowed = 1.0 + tolerance
    probes_np = probes.numpy()
    for output in range(n_active):
        best = bound_cost('low_rank', int(kept[output]), n_points)
        projections = k_probe[output] @ c['eigenvectors'][output]  # (P, M)
        rank = projection_rank(projections, c['eigenvalues'][output], base[output],
                               exact_std[output], allowed)
        if rank <= n_points and bound_cost('projection', rank, n_points) < best:
            kinds[output], ranks[output] = 'projection', rank
            best = bound_cost('projection', rank, n_points)
        if 'neighbour_index' not in c:
            continue
        one = torch.tensor([output])
        for rank in HYBRID_RANKS:
            if rank >= n_points or bound_cost('hybrid', rank, n_points) >= best:
                break
            factor = hybrid_factor(c, output, rank)
            plan = make_plan(c, [('hybrid', one, rank, factor[None])], include_noise)
            std = torch.from_numpy(predict_plan(plan, probes_np)[0, :, 1])
            if float((std / exact_std[output]).max()) <= allowed:
                kinds[output], ranks[output] = 'hybrid', rank
                factors[output] = factor
                break
    _share_projections(c, k_probe, base, exact_std, allowed)


def subspace_directions(c: dict[str, Any], output: int, basis: torch.Tensor
                        ) -> tuple[torch.Tensor, torch.Tensor]:
    """The directions of span(V) that ``K + nI`` of one output keeps apart: the eigenpairs
    (Q, lambda) of the Gram matrix ``V^T (K + nI) V``, descending, so that ``w_i = V q_i``
    satisfy ``w_i^T (K + nI) w_j = lambda_i delta_ij`` (any V, M x R, orthonormal columns).

    Returns:
        directions: (R, R) the q_i as columns; values: (R,) the lambda_i, each >= n.
    """
    coordinates = c['eigenvectors'][output].T @ basis  # (M, R)
    gram = coordinates.T @ (c['eigenvalues'][output, :, None] * coordinates)
    values, directions = torch.linalg.eigh(gram)
    # V^T A V >= n I for orthonormal V: clamp round-off below it, as the eigenvalues of A.
    return directions.flip(-1), torch.maximum(values.flip(-1), c['noise'][output])


def _share_projections(c: dict[str, Any], k_probe: torch.Tensor, base: torch.Tensor,
                       exact_std: torch.Tensor, allowed: float) -> None:
    """Put the outputs on the projection bound on one shared basis (module docstring,
    "Shared projection") if that reads fewer rows: the smallest basis, in steps of
    ``PROJECTION_RANK_STEP`` from their largest rank on, on which every one of them passes
    its probes. Sets ``c['shared']`` and their kind 'shared_projection' and rank."""
    kinds, ranks = c['bound_kind'], c['bound_rank']
    members = [o for o, kind in enumerate(kinds) if kind == 'projection']
    if len(members) < 2:
        return
    n_points = c['alpha'].shape[-1]
    member_ranks = ranks[members]
    separate = sum(int(member_ranks[group].max() + 1) * group.numel()
                   for group in rank_groups(member_ranks))
    stacked = torch.cat([c['eigenvectors'][o, :, :int(r)] for o, r in zip(members, member_ranks)],
                        dim=-1)
    left = torch.linalg.svd(stacked, full_matrices=False)[0]
    step = PROJECTION_RANK_STEP
    smallest = -(-int(member_ranks.max()) // step) * step
    for size in range(smallest, min(n_points, left.shape[-1]) + 1, step):
        if size + len(members) + SHARED_COST_ROWS >= separate:
            return
        basis = left[:, :size]  # (M, R), orthonormal
        vectors, shared_ranks = [], []
        for output in members:
            directions, values = subspace_directions(c, output, basis)
            rank = projection_rank((k_probe[output] @ basis) @ directions, values,
                                   base[output], exact_std[output], allowed)
            if rank > size:
                break
            vectors.append(directions[:, :rank] * values[:rank].rsqrt())
            shared_ranks.append(rank)
        else:
            cost = (size + len(members) + SHARED_COST_ROWS
                    + sum(shared_ranks) * size / n_points)
            if cost < separate:
                c['shared'] = {'members': torch.tensor(members), 'basis': basis,
                               'vectors': vectors}
                for output, rank in zip(members, shared_ranks):
                    kinds[output], ranks[output] = 'shared_projection', rank
            return


def chosen_parts(c: dict[str, Any]) -> list[Part]:
    """The parts of a prediction with the chosen bounds (``choose_bounds``): the low-rank
    parts, the projection parts (``rank_groups`` of their ranks), the shared projection's one
    part and one hybrid part per rank."""
    kinds, ranks = c['bound_kind'], c['bound_rank']
    outputs = torch.arange(len(kinds))

    def members(kind: str) -> torch.Tensor:
        return outputs[torch.tensor([k == kind for k in kinds], dtype=torch.bool)]

    parts = low_rank_parts(c, members('low_rank'))[0]
    projection = members('projection')
    for local in (rank_groups(ranks[projection]) if projection.numel() else []):
        group = projection[local]
        parts.append(('projection', group, int(ranks[group].max()), None))
    if 'shared' in c:
        shared = c['shared']
        parts.append(('shared_projection', shared['members'], shared['basis'].shape[-1], None))
    hybrid = members('hybrid')
    for rank in sorted(set(ranks[hybrid].tolist())):
        group = hybrid[ranks[hybrid] == rank]
        factor_t = torch.stack([c['hybrid_factor'][int(o)] for o in group])
        parts.append(('hybrid', group, rank, factor_t))
    return parts


def jittered_cholesky(a: torch.Tensor, tries: int = 6) -> torch.Tensor:
    """Cholesky factors of a batch (B, M, M) of covariance matrices.

    A batch element that is not numerically positive definite (near-duplicate inputs, a signal
    variance ~1e7 times the noise: a Car Following checkpoint held one) is refactored with
    jitter j * mean(diag) added, j = 1e-8 (float64; 1e-6 float32), then 10x per try, as GPyTorch
    does; the rest keep their exact factor.

    Raises:
        torch.linalg.LinAlgError: still not positive definite after ``tries`` jitters.
    """
    chol, info = torch.linalg.cholesky_ex(a)
    failed = info > 0
    if not bool(failed.any()):
        return chol
    eye = torch.eye(a.shape[-1], dtype=a.dtype)
    scale = a.diagonal(dim1=-2, dim2=-1).mean(-1)
    jitter = 1e-8 if a.dtype == torch.float64 else 1e-6
    for _ in range(tries):
        index = failed.nonzero().squeeze(-1)
        fixed, info_fixed = torch.linalg.cholesky_ex(
            a[index] + (jitter * scale[index])[:, None, None] * eye)
        chol[index] = fixed
        failed[index] = info_fixed > 0
        if not bool(failed.any()):
            return chol
        jitter *= 10.0
    raise torch.linalg.LinAlgError(
        f'GP covariance of output(s) {failed.nonzero().squeeze(-1).tolist()} is not positive '
        f'definite even with jitter {jitter / 10.0:g} x mean(diag)')
