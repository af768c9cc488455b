"""The learner's core: SAC + GP disturbance model + safety layer, with Algorithm 1's schedule.

:class:`SafeLearner` is what both the ``learner`` node and the in-process trainer drive; neither
holds any learning logic of its own, so for the same seed and the same first steps they produce
the same transitions. Per environment step the driver calls

1. :meth:`SafeLearner.propose` -> u_RL (plus the compensator, if any) and the GP estimate
   (mean, std) at the current state, which go to the safety filter;
2. the filter (a separate node, or :class:`~rcbf_ros.core.filter.SafetyFilter` in-process)
   returns u* = u_RL + u_S; the plant steps;
3. :meth:`SafeLearner.observe` stores (o, x, u_RL, u*, u_S, r, o', x', done) and the GP's
   training pair (x, y = (x' - x)/dt - f(x) - g(x) u*);
4. :meth:`SafeLearner.after_step` runs the schedule: SAC updates, the GP refit every
   ``gp_refit_interval`` steps (Algorithm 1 line 2; when the losses pass a layer, followed by
   one pass putting the new GP's estimate at every stored transition into the buffer's memo),
   model rollouts in model-based mode.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Any, Callable, NamedTuple

import numpy as np
import torch

from rcbf_ros.core.dynamics import ControlAffineSystem, nominal_derivative, step_euler
from rcbf_ros.core.rcbf import RCBFProblem
from rcbf_ros.learning.buffers import BatchDisturbance, ReplayBuffer, TransitionBatch
from rcbf_ros.learning.gp import DisturbanceGP, GPConfig
from rcbf_ros.learning.model_based import ModelRollout, RolloutConfig
from rcbf_ros.learning.sac import Mode, MODES, SAC, SACConfig
from rcbf_ros.learning.safety_layer import DifferentiableSafetyLayer
from rcbf_ros.training.settings import TrainingSettings

_RUN = TrainingSettings  # the defaults a run's user may set are written there


@dataclass(frozen=True)
class LearnerConfig:
    """Training schedule and model settings (one per run; the same for node and in-process).

    The fields a run's user sets take their defaults from
    :class:`~rcbf_ros.training.settings.TrainingSettings` (which builds this class); the others
    are the learner's own."""

    mode: Mode = _RUN.mode
    """Which SAC losses: see rcbf_ros.learning.sac (and MODES)."""
    model_based: bool = _RUN.model_based
    """Add k-step synthetic rollouts from prior + GP mean (MB SAC-RCBF, needs mode 'diff')."""
    seed: int = _RUN.seed
    """Seeds networks, buffers, exploration and the GP subsample."""
    batch_size: int = _RUN.batch_size
    """SAC minibatch size."""
    buffer_size: int = 200_000
    """Replay capacity (environment buffer; the model buffer has the same)."""
    start_steps: int = _RUN.start_steps
    """Uniformly random proposals before the policy acts (exploration warm-up)."""
    update_after: int = _RUN.update_after
    """Environment steps before the first SAC update."""
    updates_per_step: int = 1
    """SAC updates per environment step."""
    gp_refit_interval: int = _RUN.gp_refit_interval
    """Environment steps between GP refits (Algorithm 1: once per iteration)."""
    gp_prior_std: float = 0.1
    """Disturbance std assumed before the GP has data (the filter stays robust from step 0)."""
    gp_max_points: int = 512
    """Training-set cap of each GP refit (keeps refit < 2 s and prediction < 1 ms)."""
    k_c: float = _RUN.k_c
    """Disturbance box mean +/- k_c std (paper eq. disturb_estimate)."""
    modular_envelope: bool | None = _RUN.modular_envelope
    """Modular mode: keep the envelope's correction (the barriers that are the same in every
    layout, given to the learner as ``envelope``) in the critic target and actor loss, as the
    authors' code does for PVTOL. False: drop the whole u_S, the paper's eq. q_update_mod. On
    PVTOL use True (config/pvtol.yaml does): there the paper's form drove 3 of 4 seeds into the
    arena's corner (its critic extrapolates at proposals the envelope always cancels), while this
    variant learns the task and transfers at the paper's level (docs/RESULTS.md 4a). ``None``:
    not resolved yet, the training code takes the config file's ``/learner``
    ``modular_envelope`` (else False)."""
    rollout_interval: int = 250
    """Environment steps between model-rollout rounds (model-based only)."""
    rollouts: int = 256
    """M: start states per round."""
    rollout_horizon: int = 3
    """k: model steps per rollout."""
    model_ratio: float = 0.5
    """Fraction of each minibatch drawn from the model buffer (model-based only)."""
    policy_bound: float = 10.0
    """|u_RL| <= policy_bound for systems without actuator limits (SAC needs a box; the
    filter's correction is not limited by it)."""
    policy_min: tuple[float, ...] | None = None
    """Lower corner of the box the policy (and the warm-up's uniform proposals) draws u_RL
    from, one value per input; the filter's correction is not limited by it. ``()``: the
    system's input limits (or +/- policy_bound). ``None``: not resolved yet, the training
    code fills it from the config file's ``/learner`` ``policy_limits.min`` (else ``()``)."""
    policy_max: tuple[float, ...] | None = None
    """Upper corner of that box (``policy_limits.max``); see policy_min."""
    sac: SACConfig = field(default_factory=SACConfig)
    """SAC hyperparameters (its mode is overwritten by ``mode``)."""

    @property
    def uses_envelope(self) -> bool:
        """Whether the learner trains through the envelope's layer (modular with
        ``modular_envelope``): callers build the envelope problem only then."""
        return self.mode == 'modular' and bool(self.modular_envelope)

    def __post_init__(self) -> None:
        if self.mode not in MODES:
            raise ValueError(f'mode: expected one of {MODES}, got {self.mode!r}')
        if self.model_based and self.mode != 'diff':
            raise ValueError("model_based: the model-based variant is MB SAC-RCBF (mode 'diff')")
        for name in ('batch_size', 'buffer_size', 'updates_per_step', 'gp_refit_interval',
                     'rollout_interval', 'rollouts', 'rollout_horizon', 'gp_max_points'):
            if getattr(self, name) < 1:
                raise ValueError(f'{name}: must be >= 1')
        if not self.policy_bound > 0:
            raise ValueError('policy_bound: must be > 0')
        if (self.policy_min is None) != (self.policy_max is None) or \
                len(self.policy_min or ()) != len(self.policy_max or ()):
            raise ValueError('policy_limits: give min and max together, one value per input '
                             f'each (got min {self.policy_min}, max {self.policy_max})')
        if any(not lo < hi for lo, hi in zip(self.policy_min or (), self.policy_max or ())):
            raise ValueError(f'policy_limits: min {self.policy_min} must be < max '
                             f'{self.policy_max} in every input')
        if not 0.0 <= self.model_ratio <= 1.0:
            raise ValueError('model_ratio: must be in [0, 1]')


def policy_box(system: ControlAffineSystem,
               config: LearnerConfig) -> tuple[np.ndarray, np.ndarray]:
    """(low, high), each (n_u,): the box u_RL is drawn from. ``config.policy_min/max`` when
    set, else the system's input limits, else +/- ``config.policy_bound``.

    Raises:
        ValueError: naming ``policy_limits.min`` when the box has not one value per input.
    """
    n_u = system.n_u
    if config.policy_min:
        if len(config.policy_min) != n_u:
            raise ValueError(f'policy_limits.min: expected {n_u} values (one per input), '
                             f'got {len(config.policy_min)}')
        return (np.asarray(config.policy_min, dtype=np.float64),
                np.asarray(config.policy_max, dtype=np.float64))
    if system.u_min is None or system.u_max is None:
        return np.full(n_u, -config.policy_bound), np.full(n_u, config.policy_bound)
    return (np.asarray(system.u_min, dtype=np.float64),
            np.asarray(system.u_max, dtype=np.float64))


class Proposal(NamedTuple):
    """What the learner sends to the safety filter for one state."""

    u_proposed: np.ndarray
    """(n_u,) the action to filter (u_RL, plus the compensator's correction if any)."""
    u_rl: np.ndarray
    """(n_u,) the policy's own sample (stored for the losses)."""
    disturbance_mean: np.ndarray
    """(n_x,) GP mean at the state."""
    disturbance_std: np.ndarray
    """(n_x,) GP std at the state."""


RewardFn = Callable[[torch.Tensor, torch.Tensor, torch.Tensor],
                    tuple[torch.Tensor, torch.Tensor]]
ObsFn = Callable[[torch.Tensor], torch.Tensor]


class SafeLearner:
    """SAC-RCBF learner for one system (see module docstring).

    Args:
        problem: the RCBF problem of the training layout (the one the filter uses).
        obs_dim: observation size.
        dt: the plant's step, for the GP residuals.
        config: schedule and settings.
        model_fns: (reward_fn, obs_fn) in torch for model-based rollouts.
        envelope: the RCBF problem of the system's envelope
            (:func:`rcbf_ros.core.config.envelope_problem`), used by modular mode only.
    """

    def __init__(self, problem: RCBFProblem, obs_dim: int, dt: float,
                 config: LearnerConfig | None = None,
                 model_fns: tuple[RewardFn, ObsFn] | None = None,
                 envelope: RCBFProblem | None = None) -> None:
        self.config = cfg = config or LearnerConfig()
        self.problem = problem
        self.system = problem.system
        self.dt = float(dt)
        n_x, n_u = self.system.n_x, self.system.n_u
        self.u_low, self.u_high = policy_box(self.system, cfg)
        self.gp = DisturbanceGP(n_x, n_x, GPConfig(max_train_points=cfg.gp_max_points,
                                                   prior_std=cfg.gp_prior_std, seed=cfg.seed))
        self.safety_layer = DifferentiableSafetyLayer(problem, self.disturbance)
        self.envelope_layer: DifferentiableSafetyLayer | None = None
        if cfg.uses_envelope and envelope is not None:
            if envelope.system.n_x != n_x:
                raise ValueError(f'envelope: its system has {envelope.system.n_x} states, '
                                 f'the problem {n_x}')
            self.envelope_layer = DifferentiableSafetyLayer(envelope, self.disturbance)
        sac_config = SACConfig(**{**asdict(cfg.sac), 'mode': cfg.mode})
        layer = {'diff': self.safety_layer, 'modular': self.envelope_layer}.get(cfg.mode)
        self.sac = SAC(obs_dim, n_u, self.u_low, self.u_high, sac_config,
                       safety_layer=layer, seed=cfg.seed)
        self.buffer = ReplayBuffer(cfg.buffer_size, obs_dim, n_x, n_u, seed=cfg.seed)
        self.model_buffer: ReplayBuffer | None = None
        self.rollout: ModelRollout | None = None
        if cfg.model_based:
            if model_fns is None:
                raise ValueError('model_based: this system provides no reward/obs model')
            self.model_buffer = ReplayBuffer(cfg.buffer_size, obs_dim, n_x, n_u,
                                             seed=cfg.seed + 7)
            self.rollout = ModelRollout(
                predict_next_state=self.predict_next_state, reward_fn=model_fns[0],
                obs_fn=model_fns[1], policy=self.sac.policy_action,
                safety_layer=self.safety_layer,
                config=RolloutConfig(num_rollouts=cfg.rollouts, horizon=cfg.rollout_horizon))
        self.rng = np.random.default_rng(cfg.seed)
        self.env_steps = 0
        self.last_metrics: dict[str, float] = {}
        # The last action's GP estimate (state, mean, std, GP version), until the transition
        # from its state is stored: for the buffer's memo (``_keep_estimate``).
        self._acted: tuple[np.ndarray, np.ndarray, np.ndarray, int] | None = None

    # ------------------------------------------------------------------ models
    def disturbance(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """GP mean and std at states x: (B, n_x)."""
        mean, std = self.gp.predict(x)
        return mean.to(x.dtype), std.to(x.dtype)

    def predict_next_state(self, state: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        """Euler step of the prior plus the GP mean (model-based rollouts)."""
        x = state.to(torch.float64)
        mean, _ = self.disturbance(x)
        return step_euler(self.system, x, u.to(x.dtype), self.dt, mean).to(state.dtype)

    # ------------------------------------------------------------------ acting
    def propose(self, obs: np.ndarray, state: np.ndarray,
                deterministic: bool = False) -> Proposal:
        """u_RL (random during warm-up) and the GP estimate at ``state``.

        When the losses see the action through a layer, the estimate also goes into the
        buffer's memo of them (``_keep_estimate``), deterministic calls included."""
        if self.env_steps < self.config.start_steps and not deterministic:
            u_rl = self.rng.uniform(self.u_low, self.u_high)
            u_proposed = u_rl
        else:
            detailed = self.sac.act_detailed(np.asarray(obs, dtype=np.float64), deterministic)
            u_rl = detailed.u_rl.astype(np.float64)
            u_proposed = detailed.u_proposed.astype(np.float64)
        # One state, in numpy: the same GP posterior as ``disturbance`` without torch's per-op
        # dispatch (the per-step cost is a few small products, see DisturbanceGP).
        state = np.asarray(state, dtype=np.float64)
        mean, std = self.gp.predict_state(state)
        if self.sac.through_layer:
            self._keep_estimate(state, mean, std)
        return Proposal(u_proposed, u_rl, mean, std)

    def _keep_estimate(self, state: np.ndarray, mean: np.ndarray, std: np.ndarray) -> None:
        """Keep the acting path's estimate for the memo the losses read
        (``ReplayBuffer.predictions``; the same posterior and bound as :meth:`disturbance`):
        the state an action is proposed in is the state of the transition stored next
        (:meth:`observe` puts it into the memo) and, within an episode, the next state of the
        transition stored last (put into the memo here). Without it the update predicts both
        again the first time it draws the transition. ``ReplayBuffer.remember`` keeps it only
        for a slot that holds this state, with the GP version that predicted it (a refit in
        between makes it stale like any memo entry)."""
        version = self.gp.version
        self._acted = (state.copy(), mean.copy(), std.copy(), version)
        if len(self.buffer):
            self.buffer.remember(self.buffer.newest, 1, state, mean, std, version=version)

    def critic_value(self, obs: np.ndarray, u_rl: np.ndarray, u_safe: np.ndarray) -> float:
        """The critics' value (min of the twins) of one step, at the action they are trained
        at; compare with the discounted return that follows to see over-estimation."""
        def row(a: np.ndarray) -> torch.Tensor:
            return torch.as_tensor(np.asarray(a, dtype=np.float64)).unsqueeze(0)
        return float(self.sac.critic_value(row(obs), row(u_rl), row(u_safe)).reshape(-1)[0])

    # ------------------------------------------------------------------ learning
    def observe(self, *, obs: np.ndarray, state: np.ndarray, u_rl: np.ndarray,
                u_safe: np.ndarray, reward: float, next_obs: np.ndarray,
                next_state: np.ndarray, terminated: bool) -> None:
        """Store one transition and the GP's residual pair.

        ``terminated`` is a true terminal (goal reached); a time-limit truncation is not, so the
        critic keeps bootstrapping through it.
        """
        u_rl = np.asarray(u_rl, dtype=np.float64)
        u_safe = np.asarray(u_safe, dtype=np.float64)
        self.buffer.add(obs=obs, state=state, u_rl=u_rl, u_safe=u_safe, u_s=u_safe - u_rl,
                        reward=reward, next_obs=next_obs, next_state=next_state,
                        done=float(terminated))
        acted, self._acted = self._acted, None  # set only when the losses pass a layer
        if acted is not None:
            self.buffer.remember(self.buffer.newest, 0, *acted[:3], version=acted[3])
        x = torch.as_tensor(np.array(state, dtype=np.float64)).unsqueeze(0)
        x_next = torch.as_tensor(np.asarray(next_state, dtype=np.float64)).unsqueeze(0)
        u = torch.as_tensor(u_safe).unsqueeze(0)
        residual = (x_next - x) / self.dt - nominal_derivative(self.system, x, u)
        self.gp.add(x, residual)
        self.env_steps += 1

    def after_step(self) -> dict[str, float]:
        """Run the schedule once per environment step; returns the last update's metrics."""
        cfg = self.config
        if self.env_steps % cfg.gp_refit_interval == 0 and self.gp.num_data >= 16:
            self.gp.fit()
            self._fill_memo()
        if (self.rollout is not None and self.env_steps >= cfg.update_after
                and self.env_steps % cfg.rollout_interval == 0):
            self.rollout.run(self.buffer, self.model_buffer)
        if self.env_steps < cfg.update_after or len(self.buffer) < cfg.batch_size:
            return {}
        for _ in range(cfg.updates_per_step):
            self.last_metrics = self.sac.update(*self.sample_batch())
        return self.last_metrics

    def _fill_memo(self) -> None:
        """After a refit, when the losses see the action through a layer: the new GP's
        estimate at every stored transition into the buffers' memo, in one pass of large
        calls (``ReplayBuffer.fill_predictions``), so that the updates until the next refit
        read the memo instead of predicting their minibatch's stale states in small calls."""
        if not self.sac.through_layer:
            return
        for buffer in (self.buffer, self.model_buffer):
            if buffer is not None:
                buffer.fill_predictions(version=self.gp.version, predict=self.disturbance)

    def sample_batch(self) -> tuple[TransitionBatch, BatchDisturbance | None]:
        """A minibatch; in model-based mode a ``model_ratio`` share comes from the model.

        When the losses see the action through a safety layer, also the GP's estimate at the
        batch's states, memoised per stored transition until the next refit (the GP changes
        only there): each transition's states are predicted once per refit instead of at every
        draw of it. Otherwise None.
        """
        cfg = self.config
        if self.model_buffer is None or len(self.model_buffer) == 0:
            return self._draw(self.buffer, cfg.batch_size)
        n_model = int(round(cfg.model_ratio * cfg.batch_size))
        real, real_estimate = self._draw(self.buffer, cfg.batch_size - n_model)
        model, model_estimate = self._draw(self.model_buffer, n_model)
        batch = TransitionBatch(*(torch.cat([a, b]) for a, b in zip(real, model)))
        if real_estimate is None or model_estimate is None:
            return batch, None
        return batch, BatchDisturbance(*(torch.cat([a, b]) for a, b in
                                          zip(real_estimate, model_estimate)))

    def _draw(self, buffer: ReplayBuffer, size: int
              ) -> tuple[TransitionBatch, BatchDisturbance | None]:
        index = buffer.sample_index(size)
        if not self.sac.through_layer:
            return buffer.gather(index), None
        return buffer.gather(index), buffer.predictions(index, version=self.gp.version,
                                                        predict=self.disturbance)

    # ------------------------------------------------------------------ checkpoints
    def state_dict(self) -> dict[str, Any]:
        """Everything needed to resume: networks, optimizers, GP data, buffers, RNG states."""
        return {
            'config': asdict(self.config), 'sac': self.sac.state_dict(),
            'gp': self.gp.state_dict(), 'buffer': self.buffer.state_dict(),
            'model_buffer': None if self.model_buffer is None else self.model_buffer.state_dict(),
            'rng': self.rng.bit_generator.state, 'env_steps': self.env_steps,
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore :meth:`state_dict`."""
        self.sac.load_state_dict(state['sac'])
        self.gp.load_state_dict(state['gp'])
        self.buffer.load_state_dict(state['buffer'])
        if self.model_buffer is not None and state.get('model_buffer') is not None:
            self.model_buffer.load_state_dict(state['model_buffer'])
        self.rng.bit_generator.state = state['rng']
        self.env_steps = int(state['env_steps'])
        self._acted = None
