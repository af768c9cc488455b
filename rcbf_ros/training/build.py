"""Building a training run: its settings, and the env, filter and learner they describe.

A :class:`RunConfig` (built from :class:`~rcbf_ros.training.settings.TrainingSettings`, or
directly) names the system and the config file; :func:`resolve_run` fills in the learner
settings the run leaves to the file's ``/learner`` section (:class:`LearnerSection`, read as the
learner node reads it), and :func:`build_run` makes
the env (``/simulator``), the per-step filter (``/safety_filter``, for the env's layout) and
the :class:`~rcbf_ros.training.agent.SafeLearner`. The in-process trainer
(:mod:`rcbf_ros.training.loop`), the benchmarks and the experiments' evaluation all start here.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any, Callable, Mapping

import numpy as np

from rcbf_ros.core.config import configures_barriers, envelope_problem, filter_config_from_params
from rcbf_ros.core.filter import SafetyFilter
from rcbf_ros.envs import make_env
from rcbf_ros.learning.sac import DEFAULT_INITIAL_ALPHA
from rcbf_ros.parameters.reader import read_parameters, setting
from rcbf_ros.parameters.rules import find_config, load_params
from rcbf_ros.training.agent import LearnerConfig, SafeLearner
from rcbf_ros.training.settings import ALPHA_MAX, TrainingSettings

_RUN = TrainingSettings  # the defaults a run's user may set are written there


@dataclass(frozen=True)
class RunConfig:
    """One training run, as the trainer takes it: the defaults of what a run's user sets are
    :class:`~rcbf_ros.training.settings.TrainingSettings`' (which builds this class)."""

    system: str = _RUN.system
    """unicycle | car_following | pvtol, or the dotted path of a SafetyEnv class (then give
    config_file)."""
    episodes: int = _RUN.episodes
    """Training episodes."""
    out_dir: str = 'runs/unicycle'
    """Where metrics, checkpoints, the bag and the plot go."""
    config_file: str | None = _RUN.config_file
    """ROS params file (default: the packaged config/<system>.yaml)."""
    max_steps: int | None = _RUN.max_steps
    """Override the env's episode length."""
    no_obstacles: bool = _RUN.no_obstacles
    """Train without the layout (the transfer upper bound): no obstacles and, on PVTOL, no safety
    operator (paper: "no obstacles nor a safety operator"). Barriers that do not belong to the
    layout (PVTOL's tilt, thrust and arena envelope) stay in a filter; with none left (Unicycle)
    the run has no filter."""
    random_start: bool | None = _RUN.random_start
    """Start each episode from a random start of the env (Unicycle: corners and edges, random
    heading; the paper's value-map figure shows these starts); None: the config file's
    simulator ``random_start``."""
    checkpoint_every: int = _RUN.checkpoint_every
    """Episodes between checkpoints (a kill loses the episodes since the last one)."""
    record_bag: bool = _RUN.record_bag
    """Record the run's topics to MCAP."""
    resume: bool = _RUN.resume
    """Continue from out_dir/checkpoint.pt (without one: start at episode 0, keeping the files
    already there). Without it, an out_dir that already holds a run is refused."""
    compile_filter: bool = _RUN.compile_filter
    """Compile the per-step filter's autograd constraint assembly (worth it for long runs of a
    system or barrier without a closed form; the built-in ones need none)."""
    threads: int = _RUN.threads
    """torch threads. 1 leaves a core to other work (several runs side by side, or the other
    nodes); a lone in-process run gets 1.2-1.7x faster SAC updates from 2 on a 2-core machine
    (benchmarks/bench_training.py)."""
    learner: LearnerConfig = field(default_factory=LearnerConfig)
    """Learner settings (mode, seed, schedule)."""


class RunSetupError(ValueError):
    """The run cannot start: a bad config file, parameter or setting (the message names it)."""


@dataclass(frozen=True)
class LearnerSection:
    """A config file's ``/learner`` section: the learner settings that belong with the system
    (the temperature is tied to the scale of its reward, the box to how it may be driven, the
    envelope variant to where the paper's Modular fails). The learner node gets them as
    parameters from the same file."""

    initial_alpha: float = setting(DEFAULT_INITIAL_ALPHA, positive=True, maximum=ALPHA_MAX,
                                   description="SAC's initial entropy temperature")
    """SAC's initial entropy temperature."""
    modular_envelope: bool = setting(False, description="modular mode: keep the system "
                                                        "envelope's correction in the losses")
    """LearnerConfig.modular_envelope."""
    policy_min: tuple[float, ...] = setting(
        (), key='policy_limits.min', description='lower corner of the box the policy draws '
                                                 'u_RL from (not set: the input limits)')
    """LearnerConfig.policy_min (``()``: the input limits)."""
    policy_max: tuple[float, ...] = setting(
        (), key='policy_limits.max', description='upper corner of that box (not set: the '
                                                 'input limits)')
    """LearnerConfig.policy_max (``()``: the input limits)."""


POLICY_LIMITS = ('policy_limits.min', 'policy_limits.max')
"""The keys of the policy box in a ``/learner`` section."""


def read_learner_section(params: Mapping[str, Any], keys: tuple[str, ...]) -> LearnerSection:
    """The ``/learner`` settings of ``params`` (flat, dotted keys), reading only ``keys`` (the
    others keep their defaults: a run that sets one does not read the file's).

    Raises:
        ValueError: one line naming the bad key.
    """
    return read_parameters(LearnerSection, {k: params[k] for k in keys if k in params})


def policy_limits(params: Mapping[str, Any]) -> dict[str, tuple[float, ...]]:
    """``policy_min`` / ``policy_max`` of a LearnerConfig from a ``/learner`` section's
    ``policy_limits.min`` / ``.max`` (absent: ``()``, the input limits); errors name the key."""
    section = read_learner_section(params, POLICY_LIMITS)
    return {'policy_min': section.policy_min, 'policy_max': section.policy_max}


def resolve_run(run: RunConfig) -> RunConfig:
    """``run`` with the settings it leaves to the config file filled in from it.

    The learner's ``initial_alpha``, policy box (``policy_limits.min/max``) and
    ``modular_envelope`` come from the file's ``/learner`` section (:class:`LearnerSection`)
    when the run does not set them.

    Raises:
        FileNotFoundError: no such config file.
        ValueError: a bad value in the file (the message names the key).
    """
    learner = run.learner
    keys = (('initial_alpha',) if learner.sac.initial_alpha is None else ()) \
        + (POLICY_LIMITS if learner.policy_min is None else ()) \
        + (('modular_envelope',) if learner.modular_envelope is None else ())
    if not keys:
        return run
    params = load_params(find_config(run.config_file or run.system), 'learner')
    try:
        section = read_learner_section(params, keys)
    except ValueError as exc:
        raise ValueError(f'learner.{exc}') from None
    if learner.sac.initial_alpha is None:
        learner = replace(learner, sac=replace(learner.sac, initial_alpha=section.initial_alpha))
    if learner.policy_min is None:
        learner = replace(learner, policy_min=section.policy_min, policy_max=section.policy_max)
    if learner.modular_envelope is None:
        learner = replace(learner, modular_envelope=section.modular_envelope)
    return replace(run, learner=learner)


def refuse_sensor_sources(filter_section: Mapping[str, Any]) -> None:
    """Refuse a ``/safety_filter`` section with ``observation_sources``: training has no
    sensors (the env's layout is the barrier's obstacles).

    Raises:
        ValueError: one line naming ``observation_sources``.
    """
    if filter_section.get('observation_sources') not in (None, '', [], ()):
        raise ValueError('observation_sources: perception sources are for the safety_filter '
                         "node; training uses the config's static obstacles")


def check_config_file(run: RunConfig) -> None:
    """Read what a run takes from its config file without building anything (a bad file is
    refused before the run says it starts).

    Raises:
        FileNotFoundError: no such config file.
        ValueError: a bad value in the file, or perception sources (naming the key).
    """
    refuse_sensor_sources(load_params(find_config(run.config_file or run.system),
                                      'safety_filter'))
    resolve_run(run)


def build_run(run: RunConfig) -> tuple[Any, SafetyFilter | None, SafeLearner, dict[str, Any]]:
    """Env, per-step filter (None when unconstrained) and learner from the run's config file."""
    run = resolve_run(run)
    path = find_config(run.config_file or run.system)
    sim_params = load_params(path, 'simulator')
    if run.random_start is not None:
        sim_params['random_start'] = bool(run.random_start)
    filter_section = load_params(path, 'safety_filter')
    refuse_sensor_sources(filter_section)
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
                                       else with_far_wall(filter_params))
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


def with_far_wall(params: Mapping[str, Any]) -> dict[str, Any]:
    """Filter parameters without a layout (no obstacles, no bands) but with one far-away wall
    that never binds: without obstacles the learner still needs a problem for its system and
    limits (the filter is not used in that case), and a picture needs a scene."""
    out = {k: v for k, v in params.items() if not k.startswith(('obstacles.', 'bands.'))}
    out.update({'walls.nx': [1.0], 'walls.ny': [0.0], 'walls.offset': [-1e6]})
    return out


def model_functions(system: str, env: Any) -> tuple[Callable, Callable] | None:
    """(reward_fn, obs_fn) in torch for model-based rollouts (None: not available)."""
    return env.torch_models()
