"""The RCBF constraint set of one system: barriers -> Lie derivatives -> QP data.

:class:`RCBFProblem` is the single place where a system (f, g), its barrier families, the
class-K gain, the disturbance confidence k_c and the slack weight meet. Both the per-step
:class:`~rcbf_ros.core.filter.SafetyFilter` and the learner's differentiable layer call
:meth:`RCBFProblem.qp`; nothing else assembles constraints.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple, Sequence, TYPE_CHECKING

from rcbf_ros.core.barriers import BarrierFamily, BothPoints
from rcbf_ros.core.dynamics import ControlAffineSystem
from rcbf_ros.core.qp import build_rcbf_qp, check_input_weight, QPData, robust_margin
from rcbf_ros.core.torch_import import LazyTorch

torch = LazyTorch(globals())  # imported where first used: see rcbf_ros.core.torch_import
if TYPE_CHECKING:
    from torch import Tensor


class BarrierTerms(NamedTuple):
    """Barrier values and Lie derivatives at a batch of states (K barriers in total)."""

    h: Tensor
    """(B, K) h_i(x)."""
    grad_h: Tensor
    """(B, K, n_x) grad h_i(x)."""
    lf_h: Tensor
    """(B, K) L_f h_i(x) = grad h_i^T f(x)."""
    lg_h: Tensor
    """(B, K, n_u) L_g h_i(x) = grad h_i^T g(x)."""


def _family_values(family: BarrierFamily, x: Tensor) -> tuple[Tensor, Tensor]:
    """h (B, k) and grad h (B, k, n_x) of one family, by one autograd pass (module doc)."""
    batch, k = x.shape[0], family.count
    rows = x.detach().repeat_interleave(k, dim=0).requires_grad_(True)
    index = torch.arange(k, device=x.device).repeat(batch)
    values = family.value(rows, index)
    (grad,) = torch.autograd.grad(values.sum(), rows)
    return values.detach().reshape(batch, k), grad.reshape(batch, k, -1)


def barrier_terms(system: ControlAffineSystem, families: Sequence[BarrierFamily],
                  x: Tensor, u: Tensor | None = None) -> BarrierTerms:
    """h, grad h, L_f h, L_g h for every barrier of every family at states x: (B, n_x).

    Gradients come from one autograd pass per family over row-replicated states (row r of the
    replica carries barrier index[r], see :mod:`rcbf_ros.core.barriers`). The results are
    detached: they are constants for the QP (the learner differentiates through u_RL only).

    Direction of travel: for a :class:`CircleObstacles` with ``speed_input`` and proposals
    u: (B, n_u) given, row b guards the point behind the robot instead of the one ahead when
    u[b, speed_input] < 0 and that point is outside every obstacle of the family (h >= 0 for
    all of them); otherwise, and without u, the point ahead. Driving backwards with the point
    ahead, the cheap turn that moves that point off an obstacle turns the direction of travel
    onto it and the filter can only brake; the point behind makes reversing the mirror image of
    driving forwards. Requiring the point behind to be safe before switching bounds what a
    switch can cost: the centre is within l_p of either point, so it stays at least
    delta - 3 l_p from every obstacle centre (the margin covers 3 l_p in the shipped configs).
    The choice is a ``torch.where`` (no Python branching on values), so the compiled assembly
    traces it.
    """
    hs, grads = [], []
    with torch.enable_grad():
        for family in families:
            speed = getattr(family, 'speed_input', None)
            if speed is None or u is None:
                h, grad = _family_values(family, x)
            else:
                k = family.count
                both_h, both_grad = _family_values(BothPoints(family), x)  # type: ignore
                h_behind, grad_behind = both_h[:, k:], both_grad[:, k:]
                use = (u.detach()[:, speed] < 0) & (h_behind >= 0).all(dim=1)
                h = torch.where(use[:, None], h_behind, both_h[:, :k])
                grad = torch.where(use[:, None, None], grad_behind, both_grad[:, :k])
            hs.append(h)
            grads.append(grad)
    x = x.detach()
    if not families:  # no static barrier (a filter of sensor points only): K = 0
        hs.append(x.new_zeros((x.shape[0], 0)))
        grads.append(x.new_zeros((x.shape[0], 0, x.shape[1])))
    h = torch.cat(hs, dim=1)
    grad_h = torch.cat(grads, dim=1)
    lf_h = torch.einsum('bkn,bn->bk', grad_h, system.f(x))
    lg_h = torch.einsum('bkn,bnm->bkm', grad_h, system.g(x))
    return BarrierTerms(h, grad_h, lf_h, lg_h)


@dataclass(frozen=True)
class RCBFProblem:
    """Everything the RCBF-QP needs besides the state, the proposal and the disturbance box."""

    system: ControlAffineSystem
    """Nominal control-affine model (f, g, input limits)."""
    families: tuple[BarrierFamily, ...]
    """Barrier families, already cascaded to relative degree 1 where needed. Empty only for a
    filter whose obstacles are all sensor points (:class:`rcbf_ros.core.filter.SafetyFilter`
    with a ``footprint``): the rows are then the points' alone."""
    alpha: float = 1.0
    """Linear class-K gain: alpha(h) = alpha * h."""
    k_c: float = 2.0
    """k_c of the disturbance box mean +/- k_c std (paper eq. disturb_estimate)."""
    slack_weight: float = 1.0e6
    """l: weight of the squared slack (large: violations only when unavoidable)."""
    input_weight: tuple[float, ...] | None = None
    """w: per-input weights of u_S in the cost u_S^T diag(w) u_S (None: all 1, the paper's)."""
    use_input_limits: bool = True
    """Add the actuator-limit rows u_min <= u_RL + u_S <= u_max when the system has limits."""

    def __post_init__(self) -> None:
        if self.alpha <= 0:
            raise ValueError('alpha: must be > 0')
        if self.k_c < 0:
            raise ValueError('k_c: must be >= 0')
        if self.slack_weight <= 0:
            raise ValueError('slack_weight: must be > 0')
        if self.input_weight is not None:
            object.__setattr__(self, 'input_weight',
                               check_input_weight(self.input_weight, self.system.n_u))

    @property
    def n_barriers(self) -> int:
        """K, the number of RCBF rows."""
        return sum(f.count for f in self.families)

    @property
    def barrier_names(self) -> list[str]:
        """K names, in row order."""
        return [name for f in self.families for name in f.names]

    @property
    def has_limits(self) -> bool:
        """Whether the QP carries actuator-limit rows."""
        return self.use_input_limits and self.system.u_min is not None

    @property
    def n_constraints(self) -> int:
        """nc = K (+ 2 n_u with limits)."""
        return self.n_barriers + (2 * self.system.n_u if self.has_limits else 0)

    def terms(self, x: Tensor, u_rl: Tensor | None = None) -> BarrierTerms:
        """Barrier values and Lie derivatives. x: (B, n_x); u_rl: (B, n_u) proposals, which
        choose the look-ahead point of obstacles with a ``speed_input`` (None: the point ahead;
        see :func:`barrier_terms`)."""
        return barrier_terms(self.system, self.families, x, u_rl)

    def state_h(self, x: Tensor) -> Tensor:
        """(B, K) barrier values at states without a proposal (e.g. a bag's recorded states):
        where a look-ahead point follows the direction of travel, each row is the larger of the
        two choices, so a state is outside a barrier's set only when neither direction of
        travel has its point clear (see :func:`barrier_terms`)."""
        h = self.terms(x).h
        speeds = {s for s in (getattr(f, 'speed_input', None) for f in self.families)
                  if s is not None}
        if speeds:
            backwards = torch.zeros(x.shape[0], self.system.n_u, dtype=x.dtype,
                                    device=x.device)
            backwards[:, sorted(speeds)] = -1.0
            h = torch.maximum(h, self.terms(x, backwards).h)
        return h

    def qp(self, x: Tensor, u_rl: Tensor, mean: Tensor | None = None,
           std: Tensor | None = None, terms: BarrierTerms | None = None) -> QPData:
        """QP data for states x: (B, n_x), proposals u_rl: (B, n_u) and a disturbance box.

        Args:
            mean: (B, n_x) disturbance mean (None: zero).
            std: (B, n_x) disturbance std (None: zero, i.e. a plain CBF with a known mean).
            terms: precomputed :meth:`terms` at (x, u_rl) (saves the autograd pass when reused).
        """
        terms = self.terms(x, u_rl) if terms is None else terms
        if mean is None and std is None:
            rho = torch.zeros_like(terms.h)
        else:
            mean = torch.zeros_like(x) if mean is None else mean
            std = torch.zeros_like(x) if std is None else std
            rho = robust_margin(terms.grad_h, mean, std, self.k_c)
        limits = self.has_limits
        return build_rcbf_qp(
            h=terms.h, lf_h=terms.lf_h, lg_h=terms.lg_h, rho=rho, u_rl=u_rl,
            alpha=self.alpha, slack_weight=self.slack_weight, input_weight=self.input_weight,
            u_min=self.system.u_min if limits else None,
            u_max=self.system.u_max if limits else None)
