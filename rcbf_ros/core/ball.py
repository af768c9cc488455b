"""Midpoint-radius interval ("ball") arithmetic on Python floats, for guaranteed bounds.

A :class:`Ball` (c, r), r >= 0, stands for every real in [c - r, c + r]; each operation returns
a ball that holds the exact result for every choice of operands in their balls (an
enclosure). Radii are widened by a small relative amount (:data:`ROUNDING`) so that the float64
rounding of the centre and of the radius never shrinks the enclosure below the exact set.

It runs the straight-line code the closed forms generate (:mod:`rcbf_ros.core.lie_closed_form`)
unchanged: the operators, ``abs``, ``sin`` and ``cos`` of :data:`BALL_NAMESPACE`, and the
comparisons of their ``if`` statements. A comparison the balls decide (every point on one side)
returns that bool; an undecided one asks the current :class:`Branches` which way to go, and
:func:`hull_over_branches` runs the code once per combination of the undecided comparisons and
joins the results, so that a value near a switch is enclosed for either branch.
"""
from __future__ import annotations

import math
import threading
from typing import Any, Callable, Union

ROUNDING = 2.0 ** -48
"""Relative widening of every result's radius (a few hundred float64 ulps of the magnitudes
involved: covers the rounding of the centre, of the radius and of ``sin``/``cos``)."""
TINY = 2.0 ** -1000
"""Absolute widening (keeps a radius of a result near 0 above the rounding of subnormals)."""
MAX_BRANCHES = 64
"""Most paths :func:`hull_over_branches` runs (six undecided comparisons); beyond, the
result is the whole real line."""

Number = Union[float, int]


class Undecided(Exception):
    """A comparison of balls that overlaps its threshold, outside :func:`hull_over_branches`."""


def _widened(centre: float, radius: float) -> Ball:
    """A ball at ``centre`` whose radius covers the rounding of both."""
    return Ball(centre, radius + ROUNDING * (abs(centre) + radius) + TINY)


class Ball:
    """The reals within ``radius`` of ``centre``: an enclosure (module docstring)."""

    __slots__ = ('centre', 'radius')

    def __init__(self, centre: float, radius: float = 0.0) -> None:
        self.centre = float(centre)
        """The midpoint."""
        self.radius = float(radius)
        """The half-width, >= 0 (inf or NaN: any real)."""

    @property
    def low(self) -> float:
        return self.centre - self.radius

    @property
    def high(self) -> float:
        return self.centre + self.radius

    def magnitude(self) -> float:
        """The largest |v| over the ball (NaN becomes inf: an unknown value is unbounded)."""
        value = abs(self.centre) + self.radius
        return value if value == value else math.inf

    def __repr__(self) -> str:
        return f'Ball({self.centre!r}, {self.radius!r})'

    # arithmetic ----------------------------------------------------------------------------
    def __add__(self, other: Ball | Number) -> Ball:
        if isinstance(other, Ball):
            return _widened(self.centre + other.centre, self.radius + other.radius)
        return _widened(self.centre + other, self.radius)

    __radd__ = __add__

    def __neg__(self) -> Ball:
        return Ball(-self.centre, self.radius)

    def __pos__(self) -> Ball:
        return self

    def __sub__(self, other: Ball | Number) -> Ball:
        if isinstance(other, Ball):
            return _widened(self.centre - other.centre, self.radius + other.radius)
        return _widened(self.centre - other, self.radius)

    def __rsub__(self, other: Number) -> Ball:
        return _widened(other - self.centre, self.radius)

    def __mul__(self, other: Ball | Number) -> Ball:
        if isinstance(other, Ball):
            return _widened(self.centre * other.centre,
                            abs(self.centre) * other.radius + self.radius * abs(other.centre)
                            + self.radius * other.radius)
        return _widened(self.centre * other, abs(other) * self.radius)

    __rmul__ = __mul__

    def __truediv__(self, other: Number) -> Ball:
        if isinstance(other, Ball):
            return NotImplemented
        return _widened(self.centre / other, self.radius / abs(other))

    def __pow__(self, power: int) -> Ball:
        if type(power) is not int or not 0 <= power <= 16:
            return NotImplemented
        if power == 0:
            return Ball(1.0)
        if power % 2 == 0:  # an even power of a ball around 0 has no negative part
            base = abs(self)
            out = base
            for _ in range(power - 1):
                out = out * base
            low = max(base.low, 0.0) ** power
            return _hull_of(max(low, out.low), out.high)
        out = self
        for _ in range(power - 1):
            out = out * self
        return out

    def __abs__(self) -> Ball:
        centre, radius = abs(self.centre), self.radius
        if centre >= radius:
            return Ball(centre, radius)
        return _hull_of(0.0, centre + radius)

    # comparisons ---------------------------------------------------------------------------
    def _decide(self, certain: bool, impossible: bool) -> bool:
        if certain:
            return True
        if impossible:
            return False
        return _choose()

    def __lt__(self, other: Ball | Number) -> bool:
        low, high = _bounds(other)
        return self._decide(self.high < low, self.low >= high)

    def __le__(self, other: Ball | Number) -> bool:
        low, high = _bounds(other)
        return self._decide(self.high <= low, self.low > high)

    def __gt__(self, other: Ball | Number) -> bool:
        low, high = _bounds(other)
        return self._decide(self.low > high, self.high <= low)

    def __ge__(self, other: Ball | Number) -> bool:
        low, high = _bounds(other)
        return self._decide(self.low >= high, self.high < low)

    def __bool__(self) -> bool:
        raise TypeError('a ball has no truth value')

    __hash__ = None  # type: ignore[assignment]


def _bounds(value: Ball | Number) -> tuple[float, float]:
    if isinstance(value, Ball):
        return value.low, value.high
    return float(value), float(value)


def _hull_of(low: float, high: float) -> Ball:
    """The ball of [low, high], widened."""
    return _widened(0.5 * (low + high), 0.5 * (high - low))


def hull(first: Ball | Number, second: Ball | Number) -> Ball:
    """The smallest ball (widened) holding both."""
    a = first if isinstance(first, Ball) else Ball(first)
    b = second if isinstance(second, Ball) else Ball(second)
    return _hull_of(min(a.low, b.low), max(a.high, b.high))


def ball_sin(value: Ball | Number) -> Ball | float:
    """sin over a ball: |sin a - sin c| <= min(|a - c|, 2), within [-1, 1]."""
    if not isinstance(value, Ball):
        return math.sin(value)
    if not math.isfinite(value.centre):  # math.sin refuses inf: the whole range
        return _widened(0.0, 1.0)
    return _trig(math.sin(value.centre), value.radius)


def ball_cos(value: Ball | Number) -> Ball | float:
    """cos over a ball, as :func:`ball_sin`."""
    if not isinstance(value, Ball):
        return math.cos(value)
    if not math.isfinite(value.centre):
        return _widened(0.0, 1.0)
    return _trig(math.cos(value.centre), value.radius)


def _trig(centre: float, radius: float) -> Ball:
    """The ball of [c - r, c + r] within [-1, 1] (NaN: all of it)."""
    if not radius < 2.0:
        return _widened(0.0, 1.0)
    return _hull_of(max(centre - radius, -1.0), min(centre + radius, 1.0))


BALL_NAMESPACE: dict[str, Any] = {'cos': ball_cos, 'sin': ball_sin, 'inf': math.inf,
                                  'nan': math.nan}
"""The generated source's namespace (:data:`~rcbf_ros.core.dynamics.SOURCE_NAMESPACE`) on
balls."""


class Jet:
    """A value over a ball and its gradient over the same ball: ``value`` encloses f(x) and
    ``grad[k]`` encloses df/dx_k for every x in the input balls (forward-mode differentiation
    in ball arithmetic; an index missing from ``grad``: a derivative of 0). With it, the change
    of a smooth f over a box x_k +/- D is at most sum_k sup|df/dx_k| D_k (the mean value
    theorem), which does not suffer the cancellations that inflate ``value``."""

    __slots__ = ('value', 'grad')

    def __init__(self, value: Ball, grad: dict[int, Ball]) -> None:
        self.value = value
        """Encloses the values."""
        self.grad = grad
        """index -> encloses the partial derivative."""

    @classmethod
    def variable(cls, centre: float, radius: float, index: int) -> Jet:
        """The state entry ``index`` over [centre - radius, centre + radius]."""
        return cls(Ball(centre, radius), {index: Ball(1.0)})

    def change(self, radii: list[float]) -> float:
        """The mean value bound of |f(x) - f(x_k)| over x_k +/- radii."""
        return sum(g.magnitude() * radii[k] for k, g in self.grad.items())

    def __add__(self, other: Jet | Number) -> Jet:
        if isinstance(other, Jet):
            grad = dict(self.grad)
            for k, g in other.grad.items():
                grad[k] = grad[k] + g if k in grad else g
            return Jet(self.value + other.value, grad)
        return Jet(self.value + other, self.grad)

    __radd__ = __add__

    def __neg__(self) -> Jet:
        return Jet(-self.value, {k: -g for k, g in self.grad.items()})

    def __pos__(self) -> Jet:
        return self

    def __sub__(self, other: Jet | Number) -> Jet:
        if isinstance(other, Jet):
            return self + (-other)
        return Jet(self.value - other, self.grad)

    def __rsub__(self, other: Number) -> Jet:
        return Jet(other - self.value, {k: -g for k, g in self.grad.items()})

    def __mul__(self, other: Jet | Number) -> Jet:
        if isinstance(other, Jet):
            a, b = self.value, other.value
            grad = {k: g * b for k, g in self.grad.items()}
            for k, g in other.grad.items():
                grad[k] = grad[k] + a * g if k in grad else a * g
            return Jet(a * b, grad)
        return Jet(self.value * other, {k: g * other for k, g in self.grad.items()})

    __rmul__ = __mul__

    def __truediv__(self, other: Number) -> Jet:
        if isinstance(other, (Jet, Ball)):
            return NotImplemented
        return Jet(self.value / other, {k: g / other for k, g in self.grad.items()})

    def __pow__(self, power: int) -> Jet:
        if type(power) is not int or not 0 <= power <= 16:
            return NotImplemented
        if power == 0:
            return Jet(Ball(1.0), {})
        out = self
        for _ in range(power - 1):
            out = out * self
        return out

    def __abs__(self) -> Jet:
        if self.value.low >= 0.0:
            return self
        if self.value.high <= 0.0:
            return -self
        # a kink inside: the slope is anywhere in [-1, 1] (|f| is Lipschitz with f's bound)
        return Jet(abs(self.value), {k: Ball(0.0, g.magnitude())
                                     for k, g in self.grad.items()})

    def __lt__(self, other: Jet | Number) -> bool:
        return self.value < _value(other)

    def __le__(self, other: Jet | Number) -> bool:
        return self.value <= _value(other)

    def __gt__(self, other: Jet | Number) -> bool:
        return self.value > _value(other)

    def __ge__(self, other: Jet | Number) -> bool:
        return self.value >= _value(other)

    def __bool__(self) -> bool:
        raise TypeError('a jet has no truth value')

    __hash__ = None  # type: ignore[assignment]


def _value(value: Jet | Number) -> Ball | Number:
    return value.value if isinstance(value, Jet) else value


def jet_sin(value: Jet | Ball | Number) -> Jet | Ball | float:
    """sin of a jet (d sin = cos d), a ball or a float."""
    if isinstance(value, Jet):
        slope = ball_cos(value.value)
        return Jet(ball_sin(value.value), {k: slope * g for k, g in value.grad.items()})
    return ball_sin(value)


def jet_cos(value: Jet | Ball | Number) -> Jet | Ball | float:
    """cos of a jet (d cos = -sin d), a ball or a float."""
    if isinstance(value, Jet):
        slope = -ball_sin(value.value)
        return Jet(ball_cos(value.value), {k: slope * g for k, g in value.grad.items()})
    return ball_cos(value)


JET_NAMESPACE: dict[str, Any] = dict(BALL_NAMESPACE, cos=jet_cos, sin=jet_sin)
"""The generated source's namespace on jets."""


# branches ------------------------------------------------------------------------------------
class Branches:
    """Which way each undecided comparison of one run goes: the ``forced`` ones first, then
    True, noting the runs still to do (the same prefix, then False)."""

    def __init__(self, forced: list[bool]) -> None:
        self.forced = forced
        self.taken: list[bool] = []
        self.pending: list[list[bool]] = []

    def choose(self) -> bool:
        depth = len(self.taken)
        if depth < len(self.forced):
            choice = self.forced[depth]
        else:
            choice = True
            self.pending.append(self.taken + [False])
        self.taken.append(choice)
        return choice


_STATE = threading.local()


def _choose() -> bool:
    branches = getattr(_STATE, 'branches', None)
    if branches is None:
        raise Undecided('a comparison of balls overlaps its threshold')
    return branches.choose()


def _join(first: Any, second: Any) -> Any:
    """The hull of two results of the same shape (nested lists and tuples of balls, jets,
    floats)."""
    if isinstance(first, (list, tuple)):
        return type(first)(_join(a, b) for a, b in zip(first, second))
    if isinstance(first, Jet) or isinstance(second, Jet):
        a = first if isinstance(first, Jet) else Jet(Ball(first), {})
        b = second if isinstance(second, Jet) else Jet(Ball(second), {})
        return Jet(hull(a.value, b.value), {k: hull(a.grad.get(k, 0.0), b.grad.get(k, 0.0))
                                            for k in {*a.grad, *b.grad}})
    if isinstance(first, Ball) or isinstance(second, Ball):
        return hull(first, second)
    return first if first == second else hull(first, second)


def _everything(result: Any) -> Any:
    """A result of the same shape as ``result`` whose every value is any real."""
    if isinstance(result, (list, tuple)):
        return type(result)(_everything(v) for v in result)
    return Ball(0.0, math.inf)  # (not a jet: without a grad, no mean value bound is used)


def hull_over_branches(function: Callable[..., Any], *args: Any) -> tuple[Any, bool]:
    """``function(*args)`` run over balls, once per combination of the comparisons its balls
    leave undecided (at most :data:`MAX_BRANCHES`), the results joined (module docstring); and
    whether every comparison was decided (one path: the result is as smooth as the code's
    straight line; else it may jump where a comparison switches, and a jet's ``grad`` says
    nothing across the jump)."""
    todo: list[list[bool]] = [[]]
    joined: Any = None
    runs = 0
    previous = getattr(_STATE, 'branches', None)
    try:
        while todo:
            runs += 1
            branches = Branches(todo.pop())
            _STATE.branches = branches
            result = function(*args)
            if runs > MAX_BRANCHES:
                return _everything(result), False
            joined = result if joined is None else _join(joined, result)
            todo += branches.pending
    finally:
        _STATE.branches = previous
    return joined, runs == 1
