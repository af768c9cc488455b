"""The networks' Linear (float32 hidden-layer products through oneDNN where torch has it)
against torch's own F.linear and autograd: values and the three gradients to float32
round-off, which products take oneDNN, and nn.Linear itself bit for bit wherever it must
be (float64, thin weights, torch.func transforms)."""
from __future__ import annotations

import pytest
import torch
from torch.func import grad
import torch.nn.functional as F

from rcbf_ros.learning import networks
from rcbf_ros.learning.buffers import TransitionBatch
from rcbf_ros.learning.networks import Linear, QNetwork, twin_minimum
from rcbf_ros.learning.sac import SAC

needs_onednn = pytest.mark.skipif(networks._ONEDNN_LINEAR is None,
                                  reason='this torch build has no oneDNN linear kernel')


def _layer(n_in: int, n_out: int, seed: int, dtype=torch.float32) -> Linear:
    torch.manual_seed(seed)
    return Linear(n_in, n_out).to(dtype)


def _grads(output: torch.Tensor, upstream: torch.Tensor, *tensors: torch.Tensor):
    return torch.autograd.grad((output * upstream).sum(), tensors)


@pytest.fixture
def counted(monkeypatch):
    """Counts the calls of the oneDNN kernel (the kernel still computes them)."""
    calls = []
    kernel = networks._ONEDNN_LINEAR

    def counting(*args):
        calls.append(tuple(args[1].shape))
        return kernel(*args)

    if kernel is not None:
        monkeypatch.setattr(networks, '_ONEDNN_LINEAR', counting)
    return calls


@needs_onednn
@pytest.mark.parametrize('batch', [256, 97])
def test_a_hidden_layer_and_its_three_gradients_are_torchs_to_float32_round_off(counted, batch):
    layer = _layer(256, 192, 0)
    g = torch.Generator().manual_seed(1)
    x = torch.randn(batch, 256, generator=g).requires_grad_(True)
    upstream = torch.randn(batch, 192, generator=g)
    out = layer(x)
    grads = _grads(out, upstream, x, layer.weight, layer.bias)
    assert len(counted) == 3   # the product and both backward products took oneDNN
    expected_out = F.linear(x, layer.weight, layer.bias)
    expected = _grads(expected_out, upstream, x, layer.weight, layer.bias)
    torch.testing.assert_close(out, expected_out, rtol=1e-5, atol=1e-5)
    for ours, theirs in zip(grads, expected):
        torch.testing.assert_close(ours, theirs, rtol=1e-4, atol=1e-4)


def test_float64_thin_weights_and_func_transforms_are_nn_linear_bit_for_bit(counted):
    g = torch.Generator().manual_seed(2)
    wide64 = _layer(128, 128, 3, torch.float64)
    x64 = torch.randn(16, 128, generator=g, dtype=torch.float64)
    assert torch.equal(wide64(x64), F.linear(x64, wide64.weight, wide64.bias))
    for n_in, n_out in ((5, 256), (256, 2)):   # an input layer and a head: thin weights
        thin = _layer(n_in, n_out, 4)
        x = torch.randn(32, n_in, generator=g)
        assert torch.equal(thin(x), F.linear(x, thin.weight, thin.bias))
    wide = _layer(128, 128, 5)
    x = torch.randn(8, 128, generator=g)
    via_func = grad(lambda inputs: wide(inputs).square().sum())(x)
    direct = grad(lambda inputs: F.linear(inputs, wide.weight, wide.bias).square().sum())(x)
    assert torch.equal(via_func, direct)
    assert counted == []


def _plain(critic: QNetwork, x: torch.Tensor) -> torch.Tensor:
    """The critic by F.linear and ReLU, autograd throughout (torch's own products)."""
    linears = critic.linears
    for layer in linears[:-1]:
        x = torch.relu(F.linear(x, layer.weight, layer.bias))
    return F.linear(x, linears[-1].weight, linears[-1].bias).squeeze(-1)


@needs_onednn
def test_twin_minimum_of_float32_critics_is_autograds_to_round_off(counted):
    torch.manual_seed(6)
    first, second = QNetwork(3, 2), QNetwork(3, 2)
    g = torch.Generator().manual_seed(7)
    obs = torch.randn(256, 3, generator=g)
    action = torch.randn(256, 2, generator=g).requires_grad_(True)
    with torch.no_grad():   # each critic the minimum of about half of the samples
        second.net[-1].bias += (first(obs, action) - second(obs, action)).median()
    counted.clear()
    value = twin_minimum(first, second, obs, action)
    (ours,) = torch.autograd.grad(value.sum(), action)
    assert len(counted) == 4   # each critic's hidden product, forward and backward
    reference = action.detach().clone().requires_grad_(True)
    x = torch.cat([obs, reference], -1)
    expected_value = torch.minimum(_plain(first, x), _plain(second, x))
    (expected,) = torch.autograd.grad(expected_value.sum(), reference)
    torch.testing.assert_close(value, expected_value, rtol=1e-5, atol=1e-5)
    # Where the two critics are within rounding of each other the two ways may take the
    # minimum from different critics (each right for its own rounding): compared elsewhere.
    with torch.no_grad():
        gap = (_plain(first, x) - _plain(second, x)).abs()
    apart = gap > 1e-4 * (1.0 + expected_value.detach().abs())
    assert int(apart.sum()) > 250
    torch.testing.assert_close(ours[apart], expected[apart], rtol=1e-4, atol=1e-5)


@needs_onednn
def test_equal_seeds_train_bit_identical_networks_through_onednn(counted):
    g = torch.Generator().manual_seed(9)

    def rand(*shape: int) -> torch.Tensor:
        return torch.rand(*shape, generator=g) * 2 - 1

    batches = [TransitionBatch(obs=rand(256, 3), state=rand(256, 3), u_rl=rand(256, 2),
                               u_safe=rand(256, 2), u_s=rand(256, 2), reward=rand(256),
                               next_obs=rand(256, 3), next_state=rand(256, 3),
                               done=torch.zeros(256)) for _ in range(2)]
    agents = [SAC(3, 2, -torch.ones(2), torch.ones(2), seed=4) for _ in range(2)]
    for agent in agents:
        for batch in batches:
            agent.update(batch)
    assert counted   # the 256-wide hidden layers went through oneDNN
    for ours, theirs in zip(agents[0].actor.parameters(), agents[1].actor.parameters()):
        assert torch.equal(ours, theirs)
    for ours, theirs in zip(agents[0].q1.parameters(), agents[1].q1.parameters()):
        assert torch.equal(ours, theirs)


@needs_onednn
def test_a_second_derivative_through_the_onednn_layer_raises_instead_of_being_wrong():
    layer = _layer(64, 64, 10)
    x = torch.randn(8, 64).requires_grad_(True)
    (first,) = torch.autograd.grad(torch.tanh(layer(x)).sum(), x, create_graph=True)
    with pytest.raises(RuntimeError, match='once_differentiable|not have been used'):
        torch.autograd.grad(first.sum(), x)


def test_mkldnn_switched_off_is_f_linear_bit_for_bit(counted):
    layer = _layer(128, 128, 11)
    x = torch.randn(16, 128)
    with torch.backends.mkldnn.flags(enabled=False):
        assert torch.equal(layer(x), F.linear(x, layer.weight, layer.bias))
    assert counted == []


def test_twin_minimum_checks_its_critics_weights_and_passes_a_nan_as_torch_minimum_does():
    first, second = (QNetwork(3, 2, (8,)).to(torch.float64) for _ in range(2))
    obs = torch.randn(6, 3, dtype=torch.float64)
    action = torch.randn(6, 2, dtype=torch.float64, requires_grad=True)
    value = twin_minimum(first, second, obs, action)
    with torch.no_grad():
        first.net[0].weight.add_(1.0)   # changed between the loss and its backward
    with pytest.raises(RuntimeError, match='modified by an inplace operation'):
        value.sum().backward()
    obs[2] = float('nan')
    ours = torch.autograd.grad(twin_minimum(first, second, obs, action).sum(), action)[0]
    reference = action.detach().clone().requires_grad_(True)
    expected = torch.autograd.grad(
        torch.minimum(first(obs, reference), second(obs, reference)).sum(), reference)[0]
    torch.testing.assert_close(ours, expected, equal_nan=True, rtol=1e-12, atol=1e-14)
    assert bool((ours[2] != 0).any())   # the NaN sample's gradient reached the action


def test_an_input_of_the_wrong_width_gets_torchs_error_naming_the_shapes():
    layer = _layer(128, 128, 12)
    with pytest.raises(RuntimeError, match='shapes cannot be multiplied'):
        layer(torch.randn(4, 100))
