"""Test helpers for the safety filter: the shipped configs' filters, random calls to them,
the QP a filter solves as arrays, and a SafetyFilter that always solves with OSQP (no exact
active-set answer), for tests of what happens when OSQP fails, lies or is starved."""
from __future__ import annotations

import numpy as np

from rcbf_ros.core.config import filter_config_from_params
from rcbf_ros.core.filter import SafetyFilter
from rcbf_ros.parameters.rules import find_config, load_params


def osqp_only(safety_filter: SafetyFilter) -> SafetyFilter:
    """``safety_filter``, every active QP sent to OSQP (and its fallback)."""
    safety_filter._active_set = lambda g_matrix, upper: None
    return safety_filter


def qp_arrays(safety_filter: SafetyFilter, x: np.ndarray, applied: np.ndarray,
              mean: np.ndarray, std: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(h (K,), G (nc, n_u + 1), its right-hand side (nc,)) of the QP the filter solves at x
    and the clipped proposal ``applied``, from its assembly."""
    h, rows, upper, _ = safety_filter._assemble(*(np.asarray(a, dtype=np.float64).tolist()
                                                  for a in (x, applied, mean, std)))
    return np.array(h), np.array(rows), np.array(upper)


def shipped_filter(system: str) -> SafetyFilter:
    """The filter of ``system``'s shipped config."""
    return SafetyFilter(filter_config_from_params(
        load_params(find_config(system), 'safety_filter')).problem)


def random_call(system: str, rng: np.random.Generator) -> tuple[np.ndarray, ...]:
    """A state, a proposal (partly outside the limits, to be clipped) and a disturbance box."""
    if system == 'unicycle':
        x = np.array([*rng.uniform(-3.0, 3.0, 2), rng.uniform(-np.pi, np.pi)])
    elif system == 'pvtol':
        x1 = rng.uniform(-5.5, 5.5)
        x = np.array([x1, rng.uniform(-2.5, 2.5), *rng.normal(0.0, 0.5, 2),
                      rng.normal(0.0, 0.2), rng.uniform(0.6, 1.4), x1 + rng.uniform(-0.5, 0.5)])
    else:
        positions = np.array([34.0, 28.0, 22.0, 16.0, 10.0]) + rng.normal(0.0, 1.0, 5)
        x = np.stack([positions, 30.0 + rng.normal(0.0, 2.0, 5)], axis=1).reshape(-1)
    n_u = 1 if system == 'car_following' else 2
    return x, rng.uniform(-3.5, 3.5, n_u), np.zeros(x.size), np.full(x.size, 0.02)
