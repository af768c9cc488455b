"""Soft Actor-Critic with the training modes of SAC-RCBF (paper: "Soft Actor-Critic",
"Differentiable Safety Layer", "Modular Task Learning").

One code path, one flag (``SACConfig.mode``: ``unconstrained``, ``baseline``,
``baseline_compensator``, ``diff``, ``modular``) chooses what the critic and the actor train on.
The safety layer is injected (any callable ``safety_layer(state, u_rl) -> u_safe``,
differentiable in ``u_rl``); networks see ``obs``, the safety layer sees ``state``.

Design notes (what each mode trains on what, the compensator, the layer's contract):
docs/DESIGN.md#sacs-training-modes
"""
from __future__ import annotations

import copy
from dataclasses import dataclass
from typing import Any, Callable, Iterable, Literal, NamedTuple

import numpy as np
import torch
from torch import nn

from rcbf_ros.learning.buffers import BatchDisturbance, TransitionBatch
from rcbf_ros.learning.compiled_update import FunctionalUpdate
from rcbf_ros.learning.networks import (
    Compensator,
    NumpyMLP,
    QNetwork,
    SquashedGaussianActor,
    twin_minimum,
)

SafetyLayer = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]
Mode = Literal['unconstrained', 'baseline', 'baseline_compensator', 'diff', 'modular']
MODES: tuple[str, ...] = ('unconstrained', 'baseline', 'baseline_compensator', 'diff',
                          'modular')
DEFAULT_INITIAL_ALPHA = 0.2
"""alpha_e at the start of training when neither the run nor its config file sets one."""


@dataclass(frozen=True)
class SACConfig:
    """Hyperparameters of ``SAC``."""

    mode: Mode = 'baseline'
    """Training mode, one of ``MODES`` (see the module docstring)."""
    gamma: float = 0.99
    """Discount factor."""
    tau: float = 0.005
    """Polyak coefficient of the target critics: theta_bar <- tau theta + (1 - tau) theta_bar."""
    actor_lr: float = 3e-4
    """Adam learning rate of the actor."""
    critic_lr: float = 3e-4
    """Adam learning rate of the twin critics."""
    alpha_lr: float = 3e-4
    """Adam learning rate of log(alpha) (automatic entropy tuning)."""
    initial_alpha: float | None = None
    """Initial entropy temperature alpha_e; None: the system's config file's learner
    ``initial_alpha`` when trained through ``rcbf_ros.training`` (see config/*.yaml: it is tied
    to the reward's scale), else ``DEFAULT_INITIAL_ALPHA``."""
    autotune_alpha: bool = True
    """Tune alpha to keep the policy entropy near ``target_entropy``."""
    target_entropy: float | None = None
    """Entropy target of the tuning; None means -n_u."""
    hidden_sizes: tuple[int, ...] = (256, 256)
    """Hidden widths of actor, critics and compensator."""
    target_update_interval: int = 1
    """Update the target critics every this many ``update`` calls."""
    compensator_lr: float = 3e-4
    """Adam learning rate of the compensator (``baseline_compensator`` only)."""
    compile_update: bool = False
    """Run the networks' part of each update through ``torch.compile``
    (:mod:`rcbf_ros.learning.compiled_update`): the same update, up to float32 round-off, after
    a one-off compile of tens of seconds at the first update (twice with
    ``target_update_interval`` > 1: with and without the Polyak step). Without a safety layer in
    the losses the whole update is one graph; where the losses pass the action through the
    layer (``diff``; ``modular`` with an envelope layer) the layer runs eagerly between
    compiled graphs, the gradients flowing through it as in the eager update (the layer's
    solve is not compiled, so these modes gain less). What it gains depends on the CPU:
    benchmarks/bench_training.py times both side by side. Equal seeds still give equal
    runs."""

    def __post_init__(self) -> None:
        if self.mode not in MODES:
            raise ValueError(f'mode must be one of {MODES}, got {self.mode!r}')
        if not 0.0 <= self.gamma <= 1.0:
            raise ValueError(f'gamma must be in [0, 1], got {self.gamma}')
        if not 0.0 < self.tau <= 1.0:
            raise ValueError(f'tau must be in (0, 1], got {self.tau}')
        if self.initial_alpha is not None and not self.initial_alpha > 0:
            raise ValueError(f'initial_alpha must be > 0, got {self.initial_alpha}')
        if self.target_update_interval < 1:
            raise ValueError(
                f'target_update_interval must be >= 1, got {self.target_update_interval}')
        if not self.hidden_sizes or min(self.hidden_sizes) < 1:
            raise ValueError(f'hidden_sizes must be positive widths, got {self.hidden_sizes}')


class ActionProposal(NamedTuple):
    """What ``act_detailed`` returns (numpy, shape (n_u,) or (B, n_u))."""

    u_proposed: np.ndarray
    """Action to send to the safety filter (u^RL, or u^RL + c(obs) clipped with a
    compensator)."""
    u_rl: np.ndarray
    """The policy's own sample u^RL (store this as ``u_rl``)."""


def polyak_update(params: Iterable[nn.Parameter], target_params: Iterable[nn.Parameter],
                  tau: float) -> None:
    """In place: target <- tau * param + (1 - tau) * target, pairwise, as one multi-tensor
    ``target + tau (param - target)`` (one pass over each tensor)."""
    params, target_params = list(params), list(target_params)
    if len(params) != len(target_params):
        raise ValueError(f'polyak_update: {len(params)} parameters, {len(target_params)} '
                         'targets')
    with torch.no_grad():
        torch._foreach_lerp_(target_params, params, tau)


class AdamStep:
    """``optimizer.step()`` of a ``torch.optim.Adam`` with one group and no weight decay,
    amsgrad, maximize or differentiable mode, with less Python per call.

    It runs the kernel ``torch.optim.Adam(fused=True)`` runs, ``torch._fused_adam_``, after the
    same increment of the step counts, on the optimizer's own state tensors (``step``,
    ``exp_avg``, ``exp_avg_sq``; created as Adam creates them at its first step), with the
    group's current ``lr``, ``betas`` and ``eps``: for a fused optimizer the same update bit
    for bit, without ``Optimizer.step``'s per-call grouping, hooks and state lookups. The
    parameters' step counts (equal: they step together) become views of one tensor, so that
    one increment counts them all. Where a parameter has no gradient it leaves the step to the
    optimizer (which skips it). Build it again once the optimizer's state tensors are replaced
    (``load_state_dict``).
    """

    def __init__(self, optimizer: torch.optim.Optimizer) -> None:
        if len(optimizer.param_groups) != 1:
            raise ValueError('AdamStep: expected one parameter group')
        group = optimizer.param_groups[0]
        if (group['weight_decay'] or group['amsgrad'] or group['maximize']
                or group['differentiable'] or group.get('decoupled_weight_decay')
                or isinstance(group['lr'], torch.Tensor)):
            raise ValueError('AdamStep: supports plain Adam (no weight decay, amsgrad, '
                             'maximize, differentiable mode or tensor lr)')
        self.optimizer, self.group = optimizer, group
        self.params: list[torch.Tensor] = list(group['params'])
        for param in self.params:
            state = optimizer.state[param]
            if not state:
                state['step'] = torch.zeros((), dtype=torch.float32, device=param.device)
                state['exp_avg'] = torch.zeros_like(param, memory_format=torch.preserve_format)
                state['exp_avg_sq'] = torch.zeros_like(param,
                                                       memory_format=torch.preserve_format)
        states = [optimizer.state[param] for param in self.params]
        self.counts = torch.stack([state['step'] for state in states])
        for index, state in enumerate(states):
            state['step'] = self.counts[index]
        self.steps = [state['step'] for state in states]
        self.first = [state['exp_avg'] for state in states]
        self.second = [state['exp_avg_sq'] for state in states]

    def zero_grad(self) -> None:
        """``optimizer.zero_grad()`` (gradients set to None)."""
        for param in self.params:
            param.grad = None

    def __call__(self) -> None:
        """One Adam step of every parameter from its ``.grad``."""
        grads = [param.grad for param in self.params]
        if any(grad is None for grad in grads):
            self.optimizer.step()
            return
        group = self.group
        beta1, beta2 = group['betas']
        with torch.no_grad():
            self.counts.add_(1.0)
            torch._fused_adam_(self.params, grads, self.first, self.second, [], self.steps,
                               lr=float(group['lr']), beta1=float(beta1), beta2=float(beta2),
                               weight_decay=0.0, eps=float(group['eps']), amsgrad=False,
                               maximize=False)


class SAC:
    """SAC agent with SAC-RCBF's training modes.

    Args:
        obs_dim: observation size (the networks' input).
        n_u: action size.
        u_low, u_high: (n_u,) action box of the policy.
        config: see ``SACConfig``.
        safety_layer: differentiable ``(state, u_rl) -> u_safe``; required in ``diff`` mode;
            in ``modular`` mode optional, the envelope's layer (see the module docstring).
        seed: seeds network initialisation (without touching the global RNG) and the policy
            noise generator, so equal seeds give bit-identical training.
        dtype: parameter type (float32; float64 for gradient checks).
    """

    def __init__(self, obs_dim: int, n_u: int, u_low: np.ndarray | torch.Tensor,
                 u_high: np.ndarray | torch.Tensor, config: SACConfig | None = None, *,
                 safety_layer: SafetyLayer | None = None, seed: int = 0,
                 dtype: torch.dtype = torch.float32) -> None:
        self.config = config if config is not None else SACConfig()
        cfg = self.config
        if obs_dim < 1:
            raise ValueError(f'obs_dim must be >= 1, got {obs_dim}')
        if n_u < 1:
            raise ValueError(f'n_u must be >= 1, got {n_u}')
        low = torch.as_tensor(u_low, dtype=dtype).reshape(-1)
        high = torch.as_tensor(u_high, dtype=dtype).reshape(-1)
        if low.shape != (n_u,):
            raise ValueError(f'u_low must have shape ({n_u},), got {tuple(low.shape)}')
        if high.shape != (n_u,):
            raise ValueError(f'u_high must have shape ({n_u},), got {tuple(high.shape)}')
        if not (high > low).all():
            raise ValueError('u_high must be > u_low elementwise')
        if cfg.mode == 'diff' and safety_layer is None:
            raise ValueError("safety_layer is required in mode 'diff'")
        self.obs_dim, self.n_u, self.dtype = obs_dim, n_u, dtype
        self.u_low, self.u_high = low, high
        self.safety_layer = safety_layer
        hidden = cfg.hidden_sizes
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(seed)
            self.actor = SquashedGaussianActor(obs_dim, low, high, hidden).to(dtype)
            self.q1 = QNetwork(obs_dim, n_u, hidden).to(dtype)
            self.q2 = QNetwork(obs_dim, n_u, hidden).to(dtype)
            self.compensator = (Compensator(obs_dim, n_u, hidden).to(dtype)
                                if cfg.mode == 'baseline_compensator' else None)
        self.q1_target = copy.deepcopy(self.q1).requires_grad_(False)
        self.q2_target = copy.deepcopy(self.q2).requires_grad_(False)
        # Both targets' parameters in the critic optimizer's order (q1's, then q2's): one
        # Polyak step moves both.
        self._target_params = [*self.q1_target.parameters(), *self.q2_target.parameters()]
        alpha0 = DEFAULT_INITIAL_ALPHA if cfg.initial_alpha is None else cfg.initial_alpha
        self.log_alpha = torch.tensor(float(np.log(alpha0)), dtype=dtype,
                                      requires_grad=True)
        self.target_entropy = (cfg.target_entropy if cfg.target_entropy is not None
                               else -float(n_u))
        # Fused Adam: one kernel per step for all of a network's tensors (the same update rule;
        # its round-off differs from the per-tensor loop's).
        self.actor_optimizer = torch.optim.Adam(self.actor.parameters(), lr=cfg.actor_lr,
                                                fused=True)
        self.critic_optimizer = torch.optim.Adam(
            [*self.q1.parameters(), *self.q2.parameters()], lr=cfg.critic_lr, fused=True)
        self.alpha_optimizer = torch.optim.Adam([self.log_alpha], lr=cfg.alpha_lr, fused=True)
        # Built at the first update when ``compile_update`` (it binds the optimizers' state).
        self._functional_update: FunctionalUpdate | None = None
        self.compensator_optimizer = (
            torch.optim.Adam(self.compensator.parameters(), lr=cfg.compensator_lr, fused=True)
            if self.compensator is not None else None)
        # The optimizers' steps (AdamStep), bound at the first update that steps each.
        self._steps: dict[str, AdamStep] = {}
        self.generator = torch.Generator().manual_seed(seed + 1)
        self.num_updates = 0
        # Batch-1 acting in numpy on live views of the weights (NumpyMLP's docstring says why).
        self._numpy_actor = self.actor.numpy_sampler()
        # The one-observation noise draw fills this tensor in place (``normal_`` is what
        # ``torch.randn`` runs on a new tensor: the same numbers from the generator) and the
        # numpy actor reads it through a view.
        self._noise = torch.empty(n_u, dtype=dtype)
        self._noise_view = self._noise.numpy()
        self._numpy_compensator = (NumpyMLP(self.compensator.net)
                                   if self.compensator is not None else None)

    # ----------------------------------------------------------------- acting
    @property
    def alpha(self) -> torch.Tensor:
        """Entropy temperature alpha_e = exp(log_alpha) (detached)."""
        return self.log_alpha.detach().exp()

    def policy_action(self, obs: torch.Tensor, deterministic: bool = False) -> torch.Tensor:
        """u^RL for a batch, without gradients: obs (B, obs_dim) -> (B, n_u)."""
        with torch.no_grad():
            sample = self.actor(obs.to(self.dtype), generator=self.generator)
        return sample.mean_action if deterministic else sample.action

    def act_detailed(self, obs: np.ndarray | torch.Tensor,
                     deterministic: bool = False) -> ActionProposal:
        """Proposal for the safety filter and the policy's own sample, as numpy.

        Args:
            obs: (obs_dim,) or (B, obs_dim).
        """
        if not isinstance(obs, torch.Tensor) and np.ndim(obs) == 1 and len(obs) == self.obs_dim:
            return self._act_one(np.asarray(obs), deterministic)
        obs_t = torch.as_tensor(np.asarray(obs) if not isinstance(obs, torch.Tensor) else obs,
                                dtype=self.dtype)
        single = obs_t.ndim == 1
        if single:
            obs_t = obs_t.unsqueeze(0)
        if obs_t.ndim != 2 or obs_t.shape[1] != self.obs_dim:
            raise ValueError(f'obs must have shape ({self.obs_dim},) or (B, {self.obs_dim}), '
                             f'got {tuple(obs_t.shape)}')
        u_rl = self.policy_action(obs_t, deterministic)
        u_proposed = u_rl
        if self.compensator is not None:
            with torch.no_grad():
                u_proposed = torch.clamp(u_rl + self.compensator(obs_t), self.u_low,
                                         self.u_high)
        if single:
            u_rl, u_proposed = u_rl[0], u_proposed[0]
        return ActionProposal(u_proposed.numpy().copy(), u_rl.numpy().copy())

    def _act_one(self, obs: np.ndarray, deterministic: bool) -> ActionProposal:
        """:meth:`act_detailed` for one numpy observation, without torch ops but the noise draw
        (same generator, same draw as the batched path, so the two agree up to rounding)."""
        if deterministic:
            u_rl = self._numpy_actor(obs, None)[0]
        else:
            self._noise.normal_(generator=self.generator)
            u_rl = self._numpy_actor(obs, self._noise_view)[0]
        u_proposed = u_rl
        if self._numpy_compensator is not None:
            u_proposed = np.clip(u_rl + self._numpy_compensator(obs.astype(u_rl.dtype)),
                                 self._numpy_actor.low, self._numpy_actor.high)
        return ActionProposal(u_proposed, u_rl.copy())

    def act(self, obs: np.ndarray | torch.Tensor, deterministic: bool = False) -> np.ndarray:
        """Action to hand to the safety filter: u^RL (plus the compensator, if any)."""
        return self.act_detailed(obs, deterministic).u_proposed

    # ----------------------------------------------------------------- losses
    @property
    def through_layer(self) -> bool:
        """Whether the losses see the action through the safety layer (diff; modular with an
        envelope layer)."""
        return self.config.mode in ('diff', 'modular') and self.safety_layer is not None

    def _safe_action(self, state: torch.Tensor, u_rl: torch.Tensor,
                     disturbance: torch.Tensor | None) -> torch.Tensor:
        """u^RL + u^S(x, u^RL) = safety_layer(x, u^RL), cast to the networks' dtype.

        ``disturbance``: (B, 2, n_x) mean and std at x, or None (the layer asks its model)."""
        assert self.safety_layer is not None
        if disturbance is None:
            return self.safety_layer(state, u_rl).to(self.dtype)
        estimate = (disturbance[:, 0], disturbance[:, 1])
        return self.safety_layer(state, u_rl, estimate).to(self.dtype)

    def critic_action(self, batch: TransitionBatch) -> torch.Tensor:
        """The action the critic is trained at: u^RL_t (eq. q_update) or u*_t (eqs.
        q_update_diff, q_update_mod)."""
        return self._trained_action(batch.u_rl, batch.u_safe)

    def _trained_action(self, u_rl: torch.Tensor, u_safe: torch.Tensor) -> torch.Tensor:
        return u_safe if self.config.mode in ('diff', 'modular') else u_rl

    def critic_value(self, obs: torch.Tensor, u_rl: torch.Tensor,
                     u_safe: torch.Tensor) -> torch.Tensor:
        """min(Q1, Q2) at the action the critics are trained at (:meth:`critic_action`), no
        gradient: the soft value the learner believes in, to hold against returns."""
        action = self._trained_action(u_rl, u_safe).to(self.dtype)
        with torch.no_grad():
            obs = obs.to(self.dtype)
            return torch.minimum(self.q1(obs, action), self.q2(obs, action))

    def critic_target(self, batch: TransitionBatch, noise: torch.Tensor | None = None,
                      disturbance: BatchDisturbance | None = None) -> torch.Tensor:
        """Soft Bellman target y = r + gamma (1 - done) V_bar(x_{t+1}): (B,).

        Args:
            noise: optional (B, n_u) standard normal draw for a' ~ pi(.|x_{t+1}).
            disturbance: the estimate at the batch's states for the safety layer (None: the
                layer predicts it).
        """
        with torch.no_grad():
            next_sample = self.actor(batch.next_obs, noise=noise, generator=self.generator)
            next_action = next_sample.action
            if self.through_layer:
                # eq. q_update_diff: V_bar(x') = Q_bar(x', a' + u^S(x', a')) - alpha log pi
                # (modular: the envelope's correction u^E only).
                next_action = self._safe_action(
                    batch.next_state, next_action,
                    None if disturbance is None else disturbance.next_state)
            return self._target_at(batch, next_action, next_sample.log_prob)

    def _target_at(self, batch: TransitionBatch, next_action: torch.Tensor,
                   next_log_prob: torch.Tensor) -> torch.Tensor:
        """y = r + gamma (1 - done) (min_i Q_bar_i(x_{t+1}, next_action) - alpha log pi(a'|x'))
        for the action the target critics see at x_{t+1} (no gradient)."""
        with torch.no_grad():
            # eq. q_update (plain) and eq. q_update_mod (modular): u^S_{t+1} = 0, so
            # V_bar(x') = Q_bar(x', a') - alpha log pi(a'|x').
            next_q = torch.minimum(self.q1_target(batch.next_obs, next_action),
                                   self.q2_target(batch.next_obs, next_action))
            next_value = next_q - self.alpha * next_log_prob
            return batch.reward + self.config.gamma * (1.0 - batch.done) * next_value

    def critic_loss(self, batch: TransitionBatch, noise: torch.Tensor | None = None,
                    disturbance: BatchDisturbance | None = None
                    ) -> tuple[torch.Tensor, dict[str, float]]:
        """J_Q = E[1/2 (Q_i(x_t, action_t) - y)^2], summed over the twin critics."""
        loss, q1, q2, target = self._critic_loss(batch, noise, disturbance)
        q1_mean, q2_mean, target_mean = torch.stack([q1.detach().mean(), q2.detach().mean(),
                                                     target.mean()]).tolist()
        return loss, {'q1_mean': q1_mean, 'q2_mean': q2_mean, 'target_mean': target_mean}

    def _critic_loss(self, batch: TransitionBatch, noise: torch.Tensor | None,
                     disturbance: BatchDisturbance | None,
                     target: torch.Tensor | None = None
                     ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """:meth:`critic_loss` and the Q1, Q2 and target y (each (B,)) behind it (``target``:
        y computed already)."""
        if target is None:
            target = self.critic_target(batch, noise, disturbance)
        action = self.critic_action(batch)
        q1 = self.q1(batch.obs, action)
        q2 = self.q2(batch.obs, action)
        loss = 0.5 * ((q1 - target) ** 2).mean() + 0.5 * ((q2 - target) ** 2).mean()
        return loss, q1, q2, target

    def actor_loss(self, batch: TransitionBatch, noise: torch.Tensor | None = None,
                   disturbance: BatchDisturbance | None = None, critics_fixed: bool = False
                   ) -> tuple[torch.Tensor, torch.Tensor]:
        """J_pi = E[alpha log pi(a|x) - min_i Q_i(x, action(a))], and log pi(a|x): (B,).

        Args:
            noise: optional (B, n_u) standard normal draw for a ~ pi(.|x_t).
            disturbance: as in :meth:`critic_target`.
            critics_fixed: as in :meth:`_actor_loss_at`.
        """
        sample = self.actor(batch.obs, noise=noise, generator=self.generator)
        action = sample.action
        if self.through_layer:
            # eq. pi_update_diff: Q(x, a + u^S(x, a)); gradients flow through the layer
            # (modular: the envelope's layer).
            action = self._safe_action(batch.state, action,
                                       None if disturbance is None else disturbance.state)
        return (self._actor_loss_at(batch.obs, action, sample.log_prob, critics_fixed),
                sample.log_prob)

    def _actor_loss_at(self, obs: torch.Tensor, action: torch.Tensor, log_prob: torch.Tensor,
                       critics_fixed: bool = False) -> torch.Tensor:
        """E[alpha log pi(a|x) - min_i Q_i(x, action)] for the action the critics see.

        ``critics_fixed``: the loss's gradient is wanted in the action (and log pi) only, as in
        the actor's step (:func:`twin_minimum`); else autograd through both critics, their
        weights included."""
        # eq. pi_update (unconstrained, baselines, modular): Q(x, a).
        if critics_fixed:
            q = twin_minimum(self.q1, self.q2, obs, action)
        else:
            q = torch.minimum(self.q1(obs, action), self.q2(obs, action))
        return (self.alpha * log_prob - q).mean()

    def _through_layer_once(self, batch: TransitionBatch,
                            disturbance: BatchDisturbance | None
                            ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """Both of an update's policy samples and their safe actions from one layer call.

        a' ~ pi(.|x_{t+1}) (no gradient) and a ~ pi(.|x_t) are drawn in the order
        :meth:`critic_target` and :meth:`actor_loss` draw them (the same noise), then the layer
        runs once on (x_t, a) and (x_{t+1}, a') side by side: each sample's QP has its own
        solution, so this is the two calls of those methods in one solve of 2B problems (the
        layer must answer each row on its own: module docstring), and the layer's cost is
        mostly per call. The actor's weights change only at its own Adam step, after the critics',
        so sampling a before the critics' step draws what :meth:`actor_loss` would draw after
        it. Returns the safe action at x_t (differentiable in the actor's weights), log pi(a|x_t),
        the safe action at x_{t+1} (detached) and log pi(a'|x_{t+1})."""
        with torch.no_grad():
            following = self.actor(batch.next_obs, generator=self.generator)
        sample = self.actor(batch.obs, generator=self.generator)
        size = sample.action.shape[0]
        both = self._safe_action(
            torch.cat([batch.state, batch.next_state]),
            torch.cat([sample.action, following.action]),
            None if disturbance is None else torch.cat([disturbance.state,
                                                        disturbance.next_state]))
        return both[:size], sample.log_prob, both[size:].detach(), following.log_prob

    def compensator_loss(self, batch: TransitionBatch) -> torch.Tensor:
        """E[1/2 |c(obs_t) - u^S_t|^2] (Cheng et al. 2019: learn the filter's correction)."""
        assert self.compensator is not None
        return 0.5 * ((self.compensator(batch.obs) - batch.u_s) ** 2).sum(-1).mean()

    # ----------------------------------------------------------------- update
    def update(self, batch: TransitionBatch,
               disturbance: BatchDisturbance | None = None) -> dict[str, float]:
        """One gradient step of critics, actor, alpha (and compensator); returns metrics.

        ``disturbance``: the estimate at the batch's states for the safety layer, when the
        caller has it (None: the layer predicts it)."""
        batch = TransitionBatch(*(t.to(self.dtype) for t in batch))
        cfg = self.config
        if cfg.compile_update:
            return self._update_compiled(batch, disturbance)
        critic_step = self._step('critic')
        target = safe = log_prob = None
        if self.through_layer:
            safe, log_prob, next_safe, next_log_prob = self._through_layer_once(batch,
                                                                                disturbance)
            target = self._target_at(batch, next_safe, next_log_prob)
        critic_loss, q1, q2, target = self._critic_loss(batch, None, disturbance, target)
        critic_step.zero_grad()
        critic_loss.backward()
        critic_step()

        # The actor's loss differentiates through the critics only to reach the action
        # (twin_minimum: no weight gradients, each sample through the critic of its minimum).
        actor_step = self._step('actor')
        if safe is None:
            actor_loss, log_prob = self.actor_loss(batch, critics_fixed=True)
        else:
            actor_loss = self._actor_loss_at(batch.obs, safe, log_prob, critics_fixed=True)
        actor_step.zero_grad()
        actor_loss.backward()
        actor_step()

        log_prob = log_prob.detach()
        alpha_loss = torch.zeros((), dtype=self.dtype)
        if cfg.autotune_alpha:
            # Haarnoja et al. 2018b: J(alpha) = E[-log_alpha (log pi + target_entropy)], whose
            # gradient in log_alpha is -E[log pi + target_entropy] (no graph needed for it).
            gradient = -(log_prob + self.target_entropy).mean()
            alpha_loss = self.log_alpha.detach() * gradient
            self.log_alpha.grad = gradient
            self._step('alpha')()

        self.num_updates += 1
        if self.num_updates % cfg.target_update_interval == 0:
            polyak_update(critic_step.params, self._target_params, cfg.tau)

        # The metrics as one tensor, converted to Python floats at once.
        values = torch.stack([
            q1.detach().mean(), q2.detach().mean(), target.mean(), critic_loss.detach(),
            actor_loss.detach(), self.alpha, alpha_loss, -log_prob.mean()]).tolist()
        metrics = dict(zip(('q1_mean', 'q2_mean', 'target_mean', 'critic_loss', 'actor_loss',
                            'alpha', 'alpha_loss', 'entropy'), values))
        self._update_compensator(batch, metrics)
        return metrics

    def _step(self, name: str) -> AdamStep:
        """The :class:`AdamStep` of ``{name}_optimizer`` (bound at its first use)."""
        step = self._steps.get(name)
        if step is None:
            step = self._steps[name] = AdamStep(getattr(self, f'{name}_optimizer'))
        return step

    def _update_compensator(self, batch: TransitionBatch, metrics: dict[str, float]) -> None:
        if self.compensator is not None:
            compensator_loss = self.compensator_loss(batch)
            step = self._step('compensator')
            step.zero_grad()
            compensator_loss.backward()
            step()
            metrics['compensator_loss'] = float(compensator_loss.detach())

    def _update_compiled(self, batch: TransitionBatch,
                         disturbance: BatchDisturbance | None) -> dict[str, float]:
        """:meth:`update` through the compiled :class:`FunctionalUpdate` (with the safety layer
        between its graphs where the losses pass it): the same noise draws from ``generator``
        in the same order, the same disturbance estimates for the layer, the same metrics."""
        if self._functional_update is None:
            self._functional_update = FunctionalUpdate(
                self, compile_=True, layer=self._safe_action if self.through_layer else None)
        shape = (batch.obs.shape[0], self.n_u)
        next_noise = torch.randn(shape, generator=self.generator, dtype=self.dtype)
        noise = torch.randn(shape, generator=self.generator, dtype=self.dtype)
        self.num_updates += 1
        stats = self._functional_update.step(
            batch, self.critic_action(batch), next_noise, noise,
            self.num_updates % self.config.target_update_interval == 0,
            disturbance if self.through_layer else None)
        values = torch.stack([stats.q1_mean, stats.q2_mean, stats.target_mean,
                              stats.critic_loss, stats.actor_loss, self.alpha,
                              stats.alpha_loss, stats.entropy]).tolist()
        metrics = dict(zip(('q1_mean', 'q2_mean', 'target_mean', 'critic_loss', 'actor_loss',
                            'alpha', 'alpha_loss', 'entropy'), values))
        self._update_compensator(batch, metrics)
        return metrics

    # ------------------------------------------------------------- checkpoint
    def _modules(self) -> dict[str, Any]:
        modules: dict[str, Any] = {
            'actor': self.actor, 'q1': self.q1, 'q2': self.q2, 'q1_target': self.q1_target,
            'q2_target': self.q2_target, 'actor_optimizer': self.actor_optimizer,
            'critic_optimizer': self.critic_optimizer, 'alpha_optimizer': self.alpha_optimizer}
        if self.compensator is not None:
            modules['compensator'] = self.compensator
            modules['compensator_optimizer'] = self.compensator_optimizer
        return modules

    def state_dict(self) -> dict[str, Any]:
        """A snapshot (deep copy) of networks, optimisers, log(alpha), generator state and
        update count."""
        state = {name: copy.deepcopy(module.state_dict())
                 for name, module in self._modules().items()}
        for name in self._steps:
            # AdamStep keeps an optimizer's step counts as views of one tensor; the checkpoint
            # holds each as its own tensor, as torch.optim.Adam does.
            for entry in state[f'{name}_optimizer']['state'].values():
                entry['step'] = entry['step'].clone()
        state.update({'log_alpha': self.log_alpha.detach().clone(),
                      'generator': self.generator.get_state(),
                      'num_updates': self.num_updates, 'mode': self.config.mode})
        return state

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore a ``state_dict`` taken from an agent with the same sizes and mode."""
        if state['mode'] != self.config.mode:
            raise ValueError(f"mode mismatch: state_dict has {state['mode']!r}, agent has "
                             f'{self.config.mode!r}')
        for name, module in self._modules().items():
            module.load_state_dict(state[name])
        with torch.no_grad():
            self.log_alpha.copy_(state['log_alpha'])
        self.generator.set_state(state['generator'])
        self.num_updates = state['num_updates']
        # The optimizers' state tensors were replaced: the steps and the compiled update bind
        # the new ones.
        self._steps.clear()
        self._functional_update = None
