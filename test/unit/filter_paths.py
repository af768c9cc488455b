"""Test helper: a SafetyFilter that always solves with OSQP (no exact active-set answer),
for tests of what happens when OSQP fails, lies or is starved."""
from __future__ import annotations

from rcbf_ros.core.filter import SafetyFilter


def osqp_only(safety_filter: SafetyFilter) -> SafetyFilter:
    """``safety_filter``, every active QP sent to OSQP (and its fallback)."""
    safety_filter._active_set = lambda g_matrix, upper: None
    return safety_filter
