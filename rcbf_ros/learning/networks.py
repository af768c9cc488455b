"""Neural networks of SAC: squashed-Gaussian actor, Q critics, compensator (all MLPs)."""
from __future__ import annotations

import math
from typing import Callable, NamedTuple, Sequence

import numpy as np
import torch
from torch import nn
from torch.autograd.function import once_differentiable
import torch.nn.functional as F

LOG_STD_MIN = -5.0
LOG_STD_MAX = 2.0
_HALF_LOG_TWO_PI = 0.5 * math.log(2.0 * math.pi)


def _onednn_linear() -> Callable[..., torch.Tensor] | None:
    """torch's oneDNN linear kernel (``mkldnn::_linear_pointwise``, x W^T + b) where this
    build of torch has it and it answers a small product exactly, else None."""
    try:
        kernel = torch.ops.mkldnn._linear_pointwise
        f32 = torch.float32
        out = kernel(torch.ones(2, 3, dtype=f32), torch.full((4, 3), 2.0, dtype=f32),
                     torch.ones(4, dtype=f32), 'none', [], '')
    except (AttributeError, RuntimeError):
        return None
    return kernel if torch.equal(out, torch.full((2, 4), 7.0, dtype=f32)) else None


_ONEDNN_LINEAR = _onednn_linear()
_ONEDNN_MIN_SIZE = 64
"""oneDNN takes a product whose weight has at least this many rows and columns (a hidden
layer's); a thin one (an input layer or a head) costs oneDNN more per call than it saves."""


def linear(x: torch.Tensor, weight: torch.Tensor,
           bias: torch.Tensor | None = None) -> torch.Tensor:
    """x W^T + b for a 2-D ``x``, as ``F.linear``; float32 products through oneDNN.

    torch's own float32 product on CPU is MKL's, which takes its AVX2 path on CPUs that are
    not Intel's although they have AVX-512 (benchmarks/bench_training.py measures both
    kernels' rate on its machine); oneDNN takes the widest path the CPU has. Both are float32
    products (the order of the sums differs, so the results differ by rounding). Thin weights
    (a side under ``_ONEDNN_MIN_SIZE``), float64, ``torch.backends.mkldnn.enabled = False``
    and anything else go to ``F.linear``. No autograd graph: for the gradient use
    :class:`Linear`.
    """
    if not _onednn_takes(x, weight):
        return F.linear(x, weight, bias)
    return _ONEDNN_LINEAR(x, weight, bias, 'none', [], '')


def _onednn_takes(x: torch.Tensor, weight: torch.Tensor) -> bool:
    """Whether :func:`linear` runs x W^T through oneDNN (its docstring says when). Shapes that
    do not fit go to ``F.linear``, whose error names them (oneDNN's does not)."""
    return (_ONEDNN_LINEAR is not None and x.dtype == torch.float32
            and weight.dtype == torch.float32 and x.dim() == 2
            and x.shape[1] == weight.shape[1] and min(weight.shape) >= _ONEDNN_MIN_SIZE
            and torch.backends.mkldnn.enabled)


class _LinearFunction(torch.autograd.Function):
    """:func:`linear` with its gradient, each product through :func:`linear` (once
    differentiable: a second derivative through it raises instead of coming out wrong)."""

    @staticmethod
    def forward(ctx, x: torch.Tensor, weight: torch.Tensor,
                bias: torch.Tensor | None) -> torch.Tensor:
        ctx.save_for_backward(x, weight)
        ctx.has_bias = bias is not None
        return linear(x, weight, bias)

    @staticmethod
    @once_differentiable
    def backward(ctx, grad: torch.Tensor) -> tuple[torch.Tensor | None, ...]:
        x, weight = ctx.saved_tensors
        need_x, need_weight, need_bias = ctx.needs_input_grad
        # The transposes go to oneDNN as views: it reads a transposed weight in place and
        # copies a transposed input once itself, faster than copying both here first
        # (benchmarks/bench_linear_transpose.py).
        grad = grad.contiguous()
        grad_x = linear(grad, weight.t()) if need_x else None  # grad W
        grad_weight = linear(grad.t(), x.t()) if need_weight else None  # grad^T x
        grad_bias = grad.sum(0) if need_bias and ctx.has_bias else None
        return grad_x, grad_weight, grad_bias


class Linear(nn.Linear):
    """``nn.Linear`` (the same parameters and state dict) whose float32 products run through
    :func:`linear`, its gradient too, where the weight is not thin. Where torch.compile traces
    it or a ``torch.func`` transform runs it, and for any other dtype or shape, it is
    ``nn.Linear`` itself."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if (not _onednn_takes(x, self.weight) or torch.compiler.is_compiling()
                or torch._C._are_functorch_transforms_active()):
            return F.linear(x, self.weight, self.bias)
        return _LinearFunction.apply(x, self.weight, self.bias)


def mlp(n_in: int, n_out: int, hidden_sizes: Sequence[int]) -> nn.Sequential:
    """Fully connected ReLU network ``n_in -> hidden_sizes... -> n_out`` (linear output).

    The ReLUs work in place on their linear layer's output, which nothing else reads (the
    linear layer's gradient needs its input, not its output): one buffer less per layer."""
    layers: list[nn.Module] = []
    width = n_in
    for hidden in hidden_sizes:
        layers += [Linear(width, hidden), nn.ReLU(inplace=True)]
        width = hidden
    layers.append(Linear(width, n_out))
    return nn.Sequential(*layers)


class NumpyMLP:
    """Single-sample inference of an :func:`mlp` in numpy, on zero-copy views of its weights.

    Acting needs one forward pass per environment step at batch 1, where torch's per-op
    dispatch (and the cache misses it causes right after a SAC update) costs several times the
    arithmetic. The views share memory with the parameters, so optimizer steps and
    ``load_state_dict`` (both in place) are seen without copying; a parameter *replaced* by a
    new tensor (``.to(dtype)`` after construction) is not, so build the view after any such
    move.
    """

    def __init__(self, net: nn.Sequential) -> None:
        self.layers: list[tuple[np.ndarray, np.ndarray, bool]] = []
        modules = list(net)
        for index, module in enumerate(modules):
            if isinstance(module, nn.Linear):
                relu = index + 1 < len(modules) and isinstance(modules[index + 1], nn.ReLU)
                self.layers.append((module.weight.detach().numpy(),
                                    module.bias.detach().numpy(), relu))
            elif not isinstance(module, nn.ReLU):
                raise TypeError(f'NumpyMLP: unsupported layer {type(module).__name__}')

    def __call__(self, x: np.ndarray) -> np.ndarray:
        """x: (n_in,) -> (n_out,)."""
        for weight, bias, relu in self.layers:
            x = weight @ x
            x += bias
            if relu:
                np.maximum(x, 0.0, out=x)
        return x


class PolicySample(NamedTuple):
    """One reparameterised draw from the actor."""

    action: torch.Tensor
    """(B, n_u) action in the box [u_low, u_high]."""
    log_prob: torch.Tensor
    """(B,) log density of ``action`` under the squashed Gaussian."""
    mean_action: torch.Tensor
    """(B, n_u) deterministic action (squashed mean), for evaluation."""


class SquashedGaussianActor(nn.Module):
    """pi(u | obs): u = c + s * tanh(z), z ~ N(mu(obs), sigma(obs)^2) per action dimension.

    ``c = (u_high + u_low) / 2`` and ``s = (u_high - u_low) / 2`` map tanh's (-1, 1) to the action
    box. The log density follows from the change of variables,

        log pi(u | obs) = sum_j [log N(z_j; mu_j, sigma_j) - log(s_j (1 - tanh(z_j)^2))].

    Args:
        obs_dim: observation size.
        u_low, u_high: (n_u,) action box.
        hidden_sizes: hidden layer widths.
    """

    def __init__(self, obs_dim: int, u_low: torch.Tensor, u_high: torch.Tensor,
                 hidden_sizes: Sequence[int] = (256, 256)) -> None:
        super().__init__()
        n_u = u_low.shape[0]
        if len(hidden_sizes) < 1:
            raise ValueError('hidden_sizes must name at least one layer')
        # obs -> hidden_sizes (ReLU after each) -> two linear heads.
        self.trunk = nn.Sequential(mlp(obs_dim, hidden_sizes[-1], hidden_sizes[:-1]),
                                   nn.ReLU(inplace=True))
        self.mean_head = Linear(hidden_sizes[-1], n_u)
        self.log_std_head = Linear(hidden_sizes[-1], n_u)
        self.register_buffer('action_center', (u_high + u_low) / 2.0)
        self.register_buffer('action_half_range', (u_high - u_low) / 2.0)

    def forward(self, obs: torch.Tensor, noise: torch.Tensor | None = None,
                generator: torch.Generator | None = None) -> PolicySample:
        """Reparameterised sample.

        Args:
            obs: (B, obs_dim).
            noise: optional (B, n_u) standard-normal draw (fixes the sample, e.g. for
                finite-difference tests); drawn with ``generator`` when None.
            generator: random source for ``noise``.
        """
        features = self.trunk(obs)
        mean = self.mean_head(features)
        log_std = torch.clamp(self.log_std_head(features), LOG_STD_MIN, LOG_STD_MAX)
        if noise is None:
            noise = torch.randn(mean.shape, generator=generator, dtype=mean.dtype,
                                device=mean.device)
        half_range = self.action_half_range
        # z = mu + sigma noise; u = c + s tanh(z) (addcmul: one operation each).
        squashed = torch.tanh(torch.addcmul(mean, log_std.exp(), noise))
        action = torch.addcmul(self.action_center, half_range, squashed)
        # log N(z; mu, sigma) = -(log sigma + noise^2 / 2) - log(2 pi) / 2 per dimension, and
        # log |d u / d z| = log(s (1 - tanh^2)), written s + 1e-6 - s tanh^2 (1e-6 guards tanh
        # saturation).
        log_jacobian = torch.log(torch.addcmul(half_range + 1e-6, half_range, squashed.square(),
                                               value=-1.0))
        log_prob = ((-_HALF_LOG_TWO_PI * mean.shape[-1])
                    - (torch.addcmul(log_std, noise, noise, value=0.5) + log_jacobian).sum(-1))
        mean_action = torch.addcmul(self.action_center, half_range, torch.tanh(mean))
        return PolicySample(action, log_prob, mean_action)

    def numpy_sampler(self) -> NumpyActor:
        """A :class:`NumpyActor` on this actor's (live) weights."""
        return NumpyActor(self)


class NumpyActor:
    """The actor's action for ONE observation in numpy (see :class:`NumpyMLP`).

    Computes what :meth:`SquashedGaussianActor.forward` returns as ``action`` (for the given
    standard-normal ``noise``) and ``mean_action``, up to floating-point rounding, without the
    log density, which acting does not need.
    """

    def __init__(self, actor: SquashedGaussianActor) -> None:
        self.trunk = NumpyMLP(actor.trunk[0])
        self.heads = NumpyMLP(nn.Sequential(actor.mean_head))
        self.log_std = NumpyMLP(nn.Sequential(actor.log_std_head))
        self.center = actor.action_center.detach().numpy()
        self.half_range = actor.action_half_range.detach().numpy()
        self.low, self.high = self.center - self.half_range, self.center + self.half_range
        self.dtype = self.center.dtype
        # The two heads' views: the call below applies them in place.
        (self._mean_weight, self._mean_bias, _), = self.heads.layers
        (self._log_std_weight, self._log_std_bias, _), = self.log_std.layers

    def __call__(self, obs: np.ndarray, noise: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
        """obs: (obs_dim,); noise: (n_u,) standard normal, or None for the mean only.

        Returns:
            action (the mean action when ``noise`` is None) and mean_action, both (n_u,),
            new arrays. The operations are those of ``center + half_range * tanh(...)``, in
            place where an intermediate is not needed again (the same values).
        """
        x = self.trunk(np.asarray(obs, dtype=self.dtype))
        np.maximum(x, 0.0, out=x)  # the trunk's closing ReLU
        mean = self._mean_weight @ x
        mean += self._mean_bias
        mean_action = np.tanh(mean)
        mean_action *= self.half_range
        mean_action += self.center
        if noise is None:
            return mean_action, mean_action
        action = self._log_std_weight @ x
        action += self._log_std_bias
        np.maximum(action, LOG_STD_MIN, out=action)  # np.clip's min(max(.)), without its wrapper
        np.minimum(action, LOG_STD_MAX, out=action)
        np.exp(action, out=action)
        action *= noise
        action += mean
        np.tanh(action, out=action)
        action *= self.half_range
        action += self.center
        return action, mean_action


class QNetwork(nn.Module):
    """Q(obs, u): an MLP on the concatenation, output (B,)."""

    def __init__(self, obs_dim: int, n_u: int, hidden_sizes: Sequence[int] = (256, 256)) -> None:
        super().__init__()
        self.net = mlp(obs_dim + n_u, 1, hidden_sizes)

    @property
    def linears(self) -> list[nn.Linear]:
        """The linear layers in order (a ReLU follows each but the last)."""
        return [module for module in self.net if isinstance(module, nn.Linear)]

    def forward(self, obs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """obs: (B, obs_dim), action: (B, n_u) -> (B,)."""
        return self.net(torch.cat([obs, action], dim=-1)).squeeze(-1)


class _TwinMinimum(torch.autograd.Function):
    """min(Q1(obs, u), Q2(obs, u)) with its gradient in the action only.

    Each sample's minimum is one critic's value (at a tie, autograd's ``torch.minimum`` gives
    each half the gradient), so the backward pass runs each critic's input-gradient chain only
    over the samples whose minimum it is, instead of both critics over the whole batch with
    zeros in half of the rows: one critic's backward arithmetic instead of two. The forward
    pass is the critics' own (the same ``linear`` and ReLU, keeping each hidden layer's output
    for ReLU's backward). The critics' weights must not change between the loss and its backward
    pass (they are read again there).
    """

    @staticmethod
    def forward(ctx, action: torch.Tensor, obs: torch.Tensor, first: QNetwork,
                second: QNetwork) -> torch.Tensor:
        x = torch.cat([obs, action], dim=-1)
        values, chains = [], []
        for critic in (first, second):
            h, hidden = x, []
            linears = critic.linears
            for layer in linears[:-1]:
                h = torch.relu_(linear(h, layer.weight, layer.bias))
                hidden.append(h)
            values.append(linear(h, linears[-1].weight, linears[-1].bias).squeeze(-1))
            chains.append(([layer.weight for layer in linears], hidden))
        # Saved for backward, so that a weight changed before the backward pass raises.
        ctx.sizes = [len(hidden) for _, hidden in chains]
        ctx.save_for_backward(*values, *(t for weights, hidden in chains
                                         for t in (*weights, *hidden)))
        ctx.obs_dim = obs.shape[-1]
        return torch.minimum(*values)

    @staticmethod
    @once_differentiable
    def backward(ctx, grad: torch.Tensor) -> tuple[torch.Tensor | None, ...]:
        first, second, *rest = ctx.saved_tensors
        chains = []
        for size in ctx.sizes:
            weights, hidden = rest[:size + 1], rest[size + 1:2 * size + 1]
            chains.append((weights, hidden))
            rest = rest[2 * size + 1:]
        tie = first == second
        share = torch.where(tie, 0.5 * grad, grad)
        grad_action = None
        # As torch.minimum's backward: a critic takes the rows where it is not above the other
        # (at a tie half the gradient each; a NaN passes the gradient to both).
        for chain, picked in zip(chains, (~(second < first), ~(first < second))):
            rows = picked.nonzero().squeeze(-1)
            if rows.numel() == 0:
                continue
            weights, hidden = chain
            g = share[rows, None] @ weights[-1]
            for weight, h in zip(weights[-2::-1], hidden[::-1]):
                # ReLU's backward (the gradient where its output is > 0) on these rows, then
                # the product with the layer's weight (g W).
                g = linear(torch.ops.aten.threshold_backward(g, h.index_select(0, rows), 0.0),
                           weight.t())
            part = g[:, ctx.obs_dim:]
            if grad_action is None:
                grad_action = torch.zeros(grad.shape[0], part.shape[-1], dtype=part.dtype,
                                          device=part.device)
            grad_action.index_add_(0, rows, part)
        return grad_action, None, None, None


def twin_minimum(first: QNetwork, second: QNetwork, obs: torch.Tensor,
                 action: torch.Tensor) -> torch.Tensor:
    """min(Q1(obs, action), Q2(obs, action)): (B,), differentiable in ``action`` only.

    For a loss that holds the critics fixed (SAC's actor step): the critics' weights get no
    gradient, and ``obs`` none (it is data). The value is ``torch.minimum`` of the two
    critics; the action gradient equals autograd's through both (up to the order of the
    floating-point sums), at a tie half through each, as autograd's."""
    if obs.requires_grad:
        raise ValueError('twin_minimum: obs must not require a gradient (the action only)')
    if action.dim() != 2 or obs.dim() != 2:
        raise ValueError(f'twin_minimum: obs and action must be (B, n), got '
                         f'{tuple(obs.shape)} and {tuple(action.shape)}')
    return _TwinMinimum.apply(action, obs, first, second)


class Compensator(nn.Module):
    """c(obs) -> (B, n_u): regression of the safety filter's correction (Cheng et al. 2019)."""

    def __init__(self, obs_dim: int, n_u: int, hidden_sizes: Sequence[int] = (256, 256)) -> None:
        super().__init__()
        self.net = mlp(obs_dim, n_u, hidden_sizes)

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        """obs: (B, obs_dim) -> (B, n_u)."""
        return self.net(obs)
