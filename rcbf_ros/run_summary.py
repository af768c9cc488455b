"""Print what a training run left behind: returns, violations, speed, the bag and the plot.

    python -m rcbf_ros.run_summary bags/<run>

Reads ``<run>/learner/summary.json`` and ``metrics.jsonl`` (written by the learner node or
``rcbf_ros train``) and the MCAP bag under ``<run>/bag``. A bag whose recorder was killed is
recovered first (``rcbf_ros bag recover``: complete files from its whole chunks, the originals
kept as ``*.mcap.orig``), so that every bag reader accepts it.
"""
from __future__ import annotations

import json
from pathlib import Path
import sys


def summarize_run(run: Path) -> str:
    """The summary text for the run directory ``run``."""
    lines = [f'run: {run}']
    learner = run / 'learner'
    summary_path = learner / 'summary.json'
    if not summary_path.exists():
        return '\n'.join(lines + [f'no {summary_path}: the learner did not finish an episode'])
    summary = json.loads(summary_path.read_text())
    rows = [json.loads(line) for line in (learner / 'metrics.jsonl').read_text().splitlines()
            if line.strip()] if (learner / 'metrics.jsonl').exists() else []
    lines.append(f"episodes: {summary.get('episodes', 0)}   env steps: "
                 f"{summary.get('env_steps', 0)}   steps/s: {summary.get('steps_per_s', 0):.1f}")
    if rows:
        returns = ', '.join(f"{r['ret']:.2f}" for r in rows)
        lines.append(f'returns per episode: {returns}')
    lines.append(f"best return: {summary.get('best_return', float('nan')):.3f}   goals reached: "
                 f"{summary.get('goals_reached', 0)}")
    lines.append(f"safety violations (true barriers < 0): {summary.get('safety_violations')}")
    if 'reward_curve' in summary:
        lines.append(f"reward curve: {summary['reward_curve']}")
    lines.append(f'checkpoint: {learner / "checkpoint.pt"}   policy: {learner / "policy.pt"}')
    bag_dir = run / 'bag'
    if bag_dir.exists():
        from rcbf_ros.bag import bag_info, BagError, reindex_bag
        try:
            info = bag_info(bag_dir)
            state = 'closed cleanly'
            if not info.complete:
                reindex_bag(bag_dir)
                info, state = bag_info(bag_dir), 'recorder killed: recovered from whole chunks'
        except BagError as exc:
            return '\n'.join(lines + [f'bag: {exc}'])
        seconds = (info.end_time_ns - info.start_time_ns) / 1e9
        lines.append(f'bag: {bag_dir} ({info.message_count} messages, {seconds:.1f} s, {state})')
        for name, topic in sorted(info.topics.items()):
            lines.append(f'  {name:28s} {topic.message_count:7d}')
    return '\n'.join(lines)


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    if len(args) != 1:
        print('usage: python -m rcbf_ros.run_summary <run directory>', file=sys.stderr)
        return 2
    print(summarize_run(Path(args[0])))
    return 0


if __name__ == '__main__':
    sys.exit(main())
