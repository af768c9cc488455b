"""Car Following's sampled-data bound: why the filter refuses a period or latency on it.

The closed form of docs/SAFETY_FILTER.md ("Car Following: the bound, and why it is refused"),
sound over the hold interval and the latency (test/unit/test_sampled_data_cars.py checks it
term by term along fine-step trajectories across the braking switches) and measured by
bench_sampled_data.py's Car Following section. No filter takes it: with it most decisions of
the shipped scenario meet no command at T = L >= 20 ms, so the filter refuses the keys
(rcbf_ros.core.sampled_data.REFUSED_SYSTEMS). Kept here, beside the benchmark that measures
it, not in the package.
"""
from __future__ import annotations

from collections.abc import Sequence
import math

import numpy as np

from rcbf_ros.core.barriers import Cascaded, PairGap
from rcbf_ros.core.dynamics import CarFollowing
from rcbf_ros.core.rcbf import RCBFProblem


class CarFollowingBound:
    """The sampled-data margin of Car Following's cascaded gap rows (module docstring), in
    closed form from the relative motion of the cars, the braking switches' reach decided per
    follower: the bound behind the system's refusal (:data:`REFUSED_SYSTEMS`), which
    benchmarks/bench_sampled_data.py measures. Not a filter's margin: no filter takes it.

    ``parts(x, mean, std)`` gives, per row, (nu0, c, braking): phi_i(x_k, u) - phi_i(x, u)
    <= nu0_i + c_i |u| for every state x reachable from x_k within tau (any input within the
    limits, any disturbance in the box) and the row's own command u; ``braking`` is the part
    of nu0 the braking terms bring (the switch's jump where it can be reached).
    """

    def __init__(self, problem: RCBFProblem, horizon: float) -> None:
        system = problem.system
        if type(system) is not CarFollowing or system.u_min is None:
            raise ValueError('CarFollowingBound: a CarFollowing system with input limits')
        self.horizon = float(horizon)
        """tau = L + T (s)."""
        self._system = system
        self._reach = float(max(abs(system.u_min[0]), abs(system.u_max[0])))
        self._alpha, self._k_c = float(problem.alpha), float(problem.k_c)
        self._rows: list[tuple[int, int, float]] = []  # (car a, car b, gamma) per row
        for family in problem.families:
            base = getattr(family, 'base', None)
            if (type(family) is not Cascaded or type(base) is not PairGap
                    or any(a % 2 or b % 2 for a, b in base.pairs)):
                raise ValueError('CarFollowingBound: gaps between positions, cascaded once')
            for a, b in base.pairs:
                self._rows.append((a // 2, b // 2, float(family.gamma)))
        # follower -> (leader, gap of its switch): cars 2, 3 brake on the car ahead, 5 on 3
        self._followers = {1: (0, float(system.brake_gap)), 2: (1, float(system.brake_gap)),
                           4: (2, float(system.rear_brake_gap))}

    def _motion(self, x: np.ndarray, w: np.ndarray, braking: dict[int, float]
                ) -> tuple[np.ndarray, np.ndarray]:
        """(R (5,), A (5,)): per car, the largest |v_dot| and the largest |prior acceleration|
        over the interval, the braking term of a follower bounded by k_b ``braking[car]``."""
        s, tau = self._system, self.horizon
        rate, prior = np.zeros(5), np.zeros(5)
        for car in range(5):
            noise = w[2 * car + 1]
            if car in self._followers:
                own = s.k_v * abs(s.v_des - x[2 * car + 1]) + s.k_b * braking[car]
                # |v - v_k| <= tau R and R <= k_v (|v_des - v_k| + tau R) + k_b B + w
                rate[car] = (own + noise) / (1.0 - tau * s.k_v)
                prior[car] = own + s.k_v * tau * rate[car]
            else:  # the leader (prior 0) and car 4 (the input)
                rate[car] = noise + (self._reach if car == _INPUT_CAR else 0.0)
        return rate, prior

    def _gap_reach(self, x: np.ndarray, w: np.ndarray, rate: np.ndarray, ahead: int,
                   behind: int) -> tuple[float, float]:
        """(q_k, Q): the gap q = p_ahead - p_behind at x_k and Q >= |q(t) - q_k| over tau,
        widened by the positions' rounding (:data:`POSITION_ROUNDING` of their magnitude): a
        gap exactly on its switch leaves it in floating point as the positions advance, at
        equal speeds too."""
        tau = self.horizon
        q = x[2 * ahead] - x[2 * behind]
        closing = abs(x[2 * ahead + 1] - x[2 * behind + 1]) + w[2 * ahead] + w[2 * behind]
        rounding = POSITION_ROUNDING * (1.0 + abs(x[2 * ahead]) + abs(x[2 * behind])
                                        + tau * (abs(x[2 * ahead + 1]) + abs(x[2 * behind + 1])))
        return q, tau * closing + 0.5 * tau * tau * (rate[ahead] + rate[behind]) + rounding

    def _switches(self, x: np.ndarray, w: np.ndarray
                  ) -> tuple[dict[int, float], dict[int, tuple[float, float, float]]]:
        """(B, S): per follower, the largest |s| 1[|s| < G] its gap s to its leader takes over
        tau (0 where its switch cannot be reached) and (s_lo, s_hi, G), the interval of s.

        The followers in the chain's order (car 2 on the leader, 3 on 2, 5 on 3), each with
        its leader's B found: a follower outside its switch (|s_k| >= G) does not brake
        before its gap first enters it, so whether it can enter is decided with its own
        braking 0; where it can (or is inside), s is bounded again with it braking at its
        largest, k_b G."""
        braking = {car: gap for car, (_, gap) in self._followers.items()}
        reach = {}
        for car, (leader, gap) in self._followers.items():
            s_k = x[2 * leader] - x[2 * car]
            inside = abs(s_k) < gap
            braking[car] = gap if inside else 0.0
            rate, _ = self._motion(x, w, braking)
            _, spread = self._gap_reach(x, w, rate, leader, car)
            if not inside and _braking_reach(s_k - spread, s_k + spread, gap) > 0.0:
                braking[car] = gap
                rate, _ = self._motion(x, w, braking)
                _, spread = self._gap_reach(x, w, rate, leader, car)
            reach[car] = (s_k - spread, s_k + spread, gap)
            braking[car] = _braking_reach(s_k - spread, s_k + spread, gap)
        return braking, reach

    def parts(self, x: Sequence[float], mean: Sequence[float], std: Sequence[float]
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(nu0 (K,), c (K, 1), braking (K,)) at the sampled state x and the box (class
        docstring); inf where tau k_v >= 1 (no bound of the speeds closes)."""
        s, tau, alpha = self._system, self.horizon, self._alpha
        count = len(self._rows)
        state = np.asarray(x, dtype=np.float64)
        w = np.abs(np.asarray(mean, dtype=np.float64)) + self._k_c * np.asarray(
            std, dtype=np.float64)
        if tau * s.k_v >= 1.0 or not (np.isfinite(state).all() and np.isfinite(w).all()):
            return np.full(count, math.inf), np.zeros((count, 1)), np.full(count, math.inf)
        braking, reach = self._switches(state, w)
        rate, prior = self._motion(state, w, braking)
        rest, linear, jumps = np.zeros(count), np.zeros((count, 1)), np.zeros(count)
        for row, (a, b, gamma) in enumerate(self._rows):
            d, dd = self._gap_reach(state, w, rate, a, b)  # d and D_d
            e = state[2 * a + 1] - state[2 * b + 1]
            de = tau * (rate[a] + rate[b])  # D_e
            # F = e^2 + (gamma + alpha) d e + alpha gamma / 2 (d^2 - delta^2)
            smooth = (2.0 * abs(e) * de + de * de
                      + (gamma + alpha) * (abs(e) * dd + abs(d) * de + dd * de)
                      + 0.5 * alpha * gamma * (2.0 * abs(d) * dd + dd * dd))
            # rho: |d grad h*|^T w, grad h* = +/-(e + gamma d) on p_a, p_b, +/-d on v_a, v_b
            smooth += ((de + gamma * dd) * (w[2 * a] + w[2 * b])
                       + dd * (w[2 * a + 1] + w[2 * b + 1]))
            # d (a_a - a_b): (d - d_k) times the accelerations, d_k times their change
            smooth += dd * (prior[a] + prior[b])
            jump = 0.0
            for car, sign in ((a, 1.0), (b, -1.0)):
                if car not in self._followers:
                    continue
                smooth += abs(d) * s.k_v * tau * rate[car]  # the tracking term's change
                lo, hi, gap = reach[car]
                s_k = state[2 * self._followers[car][0]] - state[2 * car]
                at_k = s_k if abs(s_k) < gap else 0.0  # -brk_k / k_b
                # sup over s of sign d_k (brk_k - brk(s)), brk = -k_b s 1[|s| < G]
                jump += sign * d * s.k_b * -at_k + _largest_braking(
                    sign * d * s.k_b, lo, hi, gap)
            rest[row] = smooth + jump
            jumps[row] = jump
            linear[row, 0] = dd if (a == _INPUT_CAR) != (b == _INPUT_CAR) else 0.0  # L_g h* = +/-d
        return rest, linear, jumps


POSITION_ROUNDING = 1e-9
"""The rounding a gap may take per metre of its cars' positions (m/m), far above float64's
1e-16 per step over the steps of an interval."""
_INPUT_CAR = 3
"""The car (0-based) whose acceleration is the input: car 4."""


def _braking_reach(lo: float, hi: float, gap: float) -> float:
    """The largest |s| 1[|s| < G] over s in [lo, hi]: 0 where the interval stays outside the
    switch (|s| >= G throughout), else at most G."""
    if hi <= -gap or lo >= gap:
        return 0.0
    return min(gap, max(abs(lo), abs(hi)))


def _largest_braking(kappa: float, lo: float, hi: float, gap: float) -> float:
    """sup of kappa s 1[|s| < G] over s in [lo, hi] (the braking term's value the follower
    may take: 0 outside the switch, kappa s inside; the open ends' limits bound it)."""
    best = 0.0 if (lo <= -gap or hi >= gap) else -math.inf
    inside_lo, inside_hi = max(lo, -gap), min(hi, gap)
    if inside_lo < inside_hi or (inside_lo == inside_hi and abs(inside_lo) < gap):
        best = max(best, kappa * inside_hi if kappa > 0.0 else kappa * inside_lo)
    return best
