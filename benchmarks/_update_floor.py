"""The SAC update's best compiled time, for the training benchmark's floor.

``SAC.update`` (rcbf_ros/learning/sac.py) steps its networks through ``loss.backward()`` and
``torch.optim.Adam``: torch.compile can only compile the pieces between those calls, which gains
nothing measurable here. :class:`FunctionalUpdate` states the same update as ONE pure function
of the networks' tensors, so that the whole update compiles as one graph (``fullgraph=True``):
critic target (next action, target critics), critic loss and its gradient
(``torch.func.grad_and_value``), the critics' Adam step, actor loss with the critics' weights
held fixed and its gradient, the actor's Adam step, the alpha loss and its Adam step, and the
Polyak step of the target critics, each in place on copies of the agent's tensors. The update
needs no safety layer (the floor adds the differentiable QP as a separately timed part), so it
is the update of ``baseline``; ``diff`` and ``modular`` run the same network arithmetic at other
actions.

:func:`best_update` runs the first compiled call next to one ``SAC.update`` from the same
state, on the same batch and the same noise draws, and reports the largest parameter
difference (:meth:`FunctionalUpdate.difference`): the compiled function is the same update, up
to float32 round-off.
"""
from __future__ import annotations

import copy
from dataclasses import replace
import statistics
import time
from typing import Callable

import torch
from torch.func import functional_call, grad_and_value

from rcbf_ros.learning.buffers import TransitionBatch
from rcbf_ros.learning.sac import SAC

Tensors = dict[str, torch.Tensor]


def _tensors(module: torch.nn.Module) -> Tensors:
    return {name: param.detach().clone() for name, param in module.named_parameters()}


def _moments(optimizer: torch.optim.Optimizer, module_params: dict[str, torch.nn.Parameter]
             ) -> tuple[Tensors, Tensors]:
    """Copies of Adam's first and second moments of ``module_params`` (zeros before the first
    step)."""
    first, second = {}, {}
    for name, param in module_params.items():
        state = optimizer.state.get(param, {})
        first[name] = (state['exp_avg'].clone() if 'exp_avg' in state
                       else torch.zeros_like(param.detach()))
        second[name] = (state['exp_avg_sq'].clone() if 'exp_avg_sq' in state
                        else torch.zeros_like(param.detach()))
    return first, second


def _adam(params: Tensors, grads: Tensors, moments: tuple[Tensors, Tensors], *,
          step: torch.Tensor, lr: float, betas: tuple[float, float], eps: float) -> None:
    """torch.optim.Adam's rule (no weight decay, no amsgrad), in place; ``step`` counts from 1."""
    first, second = moments
    beta1, beta2 = betas
    step_size = lr / (1.0 - beta1 ** step)
    root_correction = (1.0 - beta2 ** step).sqrt()
    for name, param in params.items():
        grad = grads[name]
        first[name].lerp_(grad, 1.0 - beta1)
        second[name].mul_(beta2).addcmul_(grad, grad, value=1.0 - beta2)
        denom = (second[name].sqrt() / root_correction).add_(eps)
        param.sub_(step_size * first[name] / denom)


class FunctionalUpdate:
    """The next SAC update of ``sac`` (its weights, Adam moments and step count, copied) as one
    function ``step(batch, next_noise, noise)`` of in-place tensor operations; ``compile`` it
    with torch.compile. Only for timing and the agreement check; it never touches ``sac``."""

    def __init__(self, sac: SAC) -> None:
        cfg = sac.config
        self.config, self.target_entropy = cfg, sac.target_entropy
        self.actor, self.q1, self.q2 = (copy.deepcopy(m) for m in (sac.actor, sac.q1, sac.q2))
        self.actor_params, self.q1_params, self.q2_params = (
            _tensors(m) for m in (sac.actor, sac.q1, sac.q2))
        self.q1_target, self.q2_target = _tensors(sac.q1_target), _tensors(sac.q2_target)
        self.log_alpha = sac.log_alpha.detach().clone()
        self.moments = {
            'actor': _moments(sac.actor_optimizer, dict(sac.actor.named_parameters())),
            'q1': _moments(sac.critic_optimizer, dict(sac.q1.named_parameters())),
            'q2': _moments(sac.critic_optimizer, dict(sac.q2.named_parameters())),
            'alpha': _moments(sac.alpha_optimizer, {'log_alpha': sac.log_alpha})}
        self.step_count = torch.tensor(float(sac.num_updates), dtype=torch.float64)
        self.betas = sac.critic_optimizer.defaults['betas']
        self.eps = sac.critic_optimizer.defaults['eps']

    def step(self, batch: TransitionBatch, next_noise: torch.Tensor,
             noise: torch.Tensor) -> torch.Tensor:
        """One update (target critics stepped on every call); returns the critic loss."""
        cfg = self.config
        self.step_count.add_(1.0)
        adam = {'step': self.step_count, 'betas': self.betas, 'eps': self.eps}
        alpha = self.log_alpha.exp()
        with torch.no_grad():
            following = functional_call(self.actor, self.actor_params, (batch.next_obs,),
                                        {'noise': next_noise})
            next_q = torch.minimum(
                functional_call(self.q1, self.q1_target, (batch.next_obs, following.action)),
                functional_call(self.q2, self.q2_target, (batch.next_obs, following.action)))
            target = batch.reward + cfg.gamma * (1.0 - batch.done) * (
                next_q - alpha * following.log_prob)

        def critic_loss(q1_params: Tensors, q2_params: Tensors) -> torch.Tensor:
            q1 = functional_call(self.q1, q1_params, (batch.obs, batch.u_rl))
            q2 = functional_call(self.q2, q2_params, (batch.obs, batch.u_rl))
            return 0.5 * ((q1 - target) ** 2).mean() + 0.5 * ((q2 - target) ** 2).mean()

        (q1_grads, q2_grads), loss = grad_and_value(critic_loss, argnums=(0, 1))(
            self.q1_params, self.q2_params)
        _adam(self.q1_params, q1_grads, self.moments['q1'], lr=cfg.critic_lr, **adam)
        _adam(self.q2_params, q2_grads, self.moments['q2'], lr=cfg.critic_lr, **adam)

        def actor_loss(actor_params: Tensors) -> tuple[torch.Tensor, torch.Tensor]:
            sample = functional_call(self.actor, actor_params, (batch.obs,), {'noise': noise})
            q = torch.minimum(functional_call(self.q1, self.q1_params, (batch.obs, sample.action)),
                              functional_call(self.q2, self.q2_params, (batch.obs, sample.action)))
            return (alpha * sample.log_prob - q).mean(), sample.log_prob

        actor_grads, (_, log_prob) = grad_and_value(actor_loss, has_aux=True)(self.actor_params)
        _adam(self.actor_params, actor_grads, self.moments['actor'], lr=cfg.actor_lr, **adam)
        if cfg.autotune_alpha:
            alpha_grad = -(log_prob + self.target_entropy).mean()
            _adam({'log_alpha': self.log_alpha}, {'log_alpha': alpha_grad},
                  self.moments['alpha'], lr=cfg.alpha_lr, **adam)
        torch._foreach_lerp_(list(self.q1_target.values()), list(self.q1_params.values()),
                             cfg.tau)
        torch._foreach_lerp_(list(self.q2_target.values()), list(self.q2_params.values()),
                             cfg.tau)
        return loss

    def difference(self, sac: SAC) -> float:
        """Largest |difference| of any parameter (actor, critics, targets, log alpha) between
        this update's tensors and ``sac``'s."""
        pairs = [(sac.actor, self.actor_params), (sac.q1, self.q1_params),
                 (sac.q2, self.q2_params), (sac.q1_target, self.q1_target),
                 (sac.q2_target, self.q2_target)]
        worst = float((sac.log_alpha.detach() - self.log_alpha).abs())
        for module, params in pairs:
            for name, param in module.named_parameters():
                worst = max(worst, float((param.detach() - params[name]).abs().max()))
        return worst


def baseline_twin(sac: SAC) -> SAC:
    """A ``baseline`` agent with ``sac``'s networks, optimiser states, generator state and
    update count: the update without a safety layer, on the same tensors."""
    cfg = replace(sac.config, mode='baseline')
    twin = SAC(sac.obs_dim, sac.n_u, sac.u_low, sac.u_high, cfg, dtype=sac.dtype)
    twin.load_state_dict({**sac.state_dict(), 'mode': 'baseline'})
    return twin


def best_update(sac: SAC, batches: list[TransitionBatch], *, modes: list[str],
                calls: int) -> dict:
    """The whole update compiled in each of ``modes``, timed next to the eager ``SAC.update``;
    each from the state of ``sac`` (its ``baseline_twin``; ``sac`` itself is not touched), on
    ``batches`` in turn.

    The variants are timed interleaved, one call of each in turn, ``calls`` rounds after 5
    untimed ones, so that other load on the machine falls on all of them alike.

    Returns ``variants``: per variant ('eager', then each mode) the best and the median ms;
    ``compile_s``: each mode's one-off compile seconds (its first call, not in the timing);
    ``agreement``: per mode, the largest parameter difference between its first call and
    ``SAC.update`` from the same state on the same batch and noise draws.
    """
    out: dict = {'variants': {}, 'compile_s': {}, 'agreement': {}}
    eager = baseline_twin(sac)
    variants: dict[str, Callable[[int], object]] = {
        'eager': lambda i: eager.update(batches[i % len(batches)])}
    shape = (batches[0].obs.shape[0], sac.n_u)
    for mode in modes:
        twin = baseline_twin(sac)
        functional = FunctionalUpdate(twin)
        compiled = torch.compile(functional.step, fullgraph=True, dynamic=False,
                                 mode=None if mode == 'default' else mode)
        draws = torch.Generator()
        draws.set_state(twin.generator.get_state())
        noises = [(torch.randn(shape, generator=draws, dtype=sac.dtype),
                   torch.randn(shape, generator=draws, dtype=sac.dtype)) for _ in batches]
        start = time.perf_counter()
        compiled(batches[0], *noises[0])
        out['compile_s'][mode] = time.perf_counter() - start
        twin.update(batches[0])
        out['agreement'][mode] = functional.difference(twin)
        variants[mode] = (lambda i, c=compiled, n=noises:
                          c(batches[i % len(batches)], *n[i % len(n)]))
    times: dict[str, list[float]] = {name: [] for name in variants}
    for index in range(5 + calls):
        for name, call in variants.items():
            start = time.perf_counter()
            call(index)
            if index >= 5:
                times[name].append(time.perf_counter() - start)
    out['variants'] = {name: (1e3 * min(t), 1e3 * statistics.median(t))
                       for name, t in times.items()}
    return out
