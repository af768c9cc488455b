"""What a training run says while and after it runs: one line per episode and the totals.

Shared by the in-process trainer and the learner node, whose per-episode rows carry the same
keys (the node's lack ``max_slack``: its filter's QP runs in another process).
"""
from __future__ import annotations

from typing import Any


def summarize(history: list[dict[str, Any]]) -> dict[str, Any]:
    """Totals over a run's per-episode rows (in-process or learner node).

    ``max_slack`` is reported only when the rows carry it (the learner node does not see the
    filter's QP, which runs in another process).
    """
    if not history:
        return {'episodes': 0}
    steps = sum(r['steps'] for r in history)
    wall = sum(r['wall_s'] for r in history)
    summary = {
        'episodes': len(history),
        'env_steps': steps,
        'final_return': history[-1]['ret'],
        'best_return': max(r['ret'] for r in history),
        'goals_reached': sum(bool(r['goal_reached']) for r in history),
        'safety_violations': sum(r['violations'] for r in history),
        'steps_per_s': steps / wall if wall > 0 else 0.0,
    }
    if all('max_slack' in r for r in history):
        summary['max_slack'] = max(r['max_slack'] for r in history)
    return summary


def format_progress(row: dict[str, Any], total: int) -> str:
    """One progress line per episode (``max slack`` only when the row carries it)."""
    slack = f"max slack {row['max_slack']:.2e}  " if 'max_slack' in row else ''
    return (f"episode {row['episode'] + 1:4d}/{total}  return {row['ret']:9.3f}  "
            f"steps {row['steps']:5d}  violations {row['violations']}  {slack}"
            f"goal {'yes' if row['goal_reached'] else 'no '}  {row['steps_per_s']:6.1f} steps/s")
