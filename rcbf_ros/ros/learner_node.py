"""``learner`` node: SAC-RCBF training against the simulator and safety_filter nodes.

Thin wrapper around :class:`rcbf_ros.training.agent.SafeLearner` (the same class the in-process
trainer drives). Lock-step protocol with the simulator:

- ``sim/step`` (Float64MultiArray, sections ``state``, ``observation``, ``reward``,
  ``terminated``, ``truncated``, ``violation``, ``goal_reached``, ``episode``, ``step``): one
  message per plant step; ``reward`` is the reward of the transition INTO this state.
- the learner answers a non-terminal step with ``cmd_proposed`` (sections ``u``,
  ``disturbance_mean``, ``disturbance_std``, ``state``) for the safety_filter, whose answer
  u* reaches the plant (the learner reads neither ``cmd_safe`` nor ``filter_info``);
- the next ``sim/step`` carries the ``action`` the plant applied (u*), which completes the
  transition; the learner does not pair topics by arrival order (DDS does not order samples
  of different writers).

Per episode it logs a progress line, appends to ``<out_dir>/metrics.jsonl`` (flushed to disk)
and publishes the line as JSON on ``learner/metrics`` (so the run's MCAP holds it); checkpoints
every ``checkpoint_every`` episodes (default every one) and on exit (Ctrl-C/SIGTERM included);
after ``episodes`` it writes policy.pt, the reward curve and a summary, and shuts down.
``resume:=true`` continues from ``<out_dir>/checkpoint.pt`` (without one it starts at episode 0,
keeping the files there), also one ``rcbf_ros train`` wrote: the format is one
(:mod:`rcbf_ros.training.checkpoint`), and a checkpoint of another system, mode or network is
refused before it is loaded (exit 2, one line naming what differs). The simulator node owns the
env, so a checkpoint's env generator is not restored here and this node writes none. Without
``resume`` an ``out_dir`` that already holds a run is refused (exit 2). A file that cannot be
written (a full disk) stops the node with one line and exit status 1; nothing more is written
and the previous checkpoint stays as it was. The run's lifecycle in ``out_dir`` is
:class:`rcbf_ros.training.run.TrainingRun`, the one ``rcbf_ros train`` drives: checkpoints are
read without running code from them.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace
import json
import math
from pathlib import Path
import sys
import time
from typing import Any, Mapping

import numpy as np
import torch

from rcbf_ros.core.config import build_system, envelope_problem, filter_config_from_params
from rcbf_ros.envs.base import DT_LIMITS_S, EnvSettings
from rcbf_ros.learning.sac import DEFAULT_INITIAL_ALPHA
from rcbf_ros.messages.conversions import msg_to_sections, sections_to_msg
from rcbf_ros.node_logic.edges import SIM_STEP_SECTIONS
from rcbf_ros.node_logic.interface import (
    FLOAT64_MULTIARRAY,
    NodeInterface,
    parameter_specs,
    ParameterSpec,
    TopicSpec,
)
from rcbf_ros.parameters.reader import read_parameters, setting
from rcbf_ros.ros.node_main import declare_specs, request_stop, run_node
from rcbf_ros.ros.runtime import get_message, Node, QoSProfile
from rcbf_ros.training.agent import LearnerConfig, policy_box, SafeLearner
from rcbf_ros.training.build import LearnerSection, POLICY_LIMITS, policy_limits
from rcbf_ros.training.checkpoint import Checkpoint, CheckpointError, learner_identity
from rcbf_ros.training.episodes import CriticCheck
from rcbf_ros.training.pictures import draw_reward_curve
from rcbf_ros.training.progress import format_progress, summarize
from rcbf_ros.training.run import NODE, TrainingRun
from rcbf_ros.training.run_files import RunWriteError, write_atomically
from rcbf_ros.training.settings import TrainingSettings

WRITE_FAILED = 1
"""Exit status after a file of the run could not be written (a full disk)."""
BAD_CHECKPOINT = 2
"""Exit status for a checkpoint this run cannot resume (as for a bad parameter)."""


@dataclass(frozen=True)
class SimulatorLink:
    """The node's one parameter that is not a run's setting (the env is the simulator's)."""

    dt: float = setting(EnvSettings.dt, minimum=DT_LIMITS_S[0], maximum=DT_LIMITS_S[1],
                        description="the simulator's step (s), for the GP's derivatives")
    """The simulator's step (s)."""


NODE_DEFAULTS: dict[str, Any] = {
    'episodes': 10, 'out_dir': 'bags/learner_run', 'initial_alpha': DEFAULT_INITIAL_ALPHA,
    'modular_envelope': False}
"""The node's defaults where they are not :class:`TrainingSettings`' (``rcbf_ros train``'s): a
shorter run, written beside the bags; the ``/learner`` values declared with their value when
unset (the params file sets them)."""
NODE_SETTINGS: tuple[str, ...] = (
    'system', 'mode', 'model_based', 'seed', 'episodes', 'out_dir', 'dt', 'start_steps',
    'update_after', 'batch_size', 'gp_refit_interval', 'checkpoint_every', 'resume', 'k_c',
    'threads', 'initial_alpha', 'modular_envelope')
"""The node's own parameters, in declaration order: the run's settings the node takes (the
others, such as ``max_steps`` or ``record_bag``, are the simulator's and the recorder's), and
``dt``."""


def _node_parameters() -> tuple[ParameterSpec, ...]:
    specs = {spec.name: spec for spec in
             parameter_specs(TrainingSettings) + parameter_specs(SimulatorLink)}
    return tuple(replace(specs[name], default=NODE_DEFAULTS[name]) if name in NODE_DEFAULTS
                 else specs[name] for name in NODE_SETTINGS)


LEARNER_PARAMETERS: tuple[ParameterSpec, ...] = _node_parameters()
"""The learner's own parameters, in declaration order."""
PARAMETERS: dict[str, Any] = {spec.name: spec.default for spec in LEARNER_PARAMETERS}
"""Name -> default of :data:`LEARNER_PARAMETERS`."""

FILE_PARAMETERS: tuple[ParameterSpec, ...] = tuple(
    spec for spec in parameter_specs(LearnerSection, declared_defaults=False)
    if spec.name in POLICY_LIMITS)
"""Read from the params file when given (``/learner`` section), declared only then."""

INTERFACE = NodeInterface(
    node='learner',
    summary='SAC-RCBF training against the simulator and safety_filter nodes, in lock-step.',
    topics=(
        TopicSpec('sim/step', 'sub', FLOAT64_MULTIARRAY,
                  "the simulator's per-step sections: " + ', '.join(SIM_STEP_SECTIONS)),
        TopicSpec('cmd_proposed', 'pub', FLOAT64_MULTIARRAY,
                  'sections u (n_u), disturbance_mean, disturbance_std, state (n_x each)'),
        TopicSpec('learner/metrics', 'pub', 'std_msgs/msg/String',
                  "one JSON row per episode (as metrics.jsonl's)"),
    ),
    parameters=LEARNER_PARAMETERS + FILE_PARAMETERS,
    notes=("The safety problem's keys (system, obstacles.*, alpha, ...: see safety_filter "
           '--help) come from the params file (/** section) and are declared when given.',),
)
"""Topics and parameters (``learner --help``, README)."""


def node_settings(values: Mapping[str, Any]) -> TrainingSettings:
    """The run's settings from the node's parameter values (:data:`PARAMETERS`' defaults for
    the ones not in ``values``).

    Raises:
        ParameterError: one line naming the bad parameter.
    """
    return read_parameters(TrainingSettings, {**PARAMETERS, **values})


def learner_config_from_settings(s: TrainingSettings,
                                 filter_params: Mapping[str, Any]) -> LearnerConfig:
    """The LearnerConfig of the node's settings and of the params file's ``/learner`` policy
    box (in ``filter_params``: every parameter given to the node), as the in-process trainer
    reads it (``resolve_run``).

    Raises:
        ValueError: naming the bad policy box key.
    """
    return s.learner_config(**policy_limits(filter_params))


def learner_from_settings(s: TrainingSettings, filter_params: Mapping[str, Any],
                          obs_dim: int, *, dt: float = SimulatorLink.dt) -> SafeLearner:
    """The node's SafeLearner from its settings and the shared safety problem's parameters
    (``filter_params``): the same RCBF problem the safety_filter node solves, and, when
    ``modular_envelope`` asks for it in ``modular`` mode, the envelope problem of its losses;
    ``dt``: the simulator's step."""
    params = {**filter_params, 'k_c': s.k_c}
    config = filter_config_from_params(params)
    learner_cfg = learner_config_from_settings(s, filter_params)
    return SafeLearner(config.problem, obs_dim=obs_dim, dt=dt,
                       config=learner_cfg,
                       envelope=envelope_problem(params) if learner_cfg.uses_envelope else None)


@dataclass
class EpisodeTally:
    """Running numbers of the current episode."""

    episode: int = 0
    ret: float = 0.0
    steps: int = 0
    violations: int = 0
    goal_reached: bool = False
    critic: CriticCheck | None = None
    """First-step value vs discounted return, as the in-process trainer keeps it."""
    started: float = field(default_factory=time.perf_counter)


class LearnerNode(Node):
    """See module docstring."""

    def __init__(self) -> None:
        super().__init__('learner', automatically_declare_parameters_from_overrides=True)
        declare_specs(self, LEARNER_PARAMETERS)
        values = {name: self.get_parameter(name).value for name in PARAMETERS}
        self.settings = node_settings(values)
        self.dt = read_parameters(SimulatorLink, values).dt
        # 1 by default: the simulator, filter and recorder share the cores.
        torch.set_num_threads(self.settings.threads)
        # The safety problem's keys (system, obstacles.*, gains) come from the params file.
        self.filter_params = self._declared_filter_params()
        # The learner is built at the first step (it needs the observation's size); its
        # settings and policy box are checked now, so that a bad one exits 2 naming the key.
        system = build_system(self.filter_params)
        config = learner_config_from_settings(self.settings, self.filter_params)
        policy_box(system, config)
        # What a checkpoint to resume must match (the observation's size: at the first step).
        self.identity = learner_identity(system_name=self.settings.system, system=system,
                                         config=config, obs_dim=None)
        self.out_dir = Path(self.settings.out_dir)
        self.learner: SafeLearner | None = None
        self.pending: dict[str, np.ndarray] | None = None
        self.pending_msg: Any = None
        self.tally = EpisodeTally()
        # (exit status, one line) once the node has to stop: nothing more is written.
        self.failure: tuple[int, str] | None = None
        # The run's files (as rcbf_ros train's); the checkpoint to resume is loaded into the
        # learner when it is built.
        self.run = TrainingRun(self.out_dir, entry=NODE, system_name=self.settings.system,
                               resume=self.settings.resume,
                               checkpoint_every=self.settings.checkpoint_every,
                               settings=values,
                               log=self.get_logger().info)
        try:
            self.resume_from: Checkpoint | None = self.run.open(self.identity)
        except RunWriteError as exc:  # out_dir cannot be made or written: exit 2 naming it
            raise ValueError(f'out_dir: {exc}') from None
        self.last_step: tuple[int, int] | None = None
        qos = QoSProfile(depth=10)
        self.proposal_pub = self.create_publisher(
            get_message('std_msgs/msg/Float64MultiArray'), 'cmd_proposed', qos)
        self.metrics_pub = self.create_publisher(
            get_message('std_msgs/msg/String'), 'learner/metrics', qos)
        self.create_subscription(get_message('std_msgs/msg/Float64MultiArray'), 'sim/step',
                                 self.on_step, qos)
        self.get_logger().info(
            f'learner: {self.settings.mode} on {self.settings.system}, '
            f'{self.settings.episodes} episodes -> {self.out_dir}')

    def _declared_filter_params(self) -> dict[str, Any]:
        """Every parameter given to this node (params file / -p), flat, for the RCBF problem."""
        params = {name: p.value for name, p in self.get_parameters_by_prefix('').items()}
        params['system'] = self.settings.system
        return params

    # ----------------------------------------------------------------- callbacks
    def on_step(self, msg: Any) -> None:
        if self.failure is not None:
            return  # stopping: the step is not answered
        try:
            sections = msg_to_sections(msg)
            state, obs = sections['state'], sections['observation']
        except (KeyError, ValueError) as exc:
            self.get_logger().error(f'sim/step: {exc}')
            return
        index = (int(sections.get('episode', [-1])[0]), int(sections.get('step', [-1])[0]))
        if index == self.last_step:
            # The simulator re-published a step we answered: our proposal was lost (e.g. the
            # filter was not subscribed yet). Send the same proposal again; never re-sample.
            if self.pending_msg is not None:
                self.proposal_pub.publish(self.pending_msg)
            return
        self.last_step = index
        if self.learner is None:
            try:
                self.learner = self._build_learner(obs_dim=obs.size)
            except CheckpointError as exc:
                self._fail(BAD_CHECKPOINT, str(exc))
                return
        flag = lambda key: bool(sections.get(key, np.zeros(1))[0] > 0.5)  # noqa: E731
        terminated, truncated = flag('terminated'), flag('truncated')
        if int(sections.get('step', np.zeros(1))[0]) == 0:
            self.pending = None
            self.tally = EpisodeTally(episode=self.episodes_done)
        if self.pending is not None:
            if 'action' not in sections:
                self.get_logger().error('sim/step: no action section; transition dropped')
            else:
                reward = float(sections.get('reward', np.zeros(1))[0])
                if self.tally.critic is None:
                    self.tally.critic = CriticCheck(self.learner.sac.config.gamma)
                self.tally.critic.step(self.learner, self.pending['obs'], self.pending['u_rl'],
                                       sections['action'], reward)
                self.learner.observe(obs=self.pending['obs'], state=self.pending['state'],
                                     u_rl=self.pending['u_rl'], u_safe=sections['action'],
                                     reward=reward, next_obs=obs, next_state=state,
                                     terminated=terminated)
                self.learner.after_step()
                self.tally.ret += reward
                self.tally.steps += 1
                self.tally.violations += int(flag('violation'))
                self.tally.goal_reached |= flag('goal_reached')
        self.pending = None
        self.pending_msg = None
        if terminated or truncated:
            self._end_episode()
            return
        proposal = self.learner.propose(obs, state)
        self.pending = {'obs': obs, 'state': state, 'u_rl': proposal.u_rl}
        self.pending_msg = sections_to_msg({
            'u': proposal.u_proposed, 'disturbance_mean': proposal.disturbance_mean,
            'disturbance_std': proposal.disturbance_std, 'state': state})
        self.proposal_pub.publish(self.pending_msg)

    # ----------------------------------------------------------------- bookkeeping
    def _build_learner(self, obs_dim: int) -> SafeLearner:
        """The learner for observations of ``obs_dim`` values, with the checkpoint to resume
        loaded. CheckpointError: the checkpoint's observation size or state does not fit."""
        learner = learner_from_settings(self.settings, self.filter_params, obs_dim,
                                        dt=self.dt)
        if self.resume_from is not None:
            self.run.restore(learner, self.resume_from)
            self.resume_from = None
        return learner

    def _fail(self, status: int, line: str) -> None:
        """Stop after this callback with exit status ``status`` and ``line`` on stderr
        (:func:`main`); nothing more is written. The first failure is the one reported."""
        if self.failure is None:
            self.failure = (status, line)
        request_stop()

    def _write_failed(self, exc: OSError) -> None:
        self._fail(WRITE_FAILED, self.run.stopped(exc))

    @property
    def episodes_done(self) -> int:
        """Episodes done (a resumed run's included)."""
        return self.run.episodes

    def _end_episode(self) -> None:
        t = self.tally
        wall = time.perf_counter() - t.started
        row = {'episode': t.episode, 'ret': t.ret, 'steps': t.steps,
               'violations': t.violations, 'goal_reached': t.goal_reached,
               'wall_s': wall,
               'steps_per_s': t.steps / wall if wall > 0 else 0.0,
               # no transition this episode: an unfed check's values (gamma unused)
               **(t.critic or CriticCheck(gamma=math.nan)).as_dict(),
               'env_steps': self.learner.env_steps if self.learner else 0}
        try:
            self.run.record(row)
        except OSError as exc:
            self._write_failed(exc)
            return
        msg = get_message('std_msgs/msg/String')()
        msg.data = json.dumps(row)
        self.metrics_pub.publish(msg)
        self.get_logger().info(format_progress(row, self.settings.episodes))
        if self.run.checkpoint_due():
            self.save_checkpoint()
        if self.episodes_done >= self.settings.episodes:
            self.finish()
            request_stop()  # then destroy_node and the shutdown, after this callback

    def save_checkpoint(self) -> None:
        """Write the learner and the episodes done to checkpoint.pt (atomically); a failed
        write stops the node (:meth:`_fail`), the previous checkpoint intact."""
        if self.learner is None or self.failure is not None:
            return
        try:
            self.run.save_checkpoint(self.learner, env_rng=None)
        except OSError as exc:
            self._write_failed(exc)

    def finish(self) -> dict[str, Any]:
        """Checkpoint, policy export, reward curve and summary.json; returns the summary.
        Before the first step of a new run, or after a failure, nothing is written."""
        history = self.run.history
        summary = summarize(history)
        if (self.learner is None and not history) or self.failure is not None:
            return summary

        def reward_curve() -> None:
            if history:
                png = self.out_dir / 'reward_curve.png'
                draw_reward_curve(history, png=png, title=f'{self.settings.system} / '
                                  f'{self.settings.mode} (nodes over DDS)')
                summary['reward_curve'] = str(png)

        def summary_file() -> None:
            write_atomically(self.out_dir / 'summary.json', json.dumps(summary, indent=2))

        try:
            self.run.finish(self.learner, env_rng=None, then=(reward_curve, summary_file))
        except OSError as exc:
            self._write_failed(exc)
        return summary


def main(args: list[str] | None = None) -> int:
    """Run until the episodes are done or Ctrl-C / SIGTERM. Returns 2 on invalid parameters
    or a checkpoint this run cannot resume, 1 when a file could not be written (one line on
    stderr either way)."""
    stopped: list[LearnerNode] = []

    def keep_what_was_learned(node: LearnerNode) -> None:
        stopped.append(node)
        if node.episodes_done < node.settings.episodes:
            node.finish()  # Ctrl-C / SIGTERM before the last episode

    status = run_node('learner', LearnerNode, args, on_exit=keep_what_was_learned,
                      setup_errors=(ValueError,), interface=INTERFACE)
    failure = stopped[0].failure if stopped else None
    if status == 0 and failure is not None:
        print(f'learner: {failure[1]}', file=sys.stderr)
        return failure[0]
    return status


if __name__ == '__main__':
    sys.exit(main())
