"""Checkpoint cost: time and size of one training checkpoint as the replay data grow.

    python benchmarks/bench_checkpoint.py [--repeats 5] [--dir runs] [--no-write]

What a checkpoint of the in-process trainer holds: the learner (networks, optimisers, GP data,
replay buffer, RNG states), the env's RNG, the metrics rows and the run settings, written by
``run_files.save_payload`` (type check, torch.save, fsync, rename) and read back by
``run_files.load_payload`` (weights_only). Unicycle, diff mode, the default learner (256x256
networks, batch 256). The learner first trains for real (``--warmup`` random steps, then
``--steps`` steps with a SAC update each, timed: an episode's cost is that step time times the
packaged episode length, 1000 steps); then its replay buffer and GP data are filled to N rows
with copies of those transitions (the content does not change the cost) and each N is saved
``repeats`` times. One row with the model buffer of MB SAC-RCBF as full as the real one.
Writes the ``## Checkpoint cost`` section of benchmarks/RESULTS.md.
"""
from __future__ import annotations

# First: numpy's BLAS set up as in every rcbf_ros process (rcbf_ros/__init__.py).
import rcbf_ros  # noqa: F401  # isort: skip

import argparse
from dataclasses import asdict, replace
from pathlib import Path
import statistics
import sys
import tempfile
import time

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks._results import publish_section  # noqa: E402
from rcbf_ros.training.agent import LearnerConfig, SafeLearner  # noqa: E402
from rcbf_ros.training.build import build_run, RunConfig  # noqa: E402
from rcbf_ros.training.episodes import run_episode  # noqa: E402
from rcbf_ros.training.run_files import load_payload, save_payload  # noqa: E402

torch.set_num_threads(1)
EPISODE_STEPS = 1000
FILLS = (1_000, 10_000, 60_000, 200_000)


def fill(learner: SafeLearner, rows: int) -> None:
    """Grow the replay buffer(s) and the GP data to ``rows`` rows with copies of what they
    hold (the buffer keeps at most its capacity)."""
    data = learner.buffer.state_dict()['data']
    have = len(learner.buffer)
    for buffer in (learner.buffer, learner.model_buffer):
        if buffer is None:
            continue
        while len(buffer) < min(rows, buffer.capacity):
            k = min(have, rows - len(buffer))
            buffer.add(**{name: tensor[:k] for name, tensor in data.items()})
    gp = learner.gp
    x, y = gp.state_dict()['x'], gp.state_dict()['y']
    while gp.num_data < rows:
        k = min(x.shape[0], rows - gp.num_data)
        gp.add(x[:k], y[:k])


def checkpoint(learner: SafeLearner, env, run: RunConfig, episodes: int) -> dict:
    """The payload the in-process trainer writes after ``episodes`` episodes."""
    row = {'episode': 0, 'ret': 1.0, 'steps': EPISODE_STEPS, 'violations': 0,
           'max_slack': 0.0, 'wall_s': 30.0, 'steps_per_s': 33.0, 'critic_loss': 1.0}
    return {'learner': learner.state_dict(), 'episode': episodes,
            'env_rng': env.np_random.bit_generator.state,
            'history': [{**row, 'episode': i} for i in range(episodes)], 'run': asdict(run)}


def time_checkpoint(learner: SafeLearner, env, run: RunConfig, rows: int, path: Path,
                    repeats: int) -> tuple[float, float, float]:
    """(median save s, median load s, size MB) of the checkpoint with ``rows`` rows."""
    saves, loads = [], []
    for _ in range(repeats):
        t0 = time.perf_counter()
        save_payload(path, checkpoint(learner, env, run, max(1, rows // EPISODE_STEPS)))
        saves.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        load_payload(path)
        loads.append(time.perf_counter() - t0)
    return statistics.median(saves), statistics.median(loads), path.stat().st_size / 1e6


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('--repeats', type=int, default=5, help='saves per size')
    parser.add_argument('--warmup', type=int, default=300, help='random steps before updates')
    parser.add_argument('--steps', type=int, default=100, help='timed steps with updates')
    parser.add_argument('--dir', default='runs', help='where the checkpoint is written (the '
                        'disk runs write to; the file is removed)')
    parser.add_argument('--no-write', action='store_true', help='do not touch RESULTS.md')
    args = parser.parse_args()

    learner_cfg = LearnerConfig(mode='diff', seed=0, start_steps=args.warmup,
                                update_after=args.warmup, gp_refit_interval=args.warmup)
    run = RunConfig(system='unicycle', episodes=1, max_steps=args.warmup, record_bag=False,
                    out_dir='runs/bench_checkpoint', learner=learner_cfg)
    env, filt, learner, _ = build_run(run)
    run_episode(env, filt, learner, episode=0, seed=0)  # random actions, fills the buffer
    env.max_steps = args.steps
    stats = run_episode(env, filt, learner, episode=1, seed=None)
    step_s = stats.wall_s / stats.steps
    episode_s = step_s * EPISODE_STEPS
    print(f'{stats.steps} steps with updates: {1e3 * step_s:.1f} ms/step -> '
          f'{EPISODE_STEPS}-step episode {episode_s:.1f} s', flush=True)

    Path(args.dir).mkdir(parents=True, exist_ok=True)
    rows = ['| mode | replay rows (= GP rows) | episodes of 1000 steps | size (MB) '
            '| save, median (s) | load, median (s) | save / episode |',
            '|---|---:|---:|---:|---:|---:|---:|']
    with tempfile.TemporaryDirectory(dir=args.dir) as tmp:
        path = Path(tmp) / 'checkpoint.pt'
        settings = [('diff', learner, n) for n in FILLS]
        mb_cfg = replace(learner_cfg, model_based=True)
        _, _, mb = build_run(replace(run, learner=mb_cfg))[:3]
        mb.load_state_dict(learner.state_dict())
        settings.append(('diff + model_based', mb, FILLS[-1]))
        for label, agent, n in settings:
            fill(agent, n)
            save, load, size = time_checkpoint(agent, env, run, n, path, args.repeats)
            rows.append(f'| {label} | {n} | {n // EPISODE_STEPS} | {size:.1f} | {save:.3f} '
                        f'| {load:.3f} | {100 * save / episode_s:.2f} % |')
            print(rows[-1], flush=True)
    note = ('One checkpoint of an in-process Unicycle diff run (learner with replay buffer and GP '
            'data, env RNG, metrics rows, settings) written as the trainer writes it (plain-data '
            'check, torch.save, fsync, rename) and read back with weights_only, after N '
            'transitions; the model-based row also holds a model buffer of N rows. A training '
            f'step took {1e3 * step_s:.1f} ms here (mean of {stats.steps} steps with updates), '
            f'so a 1000-step episode about {episode_s:.0f} s: a checkpoint after every episode '
            '(the default, `--checkpoint-every 1`) costs the last column.')
    publish_section('Checkpoint cost', script='bench_checkpoint.py', blocks=[note, rows],
                    write=not args.no_write)


if __name__ == '__main__':
    main()
