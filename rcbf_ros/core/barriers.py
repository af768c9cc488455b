"""Barrier functions h(x) >= 0 and the cascaded form for higher relative degree.

A *barrier family* holds k barriers of one kind (e.g. k circular obstacles) and evaluates them
row-wise: ``value(x, index)`` takes states ``x: (R, n_x)`` and barrier indices
``index: (R,)`` and returns ``(R,)`` with row r = h_{index[r]}(x[r]). Row r depends on x[r] only,
so one autograd pass over ``sum(value)`` yields every row's own gradient; this is what lets the
cascade (which needs the gradient *inside* the barrier) run batched without nested Jacobians.

Families here (all differentiable in torch):

- :class:`CircleObstacles`  h_o = ||p(x) - p_o||^2 - delta_o^2 (paper, Unicycle and PVTOL), with an
  optional look-ahead point p = (x, y) + l_p (cos th, sin th) so that both unicycle inputs appear
  in L_g h (relative degree 1); with ``speed_input`` set, the point moves behind the robot for
  proposals that drive backwards (chosen in :func:`rcbf_ros.core.rcbf.barrier_terms`).
- :class:`BandBarrier`      h = delta^2 - (x_i - c)^2 where c is a constant or another state entry
  (the PVTOL safety operator: delta^2 - (x1 - x_h)^2), or the band's two linear sides.
- :class:`PairGap`          h = 1/2 ((x_a - x_b)^2 - delta^2) (Car Following, h_3 and h_5).
- :class:`HalfPlane`        h = n^T x_S - b (stay on one side of a line/plane; arena walls).
- :class:`Cascaded`         h* = L_f h + gamma h (paper, Car Following), applied recursively by
  :func:`cascade` for relative degree r >= 2: r - 1 applications.

Every built-in family except a look-ahead :class:`CircleObstacles` is a quadratic polynomial of the
state; ``quadratic_rows`` gives its coefficients (:class:`QuadraticRows`), from which
:mod:`rcbf_ros.core.lie_closed_form` evaluates h, grad h and the cascades in closed form.

The disturbance is accounted for only at the top level (the RCBF row): in the cascade the lower
levels use the nominal drift f. This matches the paper's cascaded RCBFs, whose lower-level
derivatives carry neither the input nor (for the systems here) the learned disturbance.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple, Protocol, runtime_checkable, Sequence, TYPE_CHECKING

import numpy as np

from rcbf_ros.core.dynamics import ControlAffineSystem
from rcbf_ros.core.torch_import import LazyTorch

torch = LazyTorch(globals())  # imported where first used: see rcbf_ros.core.torch_import
if TYPE_CHECKING:
    from torch import Tensor


@runtime_checkable
class BarrierFamily(Protocol):
    """k barriers of one kind, evaluated row-wise (see module docstring)."""

    @property
    def count(self) -> int:
        """Number of barriers k in the family."""

    @property
    def names(self) -> list[str]:
        """One name per barrier, for diagnostics (e.g. ``obstacle_3``)."""

    def value(self, x: Tensor, index: Tensor) -> Tensor:
        """x: (R, n_x), index: (R,) long in [0, k) -> (R,) with h_{index[r]}(x[r])."""


def _as_tensor(values: Sequence, like: Tensor) -> Tensor:
    return torch.as_tensor(values, dtype=like.dtype, device=like.device)


class NumberedNames:
    """``names`` of a family whose k barriers are called ``<name>_0`` ... ``<name>_{k-1}``
    (the family defines ``name`` and ``count``)."""

    @property
    def names(self) -> list[str]:
        return [f'{self.name}_{i}' for i in range(self.count)]  # type: ignore[attr-defined]


class QuadraticRows(NamedTuple):
    """k barriers that are quadratic polynomials of the state, exactly:
    h_i(x) = c_i + a_i^T x + 1/2 x^T Q_i x, so grad h_i = a_i + Q_i x and the Hessian is Q_i."""

    constant: np.ndarray
    """(k,) c_i."""
    linear: np.ndarray
    """(k, n_x) a_i."""
    hessian: np.ndarray
    """(k, n_x, n_x) Q_i, symmetric."""


def _zero_rows(k: int, n_x: int) -> QuadraticRows:
    return QuadraticRows(np.zeros(k), np.zeros((k, n_x)), np.zeros((k, n_x, n_x)))


def _add_square(rows: QuadraticRows, row: int, weight: float, i: int, j: int | None,
                center: float) -> None:
    """Add weight (x_i - x_j)^2 (j given) or weight (x_i - center)^2 to ``rows[row]``."""
    if j is None:
        rows.hessian[row, i, i] += 2.0 * weight
        rows.linear[row, i] -= 2.0 * weight * center
        rows.constant[row] += weight * center * center
        return
    for a, b, sign in ((i, i, 1.0), (j, j, 1.0), (i, j, -1.0), (j, i, -1.0)):
        rows.hessian[row, a, b] += 2.0 * weight * sign


@dataclass(frozen=True)
class CircleObstacles(NumberedNames):
    """Circular keep-out zones: h_o(x) = ||p(x) - p_o||^2 - delta_o^2, delta_o = r_o + margin."""

    centers: tuple[tuple[float, float], ...]
    """Obstacle centres p_o in the plane, one (x, y) per obstacle."""
    radii: tuple[float, ...]
    """Obstacle radii r_o (same length as centers)."""
    margin: float = 0.0
    """Added to every radius (robot size and a safety buffer): delta_o = r_o + margin."""
    position_indices: tuple[int, int] = (0, 1)
    """State entries holding the planar position."""
    heading_index: int | None = None
    """State entry of the heading, for the look-ahead point (None: no look-ahead)."""
    lookahead: float = 0.0
    """l_p: the barrier uses p = position + l_p (cos th, sin th) (ref: 0.03 on the unicycle)."""
    name: str = 'obstacle'
    """Prefix of the barrier names in diagnostics."""
    speed_input: int | None = None
    """Index of the input that drives along the heading (unicycle: v). When set, a proposal
    with a negative value there uses the point BEHIND the robot, p - l_p (cos th, sin th), as
    long as that point is outside every obstacle (see :func:`rcbf_ros.core.rcbf.barrier_terms`);
    None: always the point ahead."""

    def __post_init__(self) -> None:
        if len(self.centers) != len(self.radii):
            raise ValueError(f'obstacles: {len(self.centers)} centers but {len(self.radii)} radii')
        if any(len(c) != 2 for c in self.centers):
            raise ValueError('obstacles.centers: every center needs exactly 2 coordinates')
        if any(r < 0 for r in self.radii):
            raise ValueError('obstacles.radii: radii must be >= 0')
        if self.lookahead != 0.0 and self.heading_index is None:
            raise ValueError('obstacles.lookahead: a look-ahead point needs heading_index')
        if self.speed_input is not None and self.lookahead == 0.0:
            raise ValueError('obstacles.speed_input: needs a look-ahead point '
                             '(obstacles.lookahead != 0)')

    @property
    def count(self) -> int:
        return len(self.centers)

    def point(self, x: Tensor, side: Tensor | None = None) -> Tensor:
        """The point kept out of the obstacles. x: (R, n_x) -> (R, 2); side: (R,) +1 for the
        point ahead, -1 for the point behind (None: ahead)."""
        i, j = self.position_indices
        p = torch.stack([x[:, i], x[:, j]], dim=-1)
        if self.heading_index is not None and self.lookahead != 0.0:
            th = x[:, self.heading_index]
            offset = self.lookahead if side is None else self.lookahead * side[:, None]
            p = p + offset * torch.stack([torch.cos(th), torch.sin(th)], dim=-1)
        return p

    def value(self, x: Tensor, index: Tensor, side: Tensor | None = None) -> Tensor:
        centers = _as_tensor(self.centers, x)[index]
        delta = _as_tensor(self.radii, x)[index] + self.margin
        return ((self.point(x, side) - centers) ** 2).sum(-1) - delta ** 2

    @property
    def has_lookahead(self) -> bool:
        """Whether the guarded point is offset along the heading (then h is not quadratic)."""
        return self.heading_index is not None and self.lookahead != 0.0

    def quadratic_rows(self, n_x: int) -> QuadraticRows | None:
        """Coefficients of h_o = (x_i - c_o,x)^2 + (x_j - c_o,y)^2 - delta_o^2 (None with a
        look-ahead point: then h involves cos and sin of the heading)."""
        if self.has_lookahead:
            return None
        rows = _zero_rows(self.count, n_x)
        i, j = self.position_indices
        for o, ((cx, cy), radius) in enumerate(zip(self.centers, self.radii)):
            _add_square(rows, o, 1.0, i, None, cx)
            _add_square(rows, o, 1.0, j, None, cy)
            delta = radius + self.margin
            rows.constant[o] -= delta * delta
        return rows


@dataclass(frozen=True)
class BothPoints:
    """The obstacles of a :class:`CircleObstacles` at both look-ahead points, as one family of
    2k barriers (indices [0, k): the point ahead, [k, 2k): the point behind), so that
    :func:`rcbf_ros.core.rcbf.barrier_terms` gets both in one autograd pass."""

    base: CircleObstacles

    @property
    def count(self) -> int:
        return 2 * self.base.count

    @property
    def names(self) -> list[str]:
        return self.base.names + [f'{name}_behind' for name in self.base.names]

    def value(self, x: Tensor, index: Tensor) -> Tensor:
        k = self.base.count
        behind = index >= k
        side = torch.where(behind, -1.0, 1.0).to(x.dtype)
        return self.base.value(x, torch.where(behind, index - k, index), side)


@dataclass(frozen=True)
class BandBarrier:
    """Stay within a band |x_i - c| <= delta, c a constant or the state entry x_j.

    Two forms of the same set:

    - ``quadratic`` (the paper's): one barrier h = delta^2 - (x_i - c)^2;
    - ``sides``: two linear barriers h_upper = delta - (x_i - c), h_lower = delta + (x_i - c).

    They differ once cascaded (relative degree >= 2). The gradient of the quadratic form,
    -2 (x_i - c), vanishes at the centre, so there its first cascade level, h_dot + gamma h, is
    delta^2 gamma whatever the velocity, and further out it weighs the velocity by the offset:
    a drone crossing the PVTOL operator's centre line fast is let through, and at the far edge
    the braking it then needs exceeds the input limits. The linear sides see the velocity
    toward each edge everywhere, and h_upper h_lower equals the quadratic form.
    """

    index: int
    """State entry x_i constrained to the band."""
    half_width: float
    """delta: the allowed distance |x_i - c|."""
    center: float = 0.0
    """Constant centre c (ignored when center_index is given)."""
    center_index: int | None = None
    """State entry holding a moving centre (e.g. the safety operator x_h)."""
    name: str = 'band'
    """Barrier name in diagnostics (``sides``: ``<name>_upper``, ``<name>_lower``)."""
    form: str = 'quadratic'
    """``quadratic`` (one barrier) or ``sides`` (two linear barriers), see the class doc."""

    def __post_init__(self) -> None:
        if self.half_width <= 0:
            raise ValueError('half_width: must be > 0')
        if self.form not in ('quadratic', 'sides'):
            raise ValueError(f"form: expected 'quadratic' or 'sides', got {self.form!r}")

    @property
    def count(self) -> int:
        return 1 if self.form == 'quadratic' else 2

    @property
    def names(self) -> list[str]:
        if self.form == 'quadratic':
            return [self.name]
        return [f'{self.name}_upper', f'{self.name}_lower']

    def value(self, x: Tensor, index: Tensor) -> Tensor:
        c = x[:, self.center_index] if self.center_index is not None else self.center
        offset = x[:, self.index] - c
        if self.form == 'quadratic':
            return self.half_width ** 2 - offset ** 2
        # index 0: the upper side, 1: the lower side
        return self.half_width - torch.where(index == 0, offset, -offset)

    def quadratic_rows(self, n_x: int) -> QuadraticRows:
        """Coefficients of delta^2 - (x_i - c)^2, or of the sides delta -/+ (x_i - c)."""
        rows = _zero_rows(self.count, n_x)
        i, j, delta = self.index, self.center_index, self.half_width
        if self.form == 'quadratic':
            rows.constant[0] = delta * delta
            _add_square(rows, 0, -1.0, i, j, self.center)
            return rows
        for row, sign in ((0, -1.0), (1, 1.0)):  # h = delta + sign (x_i - c)
            rows.linear[row, i] += sign
            if j is None:
                rows.constant[row] = delta - sign * self.center
            else:
                rows.constant[row] = delta
                rows.linear[row, j] -= sign
        return rows


@dataclass(frozen=True)
class PairGap:
    """Keep two 1-D positions apart: h = 1/2 ((x_a - x_b)^2 - delta^2), one barrier per pair."""

    pairs: tuple[tuple[int, int], ...]
    """(a, b) state indices per barrier (Car Following: (p_3, p_4) and (p_5, p_4))."""
    delta: float
    """Minimum distance (paper: 3.5 m)."""
    name: str = 'gap'
    """Prefix of the barrier names in diagnostics."""

    @property
    def count(self) -> int:
        return len(self.pairs)

    @property
    def names(self) -> list[str]:
        return [f'{self.name}_{a}_{b}' for a, b in self.pairs]

    def value(self, x: Tensor, index: Tensor) -> Tensor:
        pairs = torch.as_tensor(self.pairs, device=x.device)[index]
        xa = x.gather(1, pairs[:, :1]).squeeze(1)
        xb = x.gather(1, pairs[:, 1:]).squeeze(1)
        return 0.5 * ((xa - xb) ** 2 - self.delta ** 2)

    def quadratic_rows(self, n_x: int) -> QuadraticRows:
        """Coefficients of 1/2 (x_a - x_b)^2 - 1/2 delta^2."""
        rows = _zero_rows(self.count, n_x)
        for row, (a, b) in enumerate(self.pairs):
            _add_square(rows, row, 0.5, a, b, 0.0)
            rows.constant[row] = -0.5 * self.delta * self.delta
        return rows


@dataclass(frozen=True)
class HalfPlane(NumberedNames):
    """Half-spaces h_j = n_j^T x_S - b_j >= 0 over the state entries S (e.g. arena walls)."""

    normals: tuple[tuple[float, ...], ...]
    """One normal n_j per barrier, each of length len(indices)."""
    offsets: tuple[float, ...]
    """b_j per barrier."""
    indices: tuple[int, ...] = (0, 1)
    """State entries S the normals act on."""
    name: str = 'wall'
    """Prefix of the barrier names in diagnostics."""

    def __post_init__(self) -> None:
        if len(self.normals) != len(self.offsets):
            raise ValueError('half_planes: normals and offsets differ in length')
        if any(len(n) != len(self.indices) for n in self.normals):
            raise ValueError('half_planes.normals: each normal needs len(indices) entries')

    @property
    def count(self) -> int:
        return len(self.normals)

    def value(self, x: Tensor, index: Tensor) -> Tensor:
        normals = _as_tensor(self.normals, x)[index]
        offsets = _as_tensor(self.offsets, x)[index]
        return (normals * x[:, list(self.indices)]).sum(-1) - offsets

    def quadratic_rows(self, n_x: int) -> QuadraticRows:
        """Coefficients of n_j^T x_S - b_j (linear: Q_j = 0)."""
        rows = _zero_rows(self.count, n_x)
        for row, (normal, offset) in enumerate(zip(self.normals, self.offsets)):
            for index, weight in zip(self.indices, normal):
                rows.linear[row, index] += weight
            rows.constant[row] = -offset
        return rows


@dataclass(frozen=True)
class Cascaded:
    """h*(x) = L_f h(x) + gamma h(x) = grad h(x)^T f(x) + gamma h(x) (cascaded RCBF).

    Valid where the input does not appear in h_dot (relative degree >= 2: L_g h = 0 for the
    base); the tests check that for every cascaded barrier of the built-in systems.
    """

    base: BarrierFamily
    """The barrier of one lower order."""
    system: ControlAffineSystem
    """Supplies the nominal drift f."""
    gamma: float
    """gamma_k > 0 of this cascade level."""

    @property
    def count(self) -> int:
        return self.base.count

    @property
    def names(self) -> list[str]:
        return self.base.names

    def value(self, x: Tensor, index: Tensor) -> Tensor:
        with torch.enable_grad():
            if not x.requires_grad:
                x = x.detach().requires_grad_(True)
            h = self.base.value(x, index)
            (grad_h,) = torch.autograd.grad(h.sum(), x, create_graph=True)
        return (grad_h * self.system.f(x)).sum(-1) + self.gamma * h


def uncascaded(family: BarrierFamily) -> BarrierFamily:
    """The family under every cascade level (:class:`Cascaded`, subclasses included)."""
    while isinstance(family, Cascaded):
        family = family.base
    return family


def cascade(base: BarrierFamily, system: ControlAffineSystem,
            gammas: Sequence[float]) -> BarrierFamily:
    """Apply the cascade once per gamma: relative degree r needs r - 1 gammas.

    ``cascade(h, sys, [g1, g2])`` = (L_f + g2)(L_f + g1) h, as used for PVTOL (r = 3).
    """
    family = base
    for gamma in gammas:
        if gamma <= 0:
            raise ValueError(f'gammas: every cascade gain must be > 0, got {gamma}')
        family = Cascaded(family, system, float(gamma))
    return family


def evaluate(family: BarrierFamily, x: Tensor) -> Tensor:
    """Every barrier of the family at every state. x: (B, n_x) -> (B, k)."""
    k = family.count
    rows = x.repeat_interleave(k, dim=0)
    index = torch.arange(k, device=x.device).repeat(x.shape[0])
    return family.value(rows, index).reshape(x.shape[0], k)
