"""Zero-shot transfer: a trained run's deterministic policy on N seeded random layouts.

Per layout seed s (paper: 200 layouts, "Modular Task Learning"):

1. the env of the run's system with ``layout: random, layout_seed: s``
   (:func:`rcbf_ros.envs.layouts.unicycle_random_layout` / ``pvtol_random_layout``: the layout
   depends on s alone), reset with seed s (the start is the training start);
2. a fresh per-step :class:`~rcbf_ros.core.filter.SafetyFilter` built from THAT layout's
   barriers (``env.filter_params``), i.e. the new constraints;
3. each step: u_RL = the policy's mean action (plus the compensator, if the run has one), the
   disturbance estimate (mean, std) from the run's trained GP (``gp='learned'``) or the prior
   (zero mean, ``gp_prior_std``; ``gp='prior'``), u* = filter(x, u_RL, mean, std), env step;
4. the row: return, steps, goal reached (completion), true violations, fail-safe steps, and
   how the episode ended (``ending``, one of :data:`rcbf_ros.experiments.metrics.ENDINGS`:
   goal / held by the filter / stalled / still moving, from the last 200 steps' motion and
   filter activity, ``tail_moved`` and ``tail_active``; ``goal_dist`` the final distance).

Rows recorded before endings were (``ending`` absent) get one when their evaluation is next
read: a row that reached the goal needs nothing, a failed layout is re-run (the evaluation is
deterministic given the layout seed) and must reproduce its recorded return, steps and counts.

PVTOL layouts without the operator have a 6-dimensional state while a GP trained with the
operator has 7 inputs: the GP is queried at [x, x1] (the operator right under the drone) and its
first 6 outputs are used. The other way round (the upper bound, trained without the operator, on
a layout with one) the GP is queried at the drone's 6 entries and the operator's entry gets the
prior (zero mean, ``gp_prior_std``). Nothing here trains; the learner is only read.
"""
from __future__ import annotations

import json
import math
from pathlib import Path
import time
from typing import Any, Callable, Literal, Sequence

import numpy as np
import torch

from rcbf_ros.core.config import filter_config_from_params
from rcbf_ros.core.filter import SafetyFilter
from rcbf_ros.envs import make_env
from rcbf_ros.experiments.metrics import episode_ending, episode_tail
from rcbf_ros.learning.sac import SACConfig
from rcbf_ros.parameters.rules import find_config, load_params
from rcbf_ros.training.agent import LearnerConfig, SafeLearner
from rcbf_ros.training.build import build_run, RunConfig
from rcbf_ros.training.run_files import load_payload, write_jsonl

GPSource = Literal['learned', 'prior']


def run_config_from_json(data: dict[str, Any]) -> RunConfig:
    """Rebuild the RunConfig a run wrote to ``run_config.json`` (nested dataclasses)."""
    learner = dict(data['learner'])
    sac = dict(learner.get('sac', {}))
    if 'hidden_sizes' in sac:
        sac['hidden_sizes'] = tuple(sac['hidden_sizes'])
    learner['sac'] = SACConfig(**sac)
    for corner in ('policy_min', 'policy_max'):
        # Runs from before the policy box was configurable drew from the input limits: ().
        learner[corner] = tuple(learner.get(corner) or ())
    return RunConfig(**{**data, 'learner': LearnerConfig(**learner), 'resume': False})


def load_trained_learner(run_dir: str | Path) -> tuple[RunConfig, SafeLearner]:
    """The run's config and its learner restored from ``checkpoint.pt``.

    Raises:
        FileNotFoundError: naming the missing ``run_config.json`` or ``checkpoint.pt``.
        ValueError: naming a checkpoint that holds more than tensors and plain data (refused
            unread) or is damaged.
    """
    run_dir = Path(run_dir)
    for name in ('run_config.json', 'checkpoint.pt'):
        if not (run_dir / name).exists():
            raise FileNotFoundError(f'{name}: not found in {run_dir} (train the run first)')
    run = run_config_from_json(json.loads((run_dir / 'run_config.json').read_text()))
    _, _, learner, _ = build_run(run)
    learner.load_state_dict(load_payload(run_dir / 'checkpoint.pt')['learner'])
    return run, learner


def disturbance_estimate(learner: SafeLearner, state: np.ndarray, gp: GPSource
                         ) -> tuple[np.ndarray, np.ndarray]:
    """(mean, std), each (len(state),), for the filter at ``state`` (see module docstring)."""
    n = state.size
    if gp == 'prior':
        return np.zeros(n), np.full(n, learner.config.gp_prior_std)
    n_gp = learner.system.n_x
    query = np.asarray(state, dtype=np.float64)
    if n < n_gp:  # PVTOL without operator: put the operator under the drone.
        query = np.concatenate([query, np.full(n_gp - n, query[0])])
    elif n > n_gp:  # a learner trained without the operator: the prior for what it never saw
        mean, std = learner.disturbance(torch.as_tensor(query[:n_gp]).unsqueeze(0))
        return (np.concatenate([mean[0].numpy(), np.zeros(n - n_gp)]),
                np.concatenate([std[0].numpy(), np.full(n - n_gp, learner.config.gp_prior_std)]))
    mean, std = learner.disturbance(torch.as_tensor(query).unsqueeze(0))
    return mean[0, :n].numpy().copy(), std[0, :n].numpy().copy()


def evaluate_layout(learner: SafeLearner, system: str, layout_seed: int, *,
                    max_steps: int | None = None, gp: GPSource = 'learned',
                    config_file: str | None = None,
                    trace: list[tuple[np.ndarray, bool]] | None = None) -> dict[str, Any]:
    """One deterministic episode on random layout ``layout_seed`` with the filter of that
    layout; returns the episode row (see module docstring). ``trace`` gets (state, the filter
    corrected the command: |u_S| > 1e-7) for every state, the last one included."""
    path = find_config(config_file or system)
    params = load_params(path, 'simulator')
    params.update({'layout': 'random', 'layout_seed': int(layout_seed)})
    if max_steps is not None:
        params['max_steps'] = int(max_steps)
    env = make_env(system, params)
    config = filter_config_from_params(env.filter_params(load_params(path, 'safety_filter')))
    filt = SafetyFilter(config.problem, fail_safe_action=config.fail_safe_action)
    obs, info = env.reset(seed=int(layout_seed))
    state = info['state']
    row: dict[str, Any] = {'layout_seed': int(layout_seed), 'ret': 0.0, 'steps': 0,
                           'goal_reached': False, 'violations': 0, 'fail_safe': 0,
                           'filter_active': 0, 'min_h_true': math.inf,
                           'n_obstacles': len(env.obstacles)}
    positions, active = [np.array(state[:2], dtype=np.float64)], []
    done = False
    while not done:
        u_rl = learner.sac.act(np.asarray(obs, dtype=np.float64), deterministic=True)
        mean, std = disturbance_estimate(learner, state, gp)
        result = filt.filter(state, np.asarray(u_rl, dtype=np.float64), mean, std)
        if trace is not None:
            correction = np.linalg.norm(result.u_safe - np.asarray(u_rl, dtype=np.float64))
            trace.append((np.array(state, dtype=np.float64), bool(correction > 1e-7)))
        obs, reward, terminated, truncated, info = env.step(result.u_safe)
        state = info['state']
        positions.append(np.array(state[:2], dtype=np.float64))
        active.append(bool(result.active))
        row['ret'] += float(reward)
        row['steps'] += 1
        row['violations'] += int(info['violation'])
        row['fail_safe'] += int(result.fail_safe)
        row['filter_active'] += int(result.active)
        if len(info['h_true']):
            row['min_h_true'] = min(row['min_h_true'], float(np.min(info['h_true'])))
        row['goal_reached'] = row['goal_reached'] or bool(info['goal_reached'])
        done = terminated or truncated
    if trace is not None:
        trace.append((np.array(state, dtype=np.float64), False))
    if math.isinf(row['min_h_true']):
        row['min_h_true'] = None
    tail = episode_tail(positions, active)
    row.update(goal_dist=float(np.linalg.norm(positions[-1] - env.goal)),
               tail_moved=tail.moved, tail_active=tail.active,
               ending=episode_ending(row['goal_reached'], tail))
    if system == 'pvtol':
        row['operator'] = bool(env.with_operator)
    return row


def _leading_rows(lines: Sequence[str], seeds: list[int]) -> tuple[list[dict[str, Any]], bool]:
    """The rows at the head of ``lines`` that evaluated ``seeds[0]``, ``seeds[1]``, ... in order
    (a torn line ends them), and whether a further row stood after them (another seed, or
    more rows than ``seeds``)."""
    rows: list[dict[str, Any]] = []
    for line in lines:
        try:
            row = json.loads(line)
        except json.JSONDecodeError:
            return rows, False
        if len(rows) >= len(seeds) or row.get('layout_seed') != seeds[len(rows)]:
            return rows, True
        rows.append(row)
    return rows, False


def _cached_rows(cache: Path, seeds: list[int]) -> tuple[list[dict[str, Any]], bool]:
    """The rows of ``cache`` that evaluated a prefix of ``seeds`` (a run cut short keeps
    them; a torn last line and anything after it are dropped; another evaluation's file gives
    none), and whether the file holds exactly those rows."""
    if not cache.exists():
        return [], False
    lines = cache.read_text().splitlines(keepends=True)
    rows, more = _leading_rows(lines, seeds)
    if more:
        return [], False
    return rows, len(rows) == len(lines) and all(line.endswith('\n') for line in lines)


def _cache_name(gp: str, layouts: int | str, steps_tag: str) -> str:
    """File name of a run's transfer evaluation (``layouts`` '*' makes it a glob)."""
    return f'transfer_{gp}_L{layouts}_T{steps_tag}.jsonl'


def _borrowed_rows(run_dir: Path, gp: str, steps_tag: str, seeds: list[int]
                   ) -> tuple[list[dict[str, Any]], Path | None]:
    """The longest prefix of ``seeds`` that an evaluation of the same run, disturbance source
    and episode length with another layout count already holds (``..._L50_...`` for a request
    of 200 layouts, or ``..._L200_...`` for 50), and the file it comes from. An evaluation is
    deterministic given the layout seed, so its rows are the rows this one would compute."""
    best: list[dict[str, Any]] = []
    source = None
    own = _cache_name(gp, len(seeds), steps_tag)
    prefix, _, suffix = _cache_name(gp, '*', steps_tag).partition('*')
    for other in sorted(run_dir.glob(prefix + '*' + suffix)):
        count = other.name[len(prefix):-len(suffix)]
        if other.name == own or not count.isdigit():
            continue
        rows, _ = _leading_rows(other.read_text().splitlines(), seeds)
        if len(rows) > len(best):
            best, source = rows, other
    return best, source


_REPRODUCED = ('steps', 'goal_reached', 'violations', 'fail_safe', 'filter_active')
"""Fields a re-run must give exactly as recorded, where recorded (the return: to 1e-9)."""
_ENDING_FIELDS = ('goal_dist', 'tail_moved', 'tail_active', 'ending')


def _add_endings(rows: list[dict[str, Any]], indices: Sequence[int], cache: Path,
                 evaluate: Callable[[int], dict[str, Any]], *, label: str,
                 log: Callable[[str], None] | None, progress_every: int) -> None:
    """Give ``rows[i]`` (i in ``indices``, recorded without an ending) their ending, in place
    and on disk after each: 'goal' for a goal row, a re-run (``evaluate(layout_seed)``) for a
    failed one.

    Raises:
        RuntimeError: a re-run did not reproduce its recorded row (naming the layout).
    """
    failed = [i for i in indices if not rows[i]['goal_reached']]
    for i in indices:
        if rows[i]['goal_reached']:
            rows[i]['ending'] = 'goal'
    write_jsonl(cache, rows)
    if log is not None:
        log(f'{label}: {len(indices)} layouts were recorded without their ending; re-running '
            f'the {len(failed)} that missed the goal')
    for count, i in enumerate(failed, 1):
        row = rows[i]
        again = evaluate(int(row['layout_seed']))
        differs = [k for k in _REPRODUCED if k in row and again[k] != row[k]]
        if not math.isclose(again['ret'], row['ret'], rel_tol=1e-9, abs_tol=1e-9):
            differs.insert(0, 'ret')
        if differs:
            raise RuntimeError(
                f'{label}: layout {row["layout_seed"]} re-run to classify its ending gave '
                + ', '.join(f'{k} {again[k]} (recorded {row[k]})' for k in differs)
                + f'; this code does not reproduce {cache.name} (delete it to re-evaluate)')
        row.update({k: again[k] for k in _ENDING_FIELDS})
        write_jsonl(cache, rows)
        if log is not None and (count % progress_every == 0 or count == len(failed)):
            log(f'{label}: endings {count}/{len(failed)} re-run')


def evaluate_transfer(run_dir: str | Path, layout_seeds: Sequence[int], *,
                      max_steps: int | None = None, gp: GPSource = 'learned',
                      log: Callable[[str], None] | None = None, progress_every: int = 20
                      ) -> list[dict[str, Any]]:
    """Every layout of ``layout_seeds`` for the run in ``run_dir``; cached and resumable.

    Each row goes to ``<run_dir>/transfer_<gp>_L<n>_T<steps>.jsonl`` as soon as its episode
    ends (one line per layout, ``eval_wall_s`` its wall time), so an evaluation that is
    interrupted (Ctrl-C, a crash) continues after its last finished layout; a complete file is
    read back instead of recomputed, and the same run's evaluation with another layout count
    lends its rows (so ``--layouts 200`` after ``--layouts 50`` computes only layouts 50..199).
    ``log`` gets a progress line every ``progress_every`` layouts. Rows recorded without
    their ending get it first (module docstring).

    Raises:
        RuntimeError: a failed layout re-run for its ending did not reproduce its row.
    """
    run_dir = Path(run_dir)
    seeds = [int(s) for s in layout_seeds]
    steps_tag = 'default' if max_steps is None else str(int(max_steps))
    cache = run_dir / _cache_name(gp, len(seeds), steps_tag)
    label = '/'.join(run_dir.parts[-3:])
    rows, clean = _cached_rows(cache, seeds)
    if not rows:
        rows, source = _borrowed_rows(run_dir, gp, steps_tag, seeds)
        if source is not None and log is not None:
            log(f'{label}: transfer reuses {len(rows)} layouts of {source.name}')
    if not clean:  # drop a torn line or another evaluation's rows; write borrowed ones
        write_jsonl(cache, rows)
    unclassified = [i for i, r in enumerate(rows) if 'ending' not in r]
    if len(rows) == len(seeds) and not unclassified:
        return rows
    torch.set_num_threads(1)
    run, learner = load_trained_learner(run_dir)
    if unclassified:
        _add_endings(rows, unclassified, cache, lambda seed: evaluate_layout(
            learner, run.system, seed, max_steps=max_steps, gp=gp, config_file=run.config_file),
            label=label, log=log, progress_every=progress_every)
        if len(rows) == len(seeds):
            return rows
    if rows and log is not None:
        log(f'{label}: transfer resumes after {len(rows)}/{len(seeds)} layouts')
    start = time.perf_counter()
    done_before = len(rows)
    with cache.open('a') as stream:
        for seed in seeds[len(rows):]:
            t0 = time.perf_counter()
            row = evaluate_layout(learner, run.system, seed, max_steps=max_steps, gp=gp,
                                  config_file=run.config_file)
            row['eval_wall_s'] = time.perf_counter() - t0
            stream.write(json.dumps(row) + '\n')
            stream.flush()
            rows.append(row)
            if log is not None and (len(rows) % progress_every == 0 or len(rows) == len(seeds)):
                per = (time.perf_counter() - start) / (len(rows) - done_before)
                log(f'{label}: transfer {len(rows)}/{len(seeds)} layouts, '
                    f'{sum(bool(r["goal_reached"]) for r in rows)} goals, '
                    f'{sum(int(r["violations"]) for r in rows)} violation steps, '
                    f'{per:.1f} s/layout')
    return rows


def evaluate_job(job: tuple[str, tuple[int, ...], int | None, str]) -> list[dict[str, Any]]:
    """Ray/sequential task wrapper: (run_dir, layout_seeds, max_steps, gp) -> rows."""
    run_dir, seeds, max_steps, gp = job
    return evaluate_transfer(run_dir, seeds, max_steps=max_steps, gp=gp,  # type: ignore[arg-type]
                             log=lambda line: print(line, flush=True))
