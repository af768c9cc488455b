"""SAC's network update as functions of tensors for torch.compile (``SACConfig.compile_update``).

``SAC.update`` steps its networks through ``loss.backward()`` and ``torch.optim.Adam``, and
torch.compile can only compile the pieces between those calls, which gains nothing
measurable. ``FunctionalUpdate`` states the same update as functions of the agent's tensors,
each compiled as one graph (``fullgraph=True``), with the differentiable safety layer run
eagerly between them where the losses use it. It works in place on the agent's own parameters
and Adam state, agrees with the eager update up to float32 round-off, and raises a
``RuntimeError`` naming ``compile_update`` rather than compiling again.

Design notes (the graphs, the split at the layer): docs/DESIGN.md#sacs-compiled-update
"""
from __future__ import annotations

from typing import Any, Callable, NamedTuple

import torch
from torch import nn
from torch._dynamo.utils import counters
from torch.func import functional_call, grad_and_value

from rcbf_ros.learning.buffers import BatchDisturbance, TransitionBatch

Tensors = dict[str, torch.Tensor]
SafeAction = Callable[[torch.Tensor, torch.Tensor, torch.Tensor | None], torch.Tensor]
"""(state (B, n_x), u_rl (B, n_u), disturbance (B, 2, n_x) or None) -> u_safe (B, n_u) in the
agent's dtype, differentiable in u_rl (``SAC._safe_action``)."""


class UpdateStats(NamedTuple):
    """What one functional update reports (0-d tensors), as ``SAC.update``'s metrics."""

    critic_loss: torch.Tensor
    actor_loss: torch.Tensor
    alpha_loss: torch.Tensor
    q1_mean: torch.Tensor
    q2_mean: torch.Tensor
    target_mean: torch.Tensor
    entropy: torch.Tensor


class _Adam(NamedTuple):
    """One optimizer's live tensors and constants."""

    params: Tensors
    first: Tensors
    second: Tensors
    steps: list[torch.Tensor]
    lr: float
    betas: tuple[float, float]
    eps: float


def _adam_state(optimizer: torch.optim.Optimizer, named: dict[str, nn.Parameter]) -> _Adam:
    """The optimizer's state tensors of ``named`` (created as Adam creates them on its first
    step, when it has not stepped yet). Only plain Adam: no weight decay, amsgrad, maximize."""
    group = optimizer.param_groups[0]
    if (len(optimizer.param_groups) != 1 or group['weight_decay'] or group['amsgrad']
            or group['maximize']):
        raise ValueError('compile_update: supports plain Adam (one group, no weight decay, '
                         'amsgrad or maximize)')
    first, second, steps = {}, {}, []
    for name, param in named.items():
        state = optimizer.state[param]
        if not state:
            state['step'] = torch.tensor(0.0, dtype=torch.float32)
            state['exp_avg'] = torch.zeros_like(param, memory_format=torch.preserve_format)
            state['exp_avg_sq'] = torch.zeros_like(param, memory_format=torch.preserve_format)
        first[name], second[name] = state['exp_avg'], state['exp_avg_sq']
        steps.append(state['step'])
    return _Adam(dict(named), first, second, steps, float(group['lr']),
                 tuple(group['betas']), float(group['eps']))


def _adam_step(adam: _Adam, grads: Tensors) -> None:
    """torch.optim.Adam's rule, in place on the live tensors. The bias corrections are
    computed in the parameters' dtype, as the fused Adam does (the step count is float32, in
    whose precision 1 - beta2 ** step keeps only about five digits at the first steps)."""
    torch._foreach_add_(adam.steps, 1.0)
    beta1, beta2 = adam.betas
    step = adam.steps[0].to(next(iter(adam.params.values())).dtype)
    step_size = adam.lr / (1.0 - beta1 ** step)
    root_correction = (1.0 - beta2 ** step).sqrt()
    for name, param in adam.params.items():
        grad = grads[name]
        first, second = adam.first[name], adam.second[name]
        first.lerp_(grad, 1.0 - beta1)
        second.mul_(beta2).addcmul_(grad, grad, value=1.0 - beta2)
        param.sub_(step_size * first / (second.sqrt() / root_correction + adam.eps))


def _first_line(exc: BaseException) -> str:
    lines = str(exc).strip().splitlines()
    return f'{type(exc).__name__}: {lines[0] if lines else ""}'


class _Graph:
    """``function`` through ``torch.compile(fullgraph=True, dynamic=False)`` (or as written,
    when not compiling) that compiles once per ``variant`` and raises where it would again.

    torch._dynamo counts every graph it compiles (``counters['stats']['unique_graphs']``); a
    call of a variant seen before that moved the count compiled again, because a guard failed
    (an input of another shape, dtype or layout than at the first call): that update would run
    slower than it should, at the cost of a compile, so it stops with one line instead."""

    def __init__(self, function: Callable[..., Any], name: str, *, compile_: bool,
                 mode: str | None) -> None:
        self.name, self.compiled = name, compile_
        self._run = (torch.compile(function, fullgraph=True, dynamic=False, mode=mode)
                     if compile_ else function)
        self._seen: set[Any] = set()

    def __call__(self, variant: Any, *args: Any) -> Any:
        if not self.compiled:
            return self._run(*args)
        stats = counters['stats']
        before = stats['unique_graphs']
        try:
            out = self._run(*args)
        except (torch._dynamo.exc.TorchDynamoException,
                torch._dynamo.exc.FailOnRecompileLimitHit) as exc:
            raise RuntimeError(f'compile_update: {self.name} does not compile '
                               f'({_first_line(exc)}); set it false') from exc
        if variant in self._seen and stats['unique_graphs'] != before:
            raise RuntimeError(f'compile_update: {self.name} compiled again at a later '
                               'update (an input changed shape, dtype or layout; '
                               'TORCH_LOGS=recompiles says which)')
        self._seen.add(variant)
        return out


class FunctionalUpdate:
    """One SAC update of ``sac`` (a :class:`rcbf_ros.learning.sac.SAC`) as ``step(batch,
    action, next_noise, noise, polyak, disturbance)``, on its live tensors; pass
    ``compile_=True`` to run its graphs through ``torch.compile(fullgraph=True)`` (the first
    call compiles: tens of seconds). ``layer``: the safe action the losses see (``SAC.
    _safe_action``), called eagerly between the graphs (see the module docstring); None: the
    losses see the policy's action, and the update is one graph."""

    def __init__(self, sac: Any, *, compile_: bool = False, mode: str | None = None,
                 layer: SafeAction | None = None) -> None:
        cfg = sac.config
        self.gamma, self.tau = cfg.gamma, cfg.tau
        self.autotune_alpha, self.target_entropy = cfg.autotune_alpha, sac.target_entropy
        self.actor, self.q1, self.q2 = sac.actor, sac.q1, sac.q2
        self.actor_adam = _adam_state(sac.actor_optimizer, dict(sac.actor.named_parameters()))
        critics = _adam_state(sac.critic_optimizer, {
            **{f'q1.{k}': v for k, v in sac.q1.named_parameters()},
            **{f'q2.{k}': v for k, v in sac.q2.named_parameters()}})
        self.critic_adam = critics
        self.alpha_adam = _adam_state(sac.alpha_optimizer, {'log_alpha': sac.log_alpha})
        self.q1_target = dict(sac.q1_target.named_parameters())
        self.q2_target = dict(sac.q2_target.named_parameters())
        self.layer = layer
        self._actor_names = list(self.actor_adam.params)
        self._actor_params = list(self.actor_adam.params.values())
        options = {'compile_': compile_, 'mode': mode}
        if layer is None:
            self._whole = _Graph(self._step, 'the update', **options)
        else:
            self._samples = _Graph(self._sample_step, 'the policy samples', **options)
            self._critics_step = _Graph(self._critic_step, 'the critic and actor losses',
                                        **options)
            self._actor_step = _Graph(self._actor_alpha_step, "the actor's and alpha's steps",
                                      **options)

    def step(self, batch: TransitionBatch, action: torch.Tensor, next_noise: torch.Tensor,
             noise: torch.Tensor, polyak: bool,
             disturbance: BatchDisturbance | None = None) -> UpdateStats:
        """One update. ``action``: the action the critics are trained at (B, n_u);
        ``next_noise``, ``noise``: the standard-normal draws of a' ~ pi(.|x_{t+1}) and
        a ~ pi(.|x_t); ``polyak``: step the target critics; ``disturbance``: the estimate at
        the batch's states for the layer (None: the layer predicts it)."""
        if self.layer is None:
            with torch.no_grad():
                return self._whole(polyak, batch, action, next_noise, noise, polyak)
        return self._step_through_layer(batch, action, next_noise, noise, polyak, disturbance)

    def _step_through_layer(self, batch: TransitionBatch, action: torch.Tensor,
                            next_noise: torch.Tensor, noise: torch.Tensor, polyak: bool,
                            disturbance: BatchDisturbance | None) -> UpdateStats:
        assert self.layer is not None
        with torch.enable_grad():
            sample_action, log_prob, next_action, next_log_prob = self._samples(
                None, batch.obs, batch.next_obs, noise, next_noise)
        # The layer once, at (x_t, a) and (x_{t+1}, a') side by side (module docstring, 2.).
        with torch.enable_grad():
            both = self._safe(
                torch.cat([batch.state, batch.next_state]),
                torch.cat([sample_action, next_action]),
                None if disturbance is None else torch.cat([disturbance.state,
                                                            disturbance.next_state]))
        size = sample_action.shape[0]
        safe, next_safe = both[:size], both[size:].detach()
        with torch.no_grad():
            (critic_value, actor_value, q1_mean, q2_mean, target_mean, grad_safe,
             grad_log_prob) = self._critics_step(
                polyak, batch, action, next_safe, next_log_prob, safe.detach(),
                log_prob.detach(), polyak)
        # d J_pi / d theta: the actor loss's gradients in the safe action and in log pi, back
        # through the layer's backward and the compiled backward of the sample at x_t.
        grads = torch.autograd.grad((safe, log_prob), self._actor_params,
                                    (grad_safe, grad_log_prob))
        with torch.no_grad():
            alpha_loss, entropy = self._actor_step(None, list(grads), log_prob.detach())
        return UpdateStats(critic_value, actor_value, alpha_loss, q1_mean, q2_mean,
                           target_mean, entropy)

    def _safe(self, state: torch.Tensor, u: torch.Tensor,
              disturbance: torch.Tensor | None) -> torch.Tensor:
        assert self.layer is not None
        safe = self.layer(state, u, disturbance)
        if safe.shape != u.shape or safe.dtype != u.dtype:
            raise RuntimeError(f'compile_update: the safety layer returned {safe.dtype} of '
                               f'shape {tuple(safe.shape)} for actions {u.dtype} of shape '
                               f'{tuple(u.shape)}')
        return safe.contiguous()

    # ------------------------------------------------------------------ the graphs' parts
    def _critics(self, params: Tensors) -> tuple[Tensors, Tensors]:
        q1 = {k[3:]: v for k, v in params.items() if k.startswith('q1.')}
        q2 = {k[3:]: v for k, v in params.items() if k.startswith('q2.')}
        return q1, q2

    def _target(self, batch: TransitionBatch, next_action: torch.Tensor,
                next_log_prob: torch.Tensor, alpha: torch.Tensor) -> torch.Tensor:
        """y = r + gamma (1 - done) (min_i Q_bar_i(x_{t+1}, a') - alpha log pi(a'|x_{t+1}))."""
        next_q = torch.minimum(
            functional_call(self.q1, self.q1_target, (batch.next_obs, next_action)),
            functional_call(self.q2, self.q2_target, (batch.next_obs, next_action)))
        return batch.reward + self.gamma * (1.0 - batch.done) * (next_q - alpha * next_log_prob)

    def _critic_update(self, batch: TransitionBatch, action: torch.Tensor,
                       target: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The critic loss at ``action``, its gradient and the critics' Adam step: the loss,
        Q1's and Q2's means."""
        def critic_loss(params: Tensors) -> tuple[torch.Tensor, tuple[torch.Tensor, ...]]:
            q1_params, q2_params = self._critics(params)
            q1 = functional_call(self.q1, q1_params, (batch.obs, action))
            q2 = functional_call(self.q2, q2_params, (batch.obs, action))
            loss = 0.5 * ((q1 - target) ** 2).mean() + 0.5 * ((q2 - target) ** 2).mean()
            return loss, (q1.mean(), q2.mean())

        critic_grads, (critic_value, (q1_mean, q2_mean)) = grad_and_value(
            critic_loss, has_aux=True)(self.critic_adam.params)
        _adam_step(self.critic_adam, critic_grads)
        return critic_value, q1_mean, q2_mean

    def _min_q(self, obs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        q1_params, q2_params = self._critics(self.critic_adam.params)
        return torch.minimum(functional_call(self.q1, q1_params, (obs, action)),
                             functional_call(self.q2, q2_params, (obs, action)))

    def _alpha_update(self, log_prob: torch.Tensor) -> torch.Tensor:
        """alpha's Adam step from log pi at x_t (when tuned); its loss."""
        log_alpha = self.alpha_adam.params['log_alpha']
        if not self.autotune_alpha:
            return torch.zeros((), dtype=log_alpha.dtype)
        # J(alpha) = E[-log_alpha (log pi + target_entropy)]; its gradient in log_alpha:
        alpha_loss = -(log_alpha * (log_prob + self.target_entropy)).mean()
        _adam_step(self.alpha_adam, {'log_alpha': -(log_prob + self.target_entropy).mean()})
        return alpha_loss

    def _polyak(self) -> None:
        q1_params, q2_params = self._critics(self.critic_adam.params)
        for targets, params in ((self.q1_target, q1_params), (self.q2_target, q2_params)):
            torch._foreach_lerp_(list(targets.values()), [params[k] for k in targets], self.tau)

    # ------------------------------------------------------------------ the graphs
    def _step(self, batch: TransitionBatch, action: torch.Tensor, next_noise: torch.Tensor,
              noise: torch.Tensor, polyak: bool) -> UpdateStats:
        """The whole update without a layer."""
        alpha = self.alpha_adam.params['log_alpha'].exp()
        following = functional_call(self.actor, self.actor_adam.params, (batch.next_obs,),
                                    {'noise': next_noise})
        target = self._target(batch, following.action, following.log_prob, alpha)
        critic_value, q1_mean, q2_mean = self._critic_update(batch, action, target)

        def actor_loss(params: Tensors) -> tuple[torch.Tensor, torch.Tensor]:
            sample = functional_call(self.actor, params, (batch.obs,), {'noise': noise})
            q = self._min_q(batch.obs, sample.action)
            return (alpha * sample.log_prob - q).mean(), sample.log_prob

        actor_grads, (actor_value, log_prob) = grad_and_value(actor_loss, has_aux=True)(
            self.actor_adam.params)
        _adam_step(self.actor_adam, actor_grads)
        alpha_loss = self._alpha_update(log_prob)
        if polyak:
            self._polyak()
        return UpdateStats(critic_value, actor_value, alpha_loss, q1_mean, q2_mean,
                           target.mean(), -log_prob.mean())

    def _sample_step(self, obs: torch.Tensor, next_obs: torch.Tensor, noise: torch.Tensor,
                     next_noise: torch.Tensor) -> tuple[torch.Tensor, ...]:
        """a ~ pi(.|x_t) and log pi(a|x_t), differentiable in the actor's weights; a' and
        log pi(a'|x_{t+1}) without gradient."""
        with torch.no_grad():
            following = functional_call(self.actor, self.actor_adam.params, (next_obs,),
                                        {'noise': next_noise})
        sample = functional_call(self.actor, self.actor_adam.params, (obs,), {'noise': noise})
        return sample.action, sample.log_prob, following.action, following.log_prob

    def _critic_step(self, batch: TransitionBatch, action: torch.Tensor,
                     next_safe: torch.Tensor, next_log_prob: torch.Tensor,
                     safe: torch.Tensor, log_prob: torch.Tensor, polyak: bool
                     ) -> tuple[torch.Tensor, ...]:
        """The critics' part at the layer's actions; the actor loss's value and its gradients
        in the safe action and in log pi (the updated critics' weights held fixed)."""
        alpha = self.alpha_adam.params['log_alpha'].exp()
        target = self._target(batch, next_safe, next_log_prob, alpha)
        critic_value, q1_mean, q2_mean = self._critic_update(batch, action, target)

        def actor_loss(safe_action: torch.Tensor, log_density: torch.Tensor) -> torch.Tensor:
            return (alpha * log_density - self._min_q(batch.obs, safe_action)).mean()

        (grad_safe, grad_log_prob), actor_value = grad_and_value(actor_loss, argnums=(0, 1))(
            safe, log_prob)
        if polyak:
            self._polyak()
        return (critic_value, actor_value, q1_mean, q2_mean, target.mean(), grad_safe,
                grad_log_prob)

    def _actor_alpha_step(self, grads: list[torch.Tensor], log_prob: torch.Tensor
                          ) -> tuple[torch.Tensor, torch.Tensor]:
        """The actor's Adam step from its gradients, alpha's step; alpha's loss, the
        entropy estimate."""
        _adam_step(self.actor_adam, dict(zip(self._actor_names, grads)))
        return self._alpha_update(log_prob), -log_prob.mean()
