"""SAC's network update as one function of tensors for torch.compile
(``SACConfig.compile_update``).

``SAC.update`` steps its networks through ``loss.backward()`` and ``torch.optim.Adam``;
torch.compile can only compile the pieces between those calls, which gains nothing measurable.
:class:`FunctionalUpdate` states the same update as one function of the agent's tensors, which
compiles as one graph (``fullgraph=True``): the critic target (next action, target critics), the
critic loss and its gradient (``torch.func.grad_and_value``), the critics' Adam step, the actor
loss with the critics' weights held fixed and its gradient, the actor's Adam step, alpha's loss
and Adam step, and the Polyak step of the target critics.

It works in place on the agent's own tensors: its parameters and the Adam state its optimizers
keep (``exp_avg``, ``exp_avg_sq``, ``step``, in torch.optim.Adam's layout), so checkpoints, the
numpy acting views and an eager ``SAC.update`` before or after all see one state. The noise of
the two policy samples is drawn by the caller from the agent's generator in the eager order, so
the compiled and the eager update take the same draws and agree up to float32 round-off (the
order of floating-point operations differs); equal seeds still give equal runs.

No safety layer in the losses: the differentiable QP is not one torch graph (``SAC`` refuses
``compile_update`` where the losses pass the action through a layer).
"""
from __future__ import annotations

from typing import Any, NamedTuple

import torch
from torch import nn
from torch.func import functional_call, grad_and_value

from rcbf_ros.learning.buffers import TransitionBatch

Tensors = dict[str, torch.Tensor]


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
    """torch.optim.Adam's rule, in place on the live tensors."""
    torch._foreach_add_(adam.steps, 1.0)
    beta1, beta2 = adam.betas
    step = adam.steps[0]
    step_size = adam.lr / (1.0 - beta1 ** step)
    root_correction = (1.0 - beta2 ** step).sqrt()
    for name, param in adam.params.items():
        grad = grads[name]
        first, second = adam.first[name], adam.second[name]
        first.lerp_(grad, 1.0 - beta1)
        second.mul_(beta2).addcmul_(grad, grad, value=1.0 - beta2)
        param.sub_(step_size * first / (second.sqrt() / root_correction + adam.eps))


class FunctionalUpdate:
    """One SAC update of ``sac`` (a :class:`rcbf_ros.learning.sac.SAC`) as ``step(batch,
    action, next_noise, noise, polyak)``, on its live tensors; pass ``compile_=True`` to run it
    through ``torch.compile(fullgraph=True)`` (the first call compiles: tens of seconds)."""

    def __init__(self, sac: Any, *, compile_: bool = False, mode: str | None = None) -> None:
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
        self._run = (torch.compile(self._step, fullgraph=True, dynamic=False, mode=mode)
                     if compile_ else self._step)

    def step(self, batch: TransitionBatch, action: torch.Tensor, next_noise: torch.Tensor,
             noise: torch.Tensor, polyak: bool) -> UpdateStats:
        """One update. ``action``: the action the critics are trained at (B, n_u);
        ``next_noise``, ``noise``: the standard-normal draws of a' ~ pi(.|x_{t+1}) and
        a ~ pi(.|x_t); ``polyak``: step the target critics."""
        with torch.no_grad():
            return self._run(batch, action, next_noise, noise, polyak)

    def _critics(self, params: Tensors) -> tuple[Tensors, Tensors]:
        q1 = {k[3:]: v for k, v in params.items() if k.startswith('q1.')}
        q2 = {k[3:]: v for k, v in params.items() if k.startswith('q2.')}
        return q1, q2

    def _step(self, batch: TransitionBatch, action: torch.Tensor, next_noise: torch.Tensor,
              noise: torch.Tensor, polyak: bool) -> UpdateStats:
        log_alpha = self.alpha_adam.params['log_alpha']
        alpha = log_alpha.exp()
        following = functional_call(self.actor, self.actor_adam.params, (batch.next_obs,),
                                    {'noise': next_noise})
        next_q = torch.minimum(
            functional_call(self.q1, self.q1_target, (batch.next_obs, following.action)),
            functional_call(self.q2, self.q2_target, (batch.next_obs, following.action)))
        target = batch.reward + self.gamma * (1.0 - batch.done) * (
            next_q - alpha * following.log_prob)

        def critic_loss(params: Tensors) -> tuple[torch.Tensor, tuple[torch.Tensor, ...]]:
            q1_params, q2_params = self._critics(params)
            q1 = functional_call(self.q1, q1_params, (batch.obs, action))
            q2 = functional_call(self.q2, q2_params, (batch.obs, action))
            loss = 0.5 * ((q1 - target) ** 2).mean() + 0.5 * ((q2 - target) ** 2).mean()
            return loss, (q1.mean(), q2.mean())

        critic_grads, (critic_value, (q1_mean, q2_mean)) = grad_and_value(
            critic_loss, has_aux=True)(self.critic_adam.params)
        _adam_step(self.critic_adam, critic_grads)
        q1_params, q2_params = self._critics(self.critic_adam.params)

        def actor_loss(params: Tensors) -> tuple[torch.Tensor, torch.Tensor]:
            sample = functional_call(self.actor, params, (batch.obs,), {'noise': noise})
            q = torch.minimum(functional_call(self.q1, q1_params, (batch.obs, sample.action)),
                              functional_call(self.q2, q2_params, (batch.obs, sample.action)))
            return (alpha * sample.log_prob - q).mean(), sample.log_prob

        actor_grads, (actor_value, log_prob) = grad_and_value(actor_loss, has_aux=True)(
            self.actor_adam.params)
        _adam_step(self.actor_adam, actor_grads)
        alpha_loss = torch.zeros((), dtype=alpha.dtype)
        if self.autotune_alpha:
            # J(alpha) = E[-log_alpha (log pi + target_entropy)]; its gradient in log_alpha:
            alpha_loss = -(log_alpha * (log_prob + self.target_entropy)).mean()
            _adam_step(self.alpha_adam, {'log_alpha': -(log_prob + self.target_entropy).mean()})
        if polyak:
            for targets, params in ((self.q1_target, q1_params), (self.q2_target, q2_params)):
                torch._foreach_lerp_(list(targets.values()), [params[k] for k in targets],
                                     self.tau)
        return UpdateStats(critic_value, actor_value, alpha_loss, q1_mean, q2_mean,
                           target.mean(), -log_prob.mean())
