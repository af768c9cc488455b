"""ONE builder of the RCBF-QP data, for the per-step filter (B = 1) and the differentiable layer.

The paper's RCBF-QP (eq. QP), with z = [u_S, eps]:

    minimize    u_S^T W u_S + l eps^2             (W = diag(w); w = 1: the paper's ||u_S||^2)
    subject to  grad h_i^T (f + g (u_RL + u_S)) >= -alpha h_i - min_{psi in D} grad h_i^T psi + eps
                u_min <= u_RL + u_S <= u_max                          (actuator limits, optional)

in the standard form used throughout the package,

    minimize_z  1/2 z^T P z + q^T z   subject to   G z <= h

    P = 2 diag(w_1, ..., w_m, l)                                (B, m + 1, m + 1)
    q = 0                                                       (B, m + 1)
    RCBF row i:  [-L_g h_i, -1] z <= L_f h_i + L_g h_i u_RL + alpha h_i + rho_i
    limit rows:  [ e_j, 0] z <= u_max_j - u_RL_j,   [-e_j, 0] z <= u_RL_j - u_min_j

where rho_i = min over the disturbance hull of grad h_i^T psi (:func:`robust_margin`). The slack
eps is free (paper: eps in R); with l large it is ~0 whenever the barrier rows can be met, and it
makes the QP always feasible and strictly convex. The input weights w choose how the correction
is shared between inputs: the unicycle's omega enters L_g h only through the look-ahead l_p, so
with w = 1 the smallest correction brakes instead of steering and the robot stops in front of
an obstacle; a small omega weight makes steering the cheap correction. G and h are
differentiable in u_RL, so the learner's losses see the safe action (paper eqs. q_update_diff,
pi_update_diff).
"""
from __future__ import annotations

import functools
import math
from typing import NamedTuple, Sequence, TYPE_CHECKING

from rcbf_ros.core.torch_import import LazyTorch

torch = LazyTorch(globals())  # imported where first used: see rcbf_ros.core.torch_import
if TYPE_CHECKING:
    from torch import Tensor


class QPData(NamedTuple):
    """A batch of QPs  min 1/2 z^T P z + q^T z  s.t.  G z <= h."""

    P: Tensor
    """(B, nz, nz), nz = n_u + 1."""
    q: Tensor
    """(B, nz)."""
    G: Tensor
    """(B, nc, nz), nc = n_barriers + 2 n_limited_inputs."""
    h: Tensor
    """(B, nc)."""


def robust_margin(grad_h: Tensor, mean: Tensor, std: Tensor, k_c: float) -> Tensor:
    """min over the box D = mean +/- k_c std of grad_h^T psi, in closed form.

    The minimum of a linear function over a box is attained at a vertex, coordinate-wise at
    psi_d = mean_d - k_c std_d sign(grad_d), so

        rho = grad_h^T mean - k_c |grad_h|^T std.

    This equals the paper's min over the 2^n permutation vertices Psi (tested against them).

    Args:
        grad_h: (B, K, n_x) barrier gradients.
        mean: (B, n_x) disturbance mean mu(x).
        std: (B, n_x) disturbance standard deviation sigma(x) >= 0.
        k_c: confidence multiplier.

    Returns:
        (B, K) margins rho_i.
    """
    return (_batched_matvec(grad_h, mean) - k_c * _batched_matvec(grad_h.abs(), std))


def _batched_matvec(A: Tensor, x: Tensor) -> Tensor:
    """A x per sample, A: (B, K, n), x: (B, n) -> (B, K) (einsum 'bkn,bn->bk' as one batched
    product, without einsum's per-call parsing)."""
    return torch.matmul(A, x.unsqueeze(-1)).squeeze(-1)


def check_input_weight(input_weight: Sequence[float], m: int) -> tuple[float, ...]:
    """The m input weights as floats, each finite and > 0; errors name ``input_weight``."""
    weights = tuple(float(w) for w in input_weight)
    if len(weights) != m:
        raise ValueError(f'input_weight: expected {m} values (one per input), got {len(weights)}')
    if not all(math.isfinite(w) and w > 0 for w in weights):
        raise ValueError(f'input_weight: every weight must be finite and > 0, got {weights}')
    return weights


def cost_weights(m: int, slack_weight: float,
                 input_weight: Sequence[float] | None = None) -> tuple[float, ...]:
    """(w_1, ..., w_m, l): the cost's diagonal, P = 2 diag(w, l) (the one definition, shared
    by :func:`build_rcbf_qp` and the per-step filter's fixed P)."""
    if slack_weight <= 0:
        raise ValueError('slack_weight: must be > 0')
    weights = (1.0,) * m if input_weight is None else check_input_weight(input_weight, m)
    return (*weights, float(slack_weight))


def build_rcbf_qp(*, h: Tensor, lf_h: Tensor, lg_h: Tensor, rho: Tensor, u_rl: Tensor,
                  alpha: float | Tensor, slack_weight: float,
                  input_weight: Sequence[float] | None = None,
                  u_min: Sequence[float] | None = None,
                  u_max: Sequence[float] | None = None) -> QPData:
    """Assemble the RCBF-QP in standard form (see module docstring).

    Args:
        h: (B, K) barrier values h_i(x) (the top level of a cascade).
        lf_h: (B, K) L_f h_i.
        lg_h: (B, K, m) L_g h_i.
        rho: (B, K) robust margins (zeros for a non-robust CBF).
        u_rl: (B, m) proposed actions; G and h are differentiable in it.
        alpha: linear class-K gain alpha(h) = alpha h, scalar or (K,).
        slack_weight: l > 0.
        input_weight: m weights w_j > 0 of u_S in the cost (None: all 1).
        u_min: m lower limits on u_RL + u_S, or None.
        u_max: m upper limits, or None (both or neither).

    Returns:
        QPData with nz = m + 1 and nc = K (+ 2 m with limits). P and q are the same for every
        sample, returned as expanded views (batch stride 0: read-only, shared by the batch).
    """
    batch, _, m = lg_h.shape
    dtype, device = lg_h.dtype, lg_h.device
    if (u_min is None) != (u_max is None):
        raise ValueError('u_min/u_max: give both actuator limits or neither')
    # A number multiplies as a Python scalar (rounded to dtype, as a 0-d tensor of it would be).
    alpha_t = (float(alpha) if isinstance(alpha, (int, float))
               else torch.as_tensor(alpha, dtype=dtype, device=device))
    # RCBF rows: -L_g h u_S - eps <= L_f h + L_g h u_RL + alpha h + rho
    g_rows = torch.cat([-lg_h, _constant(-1.0, dtype, device).expand(*lg_h.shape[:2], 1)],
                       dim=-1)
    h_rows = lf_h + _batched_matvec(lg_h, u_rl) + alpha_t * h + rho
    if u_min is not None:
        limit_g, lo, hi = _limit_rows(m, tuple(float(v) for v in u_min),
                                      tuple(float(v) for v in u_max), dtype, device)
        g_rows = torch.cat([g_rows, limit_g.expand(batch, -1, -1)], dim=1)
        h_rows = torch.cat([h_rows, hi - u_rl, u_rl - lo], dim=1)
    weights = cost_weights(m, slack_weight, input_weight)
    P = torch.diag_embed(torch.tensor(weights, dtype=dtype, device=device) * 2.0)
    q = torch.zeros(m + 1, dtype=dtype, device=device)
    return QPData(P.expand(batch, -1, -1), q.expand(batch, -1), g_rows, h_rows)


@functools.lru_cache(maxsize=64)
def _constant(value: float, dtype: torch.dtype, device: torch.device) -> Tensor:
    """A 0-d constant tensor, made once per value, dtype and device (only ever read)."""
    return torch.tensor(value, dtype=dtype, device=device)


@functools.lru_cache(maxsize=64)
def _limit_rows(m: int, u_min: tuple[float, ...], u_max: tuple[float, ...],
                dtype: torch.dtype, device: torch.device) -> tuple[Tensor, Tensor, Tensor]:
    """The limit rows' constant parts: G rows [I, 0; -I, 0] (2 m, m + 1), u_min and u_max
    (m,), made once per limits, dtype and device (only ever read, never returned)."""
    eye = torch.eye(m, dtype=dtype, device=device)
    limit_g = torch.cat([torch.cat([eye, -eye], dim=0),
                         torch.zeros(2 * m, 1, dtype=dtype, device=device)], dim=-1)
    return (limit_g, torch.tensor(u_min, dtype=dtype, device=device),
            torch.tensor(u_max, dtype=dtype, device=device))
