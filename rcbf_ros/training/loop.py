"""In-process training (no middleware): env + SafetyFilter + SafeLearner, Algorithm 1.

One run writes into its output directory::

    metrics.jsonl      one JSON object per episode (return, violations, max slack, steps/s, ...),
                       appended and flushed to disk as each episode ends
    checkpoint.pt      learner + episode counter (rcbf_ros.training.checkpoint), every
                       ``checkpoint_every`` episodes and on exit
    policy.pt          the final actor alone (for the ``policy`` node / evaluation)
    run_config.json    the resolved :class:`~rcbf_ros.training.build.RunConfig`
    bag_0000/          MCAP (rosbag2 layout) of the run's topics, as the node path records them;
                       each resume records into the next one (bag_0001, ...)
    reward_curve.png   return per episode
    trajectories.png   the paths of this start's episodes (at most the last 200) over the
                       layout, where the filter corrected, the closest approach
                       (rcbf_ros.reports.plots.plot_trajectories)

Ctrl-C (KeyboardInterrupt) or an exception ends the run after writing the checkpoint, closing
the bag and the metrics file, so nothing already computed is lost; a kill loses at most the
episodes since the last checkpoint (by default, the one under way). A write that fails (a full
disk) ends the run too, but nothing more is written: the bag is closed, the previous checkpoint
stays as it was and :class:`~rcbf_ros.training.run_files.RunWriteError` says which file failed.
``resume=True`` continues from ``checkpoint.pt`` (or, without one, starts again at episode 0
and keeps what is there), also one the learner node wrote (:mod:`rcbf_ros.training.checkpoint`:
one format, checked against this run before it is loaded); without ``resume`` a directory that
already holds a run is refused. Checkpoints and policies hold tensors and plain data only and
are read without running code from them (:mod:`rcbf_ros.training.run_files`).

The pieces: :mod:`~rcbf_ros.training.build` (settings -> env, filter, learner),
:mod:`~rcbf_ros.training.episodes` (one episode), :mod:`~rcbf_ros.training.run_files` (the
files), :mod:`~rcbf_ros.training.recorder` (the bag), :mod:`~rcbf_ros.training.progress` and
:mod:`~rcbf_ros.training.pictures` (what the run says and draws). This module runs them in
order, episode after episode.
"""
from __future__ import annotations

from collections import deque
from dataclasses import asdict
import json
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch

from rcbf_ros.training.agent import SafeLearner
from rcbf_ros.training.build import build_run, resolve_run, RunConfig, RunSetupError
from rcbf_ros.training.checkpoint import (
    CHECKPOINT,
    CheckpointError,
    env_seed,
    identity_of,
    read_checkpoint,
    restore_learner,
    write_checkpoint,
)
from rcbf_ros.training.episodes import run_episode
from rcbf_ros.training.pictures import (
    draw_reward_curve,
    draw_trajectories,
    episode_path,
    TRAJECTORY_EPISODES,
)
from rcbf_ros.training.policy_io import save_policy
from rcbf_ros.training.progress import format_progress
from rcbf_ros.training.recorder import RunRecorder
from rcbf_ros.training.run_files import (
    append_row,
    describe_cut,
    describe_write_error,
    next_bag_dir,
    reconcile_metrics,
    run_data,
    RunWriteError,
    write_atomically,
)

MADE_BY = 'rcbf_ros train'
"""The ``made_by`` of this entry point's checkpoints."""


def train(run: RunConfig, *, log: Callable[[str], None] = print) -> list[dict[str, Any]]:
    """Train for ``run.episodes`` episodes; returns the per-episode metrics.

    Raises:
        RunSetupError: a bad setting, an out_dir that already holds a run without ``resume``,
            or a checkpoint that cannot be resumed (the message names it).
        RunWriteError: a file of the run could not be written (a full disk): the run stopped
            there, with its bag closed and the previous checkpoint intact (one line naming
            the file).
    """
    if run.threads < 1:
        raise RunSetupError(f'threads: must be >= 1, got {run.threads}')
    torch.set_num_threads(run.threads)
    if run.episodes < 1:
        raise RunSetupError(f'episodes: must be >= 1, got {run.episodes}')
    if run.checkpoint_every < 1:
        raise RunSetupError(f'checkpoint_every: must be >= 1, got {run.checkpoint_every}')
    out = Path(run.out_dir)
    existing = check_out_dir(run)
    try:
        run = resolve_run(run)
        env, filt, learner, filter_params = build_run(run)
    except (FileNotFoundError, ValueError) as exc:
        raise RunSetupError(str(exc)) from exc
    metrics_path = out / 'metrics.jsonl'
    checkpoint_path = out / CHECKPOINT
    history: list[dict[str, Any]] = []
    first_episode = 0
    first_seed: int | None = run.learner.seed  # the env's seed for the first episode played
    saved_at = -1  # env steps the checkpoint on disk holds (-1: none of this start's)
    saved_episodes: int | None = None  # episodes the checkpoint on disk holds
    if run.resume and checkpoint_path.exists():
        first_episode, history, first_seed = _restore(checkpoint_path, learner, env, run)
        saved_at, saved_episodes = learner.env_steps, first_episode
        log(f'resumed from {checkpoint_path} at episode {first_episode}')
    elif run.resume:
        log(f'no checkpoint in {out}: starting at episode 0'
            + (' (the files there are kept)' if existing else ''))
    recorder = None
    try:
        out.mkdir(parents=True, exist_ok=True)
        cut = reconcile_metrics(metrics_path, history=history)
        if cut:
            log(describe_cut(count=cut, history=history))
        write_atomically(out / 'run_config.json', json.dumps(asdict(run), indent=2, default=str))
        if run.record_bag and first_episode < run.episodes:
            recorder = RunRecorder(next_bag_dir(out))
    except OSError as exc:
        if recorder is not None:
            _close_quietly(recorder)
        raise RunWriteError(f'{describe_write_error(exc)}; the run did not start') from None
    episode = first_episode
    paths: deque[Any] = deque(maxlen=TRAJECTORY_EPISODES)

    def save_checkpoint() -> None:
        nonlocal saved_at, saved_episodes
        write_checkpoint(checkpoint_path, learner=learner, system_name=run.system,
                         episode=episode, history=history,
                         env_rng=env.np_random.bit_generator.state, made_by=MADE_BY,
                         run=asdict(run))
        saved_at, saved_episodes = learner.env_steps, episode

    failure: OSError | None = None
    try:
        while episode < run.episodes:
            trace: list[tuple[np.ndarray, bool]] = []
            stats = run_episode(env, filt, learner, episode=episode,
                                seed=first_seed if episode == first_episode else None,
                                recorder=recorder,
                                t0_ns=int(1e9 * 1e4 * episode), trace=trace)
            episode += 1
            paths.append(episode_path(episode, trace))
            row = stats.as_json()
            row['env_steps'] = learner.env_steps
            history.append(row)
            append_row(metrics_path, row)
            if recorder is not None:
                recorder.event('/episode', {'event': 'end', **{k: row[k] for k in (
                    'episode', 'ret', 'steps', 'violations', 'goal_reached')}})
            log(format_progress(row, run.episodes))
            if episode % run.checkpoint_every == 0:
                save_checkpoint()
    except OSError as exc:
        failure = exc  # a full disk: nothing more is written, the bag is closed below
    finally:
        # A signal can land between the updates above: the rows in ``history`` are the
        # episodes done, and the metrics file gets any row it has not received yet.
        episode = len(history)
        title = f'{run.system} / {run.learner.mode}'

        def final_checkpoint() -> None:
            if learner.env_steps != saved_at:  # not already saved with every step taken
                save_checkpoint()

        def pictures() -> None:
            if history:
                draw_reward_curve(history, png=out / 'reward_curve.png', title=title)
            if paths:
                log(draw_trajectories(list(paths), env=env, filter_params=filter_params,
                                      png=out / 'trajectories.png', title=title))

        steps: list[Callable[[], Any]] = [
            lambda: reconcile_metrics(metrics_path, history=history), final_checkpoint,
            lambda: save_policy(out / 'policy.pt', learner.sac, u_low=learner.u_low,
                                u_high=learner.u_high, system=run.system),
            pictures]
        for step in steps:
            if failure is not None:
                break  # after a failed write nothing more is written
            try:
                step()
            except OSError as exc:
                failure = exc
        if recorder is not None:
            try:
                recorder.close()
            except OSError as exc:
                failure = failure or exc
        if failure is not None:
            kept = ('no checkpoint written yet' if saved_episodes is None else
                    f'{checkpoint_path.name} holds {saved_episodes} episode(s); --resume '
                    'continues from it')
            raise RunWriteError(f'{describe_write_error(failure)}; the run stopped '
                                f'({kept})') from None
    return history


def check_out_dir(run: RunConfig) -> list[str]:
    """The run data already in ``run.out_dir`` (see ``run_files.run_data``).

    Raises:
        RunSetupError: there is some and ``run.resume`` is off.
    """
    existing = run_data(run.out_dir)
    if existing and not run.resume:
        raise RunSetupError(f"out_dir: {run.out_dir} already holds a run "
                            f"({', '.join(existing)}); resume it (--resume) or choose another "
                            'directory')
    return existing


def _restore(path: Path, learner: SafeLearner, env: Any,
             run: RunConfig) -> tuple[int, list[dict[str, Any]], int | None]:
    """Load ``checkpoint.pt`` into ``learner`` and ``env``: (next episode, metrics rows, the
    env's seed for that episode: None to go on with the restored generator).

    A checkpoint of the learner node holds no env generator (the simulator node owns the
    env): the env is seeded from the run's seed and the episode (``checkpoint.env_seed``).

    Raises:
        RunSetupError: the file is refused, damaged or of another run (naming it).
    """
    try:
        checkpoint = read_checkpoint(path, identity=identity_of(learner, run.system))
        restore_learner(learner, checkpoint, path)
    except CheckpointError as exc:
        raise RunSetupError(str(exc)) from None
    seed: int | None = None
    if checkpoint.env_rng is None:
        seed = env_seed(run.learner.seed, checkpoint.episode)
    else:
        try:
            env.np_random.bit_generator.state = checkpoint.env_rng
        except (KeyError, TypeError, ValueError) as exc:
            raise RunSetupError(f'resume: {path}: env_rng: not a generator state of this env '
                                f'({exc})') from None
    if checkpoint.episode == 0:
        seed = run.learner.seed  # nothing played yet: the run's own first episode
    return checkpoint.episode, list(checkpoint.history), seed


def _close_quietly(recorder: RunRecorder) -> None:
    """Close ``recorder`` after another failure (its own is not reported twice)."""
    try:
        recorder.close()
    except OSError:
        pass
