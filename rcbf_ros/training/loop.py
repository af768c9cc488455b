"""In-process training (no middleware): env + SafetyFilter + SafeLearner, Algorithm 1.

Runs the pieces of ``rcbf_ros.training`` (build, episodes, run, recorder, progress, pictures)
in order, episode after episode, writing metrics, checkpoints, the policy, a bag and plots into
one output directory. An interrupt, an exception or a failed write ends the run without losing
what is already written; ``resume=True`` continues from the checkpoint.

The output directory, ending and resuming: docs/DESIGN.md#the-in-process-training-run
"""
from __future__ import annotations

from collections import deque
from dataclasses import asdict
import json
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch

from rcbf_ros.training.build import build_run, resolve_run, RunConfig, RunSetupError
from rcbf_ros.training.checkpoint import Checkpoint, CheckpointError, env_seed, identity_of
from rcbf_ros.training.episodes import run_episode
from rcbf_ros.training.pictures import (
    draw_reward_curve,
    draw_trajectories,
    episode_path,
    TRAJECTORY_EPISODES,
)
from rcbf_ros.training.progress import format_progress
from rcbf_ros.training.recorder import RunRecorder
from rcbf_ros.training.run import TRAINER, TrainingRun
from rcbf_ros.training.run_files import (
    describe_write_error,
    next_bag_dir,
    RunWriteError,
    write_atomically,
)


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
    check_out_dir(run)
    try:
        run = resolve_run(run)
        env, filt, learner, filter_params = build_run(run)
    except (FileNotFoundError, ValueError) as exc:
        raise RunSetupError(str(exc)) from exc
    files = training_run(run, log=log)
    first_seed: int | None = run.learner.seed  # the env's seed for the first episode played
    try:
        checkpoint = files.open(identity_of(learner, run.system))
        if checkpoint is not None:
            files.restore(learner, checkpoint)
            first_seed = _restore_env(env, checkpoint, files.checkpoint_path, run)
    except CheckpointError as exc:
        raise RunSetupError(str(exc)) from None
    first_episode = files.episodes
    recorder = None
    try:
        write_atomically(out / 'run_config.json', json.dumps(asdict(run), indent=2, default=str))
        if run.record_bag and first_episode < run.episodes:
            recorder = RunRecorder(next_bag_dir(out))
    except OSError as exc:
        if recorder is not None:
            _close_quietly(recorder)
        raise RunWriteError(f'{describe_write_error(exc)}; the run did not start') from None
    paths: deque[Any] = deque(maxlen=TRAJECTORY_EPISODES)

    def env_rng() -> dict[str, Any]:
        return env.np_random.bit_generator.state

    failure: OSError | None = None
    try:
        while files.episodes < run.episodes:
            episode = files.episodes
            trace: list[tuple[np.ndarray, bool]] = []
            stats = run_episode(env, filt, learner, episode=episode,
                                seed=first_seed if episode == first_episode else None,
                                recorder=recorder,
                                t0_ns=int(1e9 * 1e4 * episode), trace=trace)
            paths.append(episode_path(episode + 1, trace))
            row = stats.as_json()
            row['env_steps'] = learner.env_steps
            files.record(row)
            if recorder is not None:
                recorder.event('/episode', {'event': 'end', **{k: row[k] for k in (
                    'episode', 'ret', 'steps', 'violations', 'goal_reached')}})
            log(format_progress(row, run.episodes))
            if files.checkpoint_due():
                files.save_checkpoint(learner, env_rng=env_rng())
    except OSError as exc:
        failure = exc  # a full disk: nothing more is written, the bag is closed below
    finally:
        # A signal can land between the updates above: the rows in the run's history are the
        # episodes done, and the metrics file gets any row it has not received yet.
        title = f'{run.system} / {run.learner.mode}'

        def pictures() -> None:
            if files.history:
                draw_reward_curve(files.history, png=out / 'reward_curve.png', title=title)
            if paths:
                log(draw_trajectories(list(paths), env=env, filter_params=filter_params,
                                      png=out / 'trajectories.png', title=title))

        try:
            if failure is None:  # after a failed write nothing more is written
                try:
                    files.finish(learner, env_rng=env_rng(), then=(pictures,))
                except OSError as exc:
                    failure = exc
        finally:  # a signal during the finish (the pictures take a while) still closes the bag
            if recorder is not None:
                try:
                    recorder.close()
                except OSError as exc:
                    failure = failure or exc
        if failure is not None:
            raise RunWriteError(files.stopped(failure)) from None
    return files.history


def training_run(run: RunConfig, *, log: Callable[[str], None] = print) -> TrainingRun:
    """The :class:`~rcbf_ros.training.run.TrainingRun` of ``run`` (not opened yet)."""
    return TrainingRun(run.out_dir, entry=TRAINER, system_name=run.system, resume=run.resume,
                       checkpoint_every=run.checkpoint_every, settings=asdict(run), log=log)


def check_out_dir(run: RunConfig) -> list[str]:
    """The run data already in ``run.out_dir`` (see ``run_files.run_data``).

    Raises:
        RunSetupError: there is some and ``run.resume`` is off.
    """
    return training_run(run).check_out_dir()


def _restore_env(env: Any, checkpoint: Checkpoint, path: Path, run: RunConfig) -> int | None:
    """Put the env's episode generator where ``checkpoint`` left it; returns the env's seed
    for the next episode (None: go on with the restored generator).

    A checkpoint of the learner node holds no env generator (the simulator node owns the
    env): the env is seeded from the run's seed and the episode (``checkpoint.env_seed``).

    Raises:
        CheckpointError: the generator state does not fit this env (naming the file).
    """
    seed: int | None = None
    if checkpoint.env_rng is None:
        seed = env_seed(run.learner.seed, checkpoint.episode)
    else:
        try:
            env.np_random.bit_generator.state = checkpoint.env_rng
        except (KeyError, TypeError, ValueError) as exc:
            raise CheckpointError(f'resume: {path}: env_rng: not a generator state of this '
                                  f'env ({exc})') from None
    if checkpoint.episode == 0:
        seed = run.learner.seed  # nothing played yet: the run's own first episode
    return seed


def _close_quietly(recorder: RunRecorder) -> None:
    """Close ``recorder`` after another failure (its own is not reported twice)."""
    try:
        recorder.close()
    except OSError:
        pass
