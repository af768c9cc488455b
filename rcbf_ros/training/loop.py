"""In-process training (no middleware): env + SafetyFilter + SafeLearner, Algorithm 1.

One run writes into its output directory::

    metrics.jsonl      one JSON object per episode (return, violations, max slack, steps/s, ...),
                       appended and flushed to disk as each episode ends
    checkpoint.pt      learner + episode counter, every ``checkpoint_every`` episodes and on exit
    policy.pt          the final actor alone (for the ``policy`` node / evaluation)
    bag_0000/          MCAP (rosbag2 layout) of the run's topics, as the node path records them;
                       each resume records into the next one (bag_0001, ...)
    reward_curve.png   return per episode
    trajectories.png   the paths of this start's episodes (at most the last 200) over the
                       layout, where the filter corrected, the closest approach
                       (rcbf_ros.reports.plots.plot_trajectories)

Ctrl-C (KeyboardInterrupt) or an exception ends the run after writing the checkpoint, closing
the bag and the metrics file, so nothing already computed is lost; a kill loses at most the
episodes since the last checkpoint (by default, the one under way). ``resume=True`` continues
from ``checkpoint.pt`` (or, without one, starts again at episode 0 and keeps what is there);
without ``resume`` a directory that already holds a run is refused. Checkpoints and policies
hold tensors and plain data only and are read without running code from them
(:mod:`rcbf_ros.training.run_files`).
"""
from __future__ import annotations

from collections import deque
from dataclasses import asdict, dataclass, field, replace
import json
import math
from pathlib import Path
import time
from typing import Any, Callable, Mapping

import numpy as np
import torch

from rcbf_ros.core.config import (
    configures_barriers,
    envelope_problem,
    filter_config_from_params,
    flag,
    float_list,
    number,
)
from rcbf_ros.core.filter import SafetyFilter
from rcbf_ros.core.filter_info import info_sections
from rcbf_ros.envs import make_env
from rcbf_ros.learning.sac import DEFAULT_INITIAL_ALPHA
from rcbf_ros.parameters.rules import find_config, load_params
from rcbf_ros.training.agent import LearnerConfig, SafeLearner
from rcbf_ros.training.policy_io import save_policy
from rcbf_ros.training.run_files import (
    append_row,
    DEFAULT_CHECKPOINT_EVERY,
    describe_cut,
    load_payload,
    next_bag_dir,
    reconcile_metrics,
    run_data,
    save_payload,
)
from rcbf_ros.training.run_files import write_jsonl as write_jsonl  # re-exported


@dataclass(frozen=True)
class RunConfig:
    """One training run."""

    system: str = 'unicycle'
    """unicycle | car_following | pvtol."""
    episodes: int = 20
    """Training episodes."""
    out_dir: str = 'runs/unicycle'
    """Where metrics, checkpoints, the bag and the plot go."""
    config_file: str | None = None
    """ROS params file (default: the packaged config/<system>.yaml)."""
    max_steps: int | None = None
    """Override the env's episode length."""
    no_obstacles: bool = False
    """Train without the layout (the transfer upper bound): no obstacles and, on PVTOL, no safety
    operator (paper: "no obstacles nor a safety operator"). Barriers that do not belong to the
    layout (PVTOL's tilt, thrust and arena envelope) stay in a filter; with none left (Unicycle)
    the run has no filter."""
    random_start: bool | None = None
    """Start each episode from a random start of the env (Unicycle: corners and edges, random
    heading; the paper's value-map figure shows these starts); None: the config file's
    simulator ``random_start``."""
    checkpoint_every: int = DEFAULT_CHECKPOINT_EVERY
    """Episodes between checkpoints (a kill loses the episodes since the last one)."""
    record_bag: bool = True
    """Record the run's topics to MCAP."""
    resume: bool = False
    """Continue from out_dir/checkpoint.pt (without one: start at episode 0, keeping the files
    already there). Without it, an out_dir that already holds a run is refused."""
    compile_filter: bool = False
    """Compile the per-step filter's autograd constraint assembly (worth it for long runs of a
    system or barrier without a closed form; the built-in ones need none)."""
    threads: int = 1
    """torch threads. 1 leaves a core to other work (several runs side by side, or the other
    nodes); a lone in-process run gets 1.2-1.7x faster SAC updates from 2 on a 2-core machine
    (benchmarks/bench_training.py)."""
    learner: LearnerConfig = field(default_factory=LearnerConfig)
    """Learner settings (mode, seed, schedule)."""


class RunSetupError(ValueError):
    """The run cannot start: a bad config file, parameter or setting (the message names it)."""


def policy_limits(params: Mapping[str, Any]) -> dict[str, tuple[float, ...]]:
    """``policy_min`` / ``policy_max`` of a LearnerConfig from a ``/learner`` section's
    ``policy_limits.min`` / ``.max`` (absent: ``()``, the input limits); errors name the key."""
    return {'policy_min': float_list(params, 'policy_limits.min'),
            'policy_max': float_list(params, 'policy_limits.max')}


def resolve_run(run: RunConfig) -> RunConfig:
    """``run`` with the settings it leaves to the config file filled in from it.

    The learner's ``initial_alpha``, policy box (``policy_limits.min/max``) and
    ``modular_envelope`` come from the file's ``/learner`` section when the run does not set
    them: they belong with the system (the temperature is tied to the scale of its reward, the
    box to how it may be driven, the envelope variant to where the paper's Modular fails).

    Raises:
        FileNotFoundError: no such config file.
        ValueError: a bad value in the file (the message names the key).
    """
    learner = run.learner
    if (learner.sac.initial_alpha is not None and learner.policy_min is not None
            and learner.modular_envelope is not None):
        return run
    section = load_params(find_config(run.config_file or run.system), 'learner')
    try:
        if learner.sac.initial_alpha is None:
            value = number(section, 'initial_alpha', DEFAULT_INITIAL_ALPHA, positive=True)
            learner = replace(learner, sac=replace(learner.sac, initial_alpha=value))
        if learner.policy_min is None:
            learner = replace(learner, **policy_limits(section))
        if learner.modular_envelope is None:
            learner = replace(learner, modular_envelope=flag(section, 'modular_envelope'))
    except ValueError as exc:
        raise ValueError(f'learner.{exc}') from None
    return replace(run, learner=learner)


def build_run(run: RunConfig) -> tuple[Any, SafetyFilter | None, SafeLearner, dict[str, Any]]:
    """Env, per-step filter (None when unconstrained) and learner from the run's config file."""
    run = resolve_run(run)
    path = find_config(run.config_file or run.system)
    sim_params = load_params(path, 'simulator')
    if run.random_start is not None:
        sim_params['random_start'] = bool(run.random_start)
    filter_section = load_params(path, 'safety_filter')
    if run.no_obstacles:
        sim_params.update({'obstacles.x': [], 'obstacles.y': [], 'obstacles.radius': []})
        if 'system_params.with_operator' in sim_params:
            sim_params['system_params.with_operator'] = False
    if run.max_steps is not None:
        sim_params['max_steps'] = int(run.max_steps)
    env = make_env(run.system, sim_params)
    filter_params = env.filter_params(filter_section)
    has_barrier = configures_barriers(filter_params)
    config = filter_config_from_params(filter_params if has_barrier
                                       else _any_barrier(filter_params))
    learner_cfg = run.learner
    # Without the layout only the envelope is filtered, whatever the learner's mode.
    constrained = has_barrier and (learner_cfg.mode != 'unconstrained' or run.no_obstacles)
    if not constrained and learner_cfg.mode != 'unconstrained':
        learner_cfg = replace(learner_cfg, mode='unconstrained')
    obs, _ = env.reset(seed=learner_cfg.seed)
    learner = SafeLearner(config.problem, obs_dim=int(np.asarray(obs).size), dt=env.dt,
                          config=learner_cfg, model_fns=model_functions(run.system, env),
                          envelope=envelope_problem(filter_params)
                          if constrained and learner_cfg.uses_envelope else None)
    filt = SafetyFilter(config.problem, fail_safe_action=config.fail_safe_action,
                        compile_assembly=run.compile_filter or config.compile_assembly) \
        if constrained else None
    return env, filt, learner, filter_params


def _any_barrier(params: dict[str, Any]) -> dict[str, Any]:
    """Without obstacles the learner still needs a problem for its system and limits: a
    far-away wall that never binds (the filter is not used in that case)."""
    out = {k: v for k, v in params.items() if not k.startswith(('obstacles.', 'bands.'))}
    out.update({'walls.nx': [1.0], 'walls.ny': [0.0], 'walls.offset': [-1e6]})
    return out


def model_functions(system: str, env: Any) -> tuple[Callable, Callable] | None:
    """(reward_fn, obs_fn) in torch for model-based rollouts (None: not available)."""
    from rcbf_ros.training.models import MODELS
    return MODELS[system](env) if system in MODELS else None


# --------------------------------------------------------------------------- recording
class RunRecorder:
    """MCAP of an in-process run with the topics the node path uses (so tools read both)."""

    TOPICS = {
        '/state': 'std_msgs/msg/Float64MultiArray',
        '/cmd_proposed': 'std_msgs/msg/Float64MultiArray',
        '/cmd_safe': 'std_msgs/msg/Float64MultiArray',
        '/filter_info': 'std_msgs/msg/Float64MultiArray',
        '/reward': 'std_msgs/msg/Float64',
        '/episode': 'std_msgs/msg/String',
        '/learner/metrics': 'std_msgs/msg/String',
    }

    def __init__(self, directory: Path) -> None:
        from rcbf_ros.bag.writer import BagWriter
        self.writer = BagWriter(directory)
        for name, type_name in self.TOPICS.items():
            self.writer.add_topic(name, type_name)
        self.t_ns = 0

    @staticmethod
    def _array(sections: dict[str, np.ndarray]) -> dict[str, Any]:
        dims = [{'label': k, 'size': int(np.size(v)), 'stride': int(np.size(v))}
                for k, v in sections.items()]
        data = np.concatenate([np.asarray(v, dtype=np.float64).reshape(-1)
                               for v in sections.values()])
        return {'layout': {'dim': dims, 'data_offset': 0}, 'data': data}

    def step(self, t_ns: int, *, state: np.ndarray, proposal: Any, u_safe: np.ndarray,
             reward: float, result: Any = None) -> None:
        """One step as the nodes publish it: the command alone on /cmd_safe, the details on
        /filter_info (``result``: the filter's, None when the run is not filtered)."""
        self.t_ns = t_ns
        self.writer.write_message('/state', self._array({'state': state}), t_ns)
        self.writer.write_message('/cmd_proposed', self._array({
            'u': proposal.u_proposed, 'disturbance_mean': proposal.disturbance_mean,
            'disturbance_std': proposal.disturbance_std, 'state': state}), t_ns)
        self.writer.write_message('/cmd_safe', self._array({'u': u_safe}), t_ns)
        fail_safe = bool(result is not None and result.fail_safe)
        self.writer.write_message('/filter_info', self._array(info_sections(
            u=u_safe, u_rl=proposal.u_proposed, fail_safe=fail_safe, result=result,
            status=result.status if result is not None else 'solved', state=state)), t_ns)
        self.writer.write_message('/reward', {'data': float(reward)}, t_ns)

    def event(self, topic: str, payload: dict[str, Any]) -> None:
        self.writer.write_message(topic, {'data': json.dumps(payload)}, self.t_ns)

    def close(self) -> None:
        self.writer.close()


# --------------------------------------------------------------------------- the loop
@dataclass
class EpisodeStats:
    """Per-episode numbers that go to metrics.jsonl and the progress line."""

    episode: int
    ret: float = 0.0
    steps: int = 0
    violations: int = 0
    min_h_true: float = math.inf
    max_slack: float = 0.0
    filter_active: int = 0
    fail_safe: int = 0
    goal_reached: bool = False
    wall_s: float = 0.0
    extra: dict[str, float] = field(default_factory=dict)

    def as_json(self) -> dict[str, Any]:
        out = asdict(self)
        out.update(out.pop('extra'))
        out['steps_per_s'] = self.steps / self.wall_s if self.wall_s > 0 else 0.0
        out['min_h_true'] = None if math.isinf(self.min_h_true) else self.min_h_true
        return out


@dataclass
class CriticCheck:
    """The critics' value of an episode's first step against the discounted return that
    followed (no bootstrap at a time limit): a persistent ``q_start >> disc_return`` is
    over-estimation. The soft value also counts the entropy bonus, at most
    alpha * entropy / (1 - gamma) more. One per episode, fed in step order by the in-process
    loop and by the learner node alike."""

    gamma: float
    """Discount of the learner's SAC."""
    q_start: float = math.nan
    """Q of the first step at (obs, u_RL -> u_safe), read before that step's update."""
    disc_return: float = 0.0
    """sum_t gamma^t r_t over the steps so far."""
    steps: int = 0

    def step(self, learner: SafeLearner, obs: np.ndarray, u_rl: np.ndarray,
             u_safe: np.ndarray, reward: float) -> None:
        """Account one transition; call before the learner observes it."""
        if self.steps == 0:
            self.q_start = learner.critic_value(obs, u_rl, u_safe)
        self.disc_return += self.gamma ** self.steps * reward
        self.steps += 1

    def as_dict(self) -> dict[str, float]:
        return {'q_start': self.q_start, 'disc_return': self.disc_return}


def run_episode(env: Any, filt: SafetyFilter | None, learner: SafeLearner, *, episode: int,
                seed: int | None, recorder: RunRecorder | None = None, train: bool = True,
                deterministic: bool = False, t0_ns: int = 0,
                trace: list[tuple[np.ndarray, bool]] | None = None) -> EpisodeStats:
    """One episode of Algorithm 1's inner loop (lines 3-7), plus the learner's schedule.

    ``seed`` seeds the env's reset (None: continue its generator), as the simulator node does:
    the first episode with the run's seed, later ones from the same stream. ``trace`` gets
    (state, the filter corrected the command: |u_S| > 1e-7) for every state of the episode,
    the last one included.
    """
    stats = EpisodeStats(episode=episode)
    start = time.perf_counter()
    obs, info = env.reset(seed=seed)
    state = info['state']
    done = False
    critic = CriticCheck(learner.sac.config.gamma)
    while not done:
        proposal = learner.propose(obs, state, deterministic=deterministic)
        if filt is None:
            u_safe, slack, result = proposal.u_proposed, 0.0, None
        else:
            result = filt.filter(state, proposal.u_proposed, proposal.disturbance_mean,
                                 proposal.disturbance_std)
            u_safe, slack = result.u_safe, result.slack
            stats.filter_active += int(result.active)
            stats.fail_safe += int(result.fail_safe)
        if trace is not None:
            correction = np.linalg.norm(np.asarray(u_safe) - proposal.u_proposed)
            trace.append((np.array(state, dtype=np.float64), bool(correction > 1e-7)))
        next_obs, reward, terminated, truncated, info = env.step(u_safe)
        next_state = info['state']
        if train:
            critic.step(learner, obs, proposal.u_rl, u_safe, reward)
            learner.observe(obs=obs, state=state, u_rl=proposal.u_rl, u_safe=u_safe,
                            reward=reward, next_obs=next_obs, next_state=next_state,
                            terminated=terminated)
            learner.after_step()
        if recorder is not None:
            recorder.step(t0_ns + int(1e9 * env.t), state=state, proposal=proposal,
                          u_safe=u_safe, reward=reward, result=result)
        stats.ret += reward
        stats.steps += 1
        stats.violations += int(info['violation'])
        if len(info['h_true']):
            stats.min_h_true = min(stats.min_h_true, float(np.min(info['h_true'])))
        if not math.isnan(slack):
            stats.max_slack = max(stats.max_slack, slack)
        stats.goal_reached = stats.goal_reached or bool(info['goal_reached'])
        obs, state = next_obs, next_state
        done = terminated or truncated
    if trace is not None:
        trace.append((np.array(state, dtype=np.float64), False))
    stats.wall_s = time.perf_counter() - start
    stats.extra = {k: float(v) for k, v in learner.last_metrics.items()}
    if train:
        stats.extra.update(critic.as_dict())
    return stats


def train(run: RunConfig, *, log: Callable[[str], None] = print) -> list[dict[str, Any]]:
    """Train for ``run.episodes`` episodes; returns the per-episode metrics.

    Raises:
        RunSetupError: a bad setting, an out_dir that already holds a run without ``resume``,
            or a checkpoint that cannot be resumed (the message names it).
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
    checkpoint_path = out / 'checkpoint.pt'
    history: list[dict[str, Any]] = []
    first_episode = 0
    saved_at = -1  # env steps the checkpoint on disk holds (-1: none of this start's)
    if run.resume and checkpoint_path.exists():
        first_episode, history = _restore(checkpoint_path, learner, env)
        saved_at = learner.env_steps
        log(f'resumed from {checkpoint_path} at episode {first_episode}')
    elif run.resume:
        log(f'no checkpoint in {out}: starting at episode 0'
            + (' (the files there are kept)' if existing else ''))
    out.mkdir(parents=True, exist_ok=True)
    cut = reconcile_metrics(metrics_path, history=history)
    if cut:
        log(describe_cut(count=cut, history=history))
    (out / 'run_config.json').write_text(json.dumps(asdict(run), indent=2, default=str))
    recorder = None
    if run.record_bag and first_episode < run.episodes:
        recorder = RunRecorder(next_bag_dir(out))
    episode = first_episode
    paths: deque[Any] = deque(maxlen=TRAJECTORY_EPISODES)

    def save_checkpoint() -> None:
        nonlocal saved_at
        save_payload(checkpoint_path, {
            'learner': learner.state_dict(), 'episode': episode,
            'env_rng': env.np_random.bit_generator.state, 'history': history,
            'run': asdict(run)})
        saved_at = learner.env_steps

    try:
        while episode < run.episodes:
            trace: list[tuple[np.ndarray, bool]] = []
            stats = run_episode(env, filt, learner, episode=episode,
                                seed=run.learner.seed if episode == 0 else None,
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
    finally:
        if learner.env_steps != saved_at:  # not already saved with every step taken so far
            save_checkpoint()
        save_policy(out / 'policy.pt', learner.sac, u_low=learner.u_low, u_high=learner.u_high,
                    system=run.system)
        if recorder is not None:
            recorder.close()
        if history:
            from rcbf_ros.reports.plots import plot_reward_curve
            plot_reward_curve([row['ret'] for row in history], out / 'reward_curve.png',
                              title=f'{run.system} / {run.learner.mode}')
        if paths:
            log(draw_trajectories(list(paths), env=env, filter_params=filter_params,
                                  png=out / 'trajectories.png',
                                  title=f'{run.system} / {run.learner.mode}'))
    return history


TRAJECTORY_EPISODES = 200
"""The trajectory picture of an in-process run draws at most this many (the last) episodes."""


def episode_path(number: int, trace: list[tuple[np.ndarray, bool]]) -> Any:
    """The :class:`rcbf_ros.reports.plots.EpisodePath` of a :func:`run_episode` trace."""
    from rcbf_ros.reports.plots import EpisodePath
    return EpisodePath(number, np.array([state for state, _ in trace]),
                       np.array([corrected for _, corrected in trace], dtype=bool))


def draw_trajectories(paths: list[Any], *, env: Any, filter_params: Mapping[str, Any],
                      png: Path, title: str) -> str:
    """Draw episodes (:class:`rcbf_ros.reports.plots.EpisodePath`) over the env's layout into
    ``png``; one line saying where and the closest approach, or why not."""
    from rcbf_ros.core.scene import scene_geometry
    from rcbf_ros.reports.plots import plot_trajectories
    if getattr(env, 'layout_mode', 'fixed') == 'random' and getattr(env, 'layout_seed', 0) < 0:
        return 'trajectories: not drawn: every episode ran on a new random layout'
    try:
        params = filter_params if configures_barriers(filter_params) \
            else _any_barrier(dict(filter_params))
        picture = plot_trajectories(
            paths, scene_geometry(params), png, obstacles=getattr(env, 'obstacles', None),
            goal=getattr(env, 'goal', None), dt=getattr(env, 'dt', None),
            true_gap=getattr(env, 'min_gap', None), title=f'{title}: {len(paths)} episodes')
    except ValueError as exc:
        return f'trajectories: not drawn: {exc}'
    closest = f'; closest approach {picture.closest.describe()}' if picture.closest else ''
    return f'trajectories: {picture.path}{closest}'


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


def _restore(path: Path, learner: SafeLearner, env: Any) -> tuple[int, list[dict[str, Any]]]:
    """Load ``checkpoint.pt`` into ``learner`` and ``env``; (next episode, metrics rows).

    Raises:
        RunSetupError: the file is refused, damaged or of another run (naming it).
    """
    try:
        checkpoint = load_payload(path)
        learner.load_state_dict(checkpoint['learner'])
        env.np_random.bit_generator.state = checkpoint['env_rng']
        return int(checkpoint['episode']), list(checkpoint['history'])
    except KeyError as exc:
        raise RunSetupError(f'resume: {path}: no {exc} entry (not a checkpoint?)') from None
    except (TypeError, ValueError) as exc:
        message = str(exc) if str(exc).startswith(str(path)) else f'{path}: {exc}'
        raise RunSetupError(f'resume: {message}') from None


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
