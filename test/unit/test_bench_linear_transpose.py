"""The transposed-operand benchmark compares the library's hidden-layer backward with a copying
one that computes the same update, and leaves the library as it found it."""
from __future__ import annotations

from benchmark_modules import load_benchmark
import numpy as np
from sac_batches import N_U, OBS, random_batches
import torch

from rcbf_ros.learning import networks
from rcbf_ros.learning.sac import SAC, SACConfig

bench = load_benchmark('bench_linear_transpose')


def _agent() -> SAC:
    # Hidden layers of 64: the smallest that go through oneDNN (networks._ONEDNN_MIN_SIZE).
    return SAC(OBS, N_U, -np.ones(N_U), np.ones(N_U),
               SACConfig(mode='baseline', hidden_sizes=(64, 64)), seed=5)


def test_the_copying_backward_is_the_same_update_and_is_undone_after_its_block():
    viewing, copying = _agent(), _agent()
    backward, linear = networks._LinearFunction.backward, networks.linear
    copied = []
    contiguous = torch.Tensor.contiguous

    def counting(self, *args, **kwargs):
        if not self.is_contiguous():
            copied.append(tuple(self.shape))
        return contiguous(self, *args, **kwargs)

    for batch in random_batches(3):
        viewing.update(batch)
        torch.Tensor.contiguous = counting
        try:
            with bench.copies_first():
                copying.update(batch)
        finally:
            torch.Tensor.contiguous = contiguous
    assert networks._LinearFunction.backward is backward and networks.linear is linear
    # Every hidden-layer backward copied its transposes: per update, each critic's and the
    # actor's layer (weight, grad, input) and twin_minimum's pass through each critic's.
    assert len(copied) >= 3 * 3
    for name in ('actor', 'q1', 'q2'):
        for p, q in zip(getattr(viewing, name).parameters(),
                        getattr(copying, name).parameters()):
            torch.testing.assert_close(p, q, rtol=1e-5, atol=1e-6)
