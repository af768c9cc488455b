"""The SAC update's best time, compiled or eager, for the training benchmark's floor.

The update compiled is the library's own (:class:`rcbf_ros.learning.compiled_update.
FunctionalUpdate`, what ``SACConfig.compile_update`` runs): the whole network update as one
function, compiled with ``torch.compile(fullgraph=True)``. It runs on a ``baseline`` twin of the
learner's agent (the same networks, Adam state and alpha; no safety layer: the floor adds the
differentiable QP as a separately timed part, and ``diff`` and ``modular`` run the same network
arithmetic at other actions), so the learner is never touched.

:func:`best_update` runs the first compiled call next to one ``SAC.update`` from the same
state, on the same batch and the same noise draws, and reports the largest parameter
difference: the compiled function is the same update, up to float32 round-off.
"""
from __future__ import annotations

from dataclasses import replace
import statistics
import time
from typing import Callable

import torch

from rcbf_ros.learning.buffers import TransitionBatch
from rcbf_ros.learning.compiled_update import FunctionalUpdate
from rcbf_ros.learning.sac import SAC

BLOCK = 25
"""Consecutive timed calls of one way of updating in :func:`best_update`."""


def difference(a: SAC, b: SAC) -> float:
    """Largest |difference| of any parameter (actor, critics, targets, log alpha) of two
    agents of the same sizes."""
    worst = float((a.log_alpha.detach() - b.log_alpha.detach()).abs())
    for name in ('actor', 'q1', 'q2', 'q1_target', 'q2_target'):
        for p, q in zip(getattr(a, name).parameters(), getattr(b, name).parameters()):
            worst = max(worst, float((p.detach() - q.detach()).abs().max()))
    return worst


def baseline_twin(sac: SAC) -> SAC:
    """A ``baseline`` agent with ``sac``'s networks, optimiser states, generator state and
    update count: the update without a safety layer, on the same tensors."""
    cfg = replace(sac.config, mode='baseline', compile_update=False)
    twin = SAC(sac.obs_dim, sac.n_u, sac.u_low, sac.u_high, cfg, dtype=sac.dtype)
    twin.load_state_dict({**sac.state_dict(), 'mode': 'baseline'})
    return twin


def best_update(sac: SAC, batches: list[TransitionBatch], *, modes: list[str],
                calls: int, block: int = BLOCK) -> dict:
    """The whole update compiled in each of ``modes``, timed next to the eager ``SAC.update``;
    each from the state of ``sac`` (its ``baseline_twin``; ``sac`` itself is not touched), on
    ``batches`` in turn.

    Each variant is timed ``calls`` times, in blocks of ``block`` consecutive calls, each
    block after one untimed call, the variants' blocks in turn (after 5 untimed calls of
    each). In its own block a variant runs as a training loop runs it, its working set in the
    caches: one call of each in turn would time every call just after another variant's
    products evicted it (the eager update's best call 13-18 % slower next to the compiled
    graphs than on its own, measured on this benchmark's host). The blocks alternating, a
    slower minute of the host falls on all of them alike.

    Returns ``variants``: per variant ('eager', then each mode) the best and the median ms;
    ``compile_s``: each mode's one-off compile seconds (its first call, not in the timing);
    ``agreement``: per mode, the largest parameter difference between its first call and
    ``SAC.update`` from the same state on the same batch and noise draws.
    """
    if block < 1:
        raise ValueError(f'block must be >= 1, got {block}')
    out: dict = {'variants': {}, 'compile_s': {}, 'agreement': {}}
    eager = baseline_twin(sac)
    variants: dict[str, Callable[[int], object]] = {
        'eager': lambda i: eager.update(batches[i % len(batches)])}
    shape = (batches[0].obs.shape[0], sac.n_u)
    for mode in modes:
        twin, reference = baseline_twin(sac), baseline_twin(sac)
        functional = FunctionalUpdate(twin, compile_=True,
                                      mode=None if mode == 'default' else mode)
        draws = torch.Generator()
        draws.set_state(twin.generator.get_state())
        noises = [(torch.randn(shape, generator=draws, dtype=sac.dtype),
                   torch.randn(shape, generator=draws, dtype=sac.dtype)) for _ in batches]
        start = time.perf_counter()
        functional.step(batches[0], batches[0].u_rl, *noises[0], True)
        out['compile_s'][mode] = time.perf_counter() - start
        reference.update(batches[0])
        out['agreement'][mode] = difference(twin, reference)
        variants[mode] = (lambda i, f=functional, n=noises: f.step(
            batches[i % len(batches)], batches[i % len(batches)].u_rl, *n[i % len(n)], True))
    times: dict[str, list[float]] = {name: [] for name in variants}
    made = dict.fromkeys(variants, 0)  # each variant's calls so far: its next batch

    def run(name: str) -> float:
        start = time.perf_counter()
        variants[name](made[name])
        made[name] += 1
        return time.perf_counter() - start

    for name in variants:
        for _ in range(5):
            run(name)
    while any(len(timed) < calls for timed in times.values()):
        for name, timed in times.items():
            if len(timed) < calls:
                run(name)
                timed.extend(run(name) for _ in range(min(block, calls - len(timed))))
    out['variants'] = {name: (1e3 * min(t), 1e3 * statistics.median(t))
                       for name, t in times.items()}
    return out
