"""Training speed: environment steps per second including SAC updates, per system and mode,
ours against the authors' reference code re-run side by side.

    python benchmarks/bench_training.py [--steps 200] [--systems unicycle ...]
        [--reference DIR --reference-python PATH [--repeats 2]]
        [--floor-modes default max-autotune-no-cudagraphs] [--floor-calls 200]
        [--compile-update]

Ours: in-process, 1 SAC update per environment step, minibatch 256, 256x256 networks, the
per-step safety filter (closed-form assembly) and the GP estimate on every step. Each row first
fills the buffer with ``--warmup`` random steps (not timed; the GP is fitted on them, at most
512 points, at the last one), then times ``--steps`` steps with updates. Also reported: the
median SAC update (diff mode: both losses through the differentiable QP), the per-action
latency (policy + GP prediction + filter) and the update's arithmetic floor.

Reference (``--reference DIR``, the authors' Mod-RL-RCBF tree, e.g. exported from its git
repository outside this one): its own ``main.py``, unmodified, in its own venv, one subprocess
per row and repeat, timed from outside by benchmarks/_reference.py (read its docstring: it
stamps each entry into the environment's ``step`` and each GP refit by wrapping them, never
editing the reference's files). Prepare the venv once, outside this repository:

    python3 -m venv ref-venv
    ref-venv/bin/python -m pip install -c constraints.txt torch==2.13.0 qpth \
        gpytorch gym==0.25.2 comet_ml

(torch pinned by constraints.txt, a CPU wheel, as in scripts/setup.sh; gym 0.25 still has the
``Env.seed`` its main.py calls; comet_ml is imported by its main.py, never used here.) The
reference runs with ``--start_steps`` = ``--reference-warmup`` (default 400: its first GP refit,
on 200 points, falls on step 400, before the window) and evaluation off; it starts its SAC
updates once its buffer holds more than 256 transitions. Both sides run 1 thread
(torch.set_num_threads(1), OMP_NUM_THREADS=1). For each row the runs alternate, ours then the
reference, ``--repeats`` times; a row's steps/s is the median over the repeats.

Steady state: steps/s over the timed window with every GP refit's own time taken out (ours
refits at the end of the warm-up, outside the window anyway). Also from process CPU time
(time.process_time stamps on both sides: what each process itself consumed, though cores shared
with other work still slow it).
Amortized: the same with each side's refit, as measured in the run, spread over its schedule
while the GP learns: ours every LearnerConfig.gp_refit_interval steps, the reference every 400
steps (a data point every 2nd step, a refit every 200 points; during its first 100 episodes).

Own floor (the goal: a training step at most 1.25x it, measured in the same run): the SAC
update's best time (compiled, or eager where that is faster), plus the differentiable QP's
forward and backward where the mode trains through it, plus the action and the environment
step, each run's measured right after its timed window (host speed that drifts between minutes
then moves a run's step and its floor alike). The update: the whole update of the learner's
agent as it stands (networks, Adam moments, alpha), the one ``SACConfig.compile_update`` runs
(benchmarks/_update_floor.py), compiled with ``torch.compile(fullgraph=True)`` in each of
``--floor-modes`` and called ``--floor-calls`` times on minibatches from the buffer, as is
the eager ``SAC.update``, each in blocks of consecutive calls, the blocks of the ways
alternating (in its own block a way runs warm, as in training); its part of the floor is the
best call of the
fastest of them, the eager update included (its hidden-layer products run through oneDNN, the
compiled graph's through MKL: on a CPU where MKL takes its AVX2 path the eager update is the
faster). The first call of each mode compiles (its one-off cost is printed, never timed in) and
is checked against ``SAC.update`` from the same state on the same batch and noise draws (the
largest parameter difference is printed). The QP: 30 minibatches from the buffer, each timed 3
times in each of two ways that give the same actions and gradients: as both updates run the
layer (one forward of both halves side by side, the backward from the states' half) and with
the layer called apart for the critic target and the actor loss (forward at the next states
without gradient, forward and backward at the states), at the actor's samples, with the
memoised disturbance estimate; its part is the median over the minibatches of each one's best
call (its work depends on the minibatch: one with almost no row to correct runs far faster
than a typical one, and the step does typical ones; see ``typical_best``). The action
(policy + GP + filter) and the environment step (``env.step`` alone): medians over the timed
window. The step: 1000 / steady-state steps/s. Reported per row: step ms, floor ms and its
parts (medians over the runs), step / floor against the target (the median of the runs' own
ratios, each shown). Beyond the floor: the eager update (unless ``--compile-update``), storing
the transition and the GP's residual pair, drawing the minibatch (and its memoised disturbance
estimate), the model-based rollouts (``--model-based`` rows), Python between the parts.

``--compile-update``: ours trains with ``SACConfig.compile_update`` in every row (without a
safety layer in the losses the update the floor times; where the losses pass the layer, diff
and PVTOL modular with its envelope, the network parts compiled and the layer eager between
them); its first update, which compiles, is moved to the last warm-up step so that the compile
stays out of the window, and its time is printed ("first update, compiling"). Without it, ours
trains as configured by default (the eager update).

Mode map (ours <- reference ``--cbf_mode``): baseline <- baseline, modular <- mod,
diff <- full. Without ``--reference`` the comparison is skipped and its columns stay empty.
"""
from __future__ import annotations

# First: numpy's BLAS set up as in every rcbf_ros process (rcbf_ros/__init__.py).
import rcbf_ros  # noqa: F401  # isort: skip

import argparse
from dataclasses import replace
import os
from pathlib import Path
import statistics
import sys
import time

from _reference import (
    add_reference_arguments,
    amortized_rate,
    CBF_MODES,
    ENV_NAMES,
    reference_requested,
    ReferenceError,
    Refit,
    REFIT_EVERY_STEPS,
    run_reference,
    steady_rate,
)
from _update_floor import best_update
from _update_floor import BLOCK as FLOOR_BLOCK
import numpy as np
import torch

from rcbf_ros.learning.buffers import TransitionBatch
from rcbf_ros.learning.networks import linear
from rcbf_ros.training.agent import LearnerConfig, SafeLearner
from rcbf_ros.training.build import build_run, resolve_run, RunConfig

torch.set_num_threads(1)

TARGETS = {('unicycle', 'baseline'): 2.5, ('unicycle', 'modular'): 2.5,
           ('car_following', 'baseline'): 2.5, ('car_following', 'modular'): 2.5,
           ('pvtol', 'baseline'): 2.5, ('pvtol', 'modular'): 2.5,
           ('unicycle', 'diff'): 4.0, ('car_following', 'diff'): 6.0, ('pvtol', 'diff'): 6.0}
"""The project's speed goals: minimum steady-state steps/s of ours over the reference's."""
DIFFERENCES = (
    'What the two sides do differently. Per-step filter: ours solves the RCBF-QP exactly with '
    'a small active-set method (OSQP where it cannot certify its answer) on a closed-form '
    'constraint assembly (float64, one state, numpy); the reference '
    'assembles it in torch and solves it with qpth at batch 1 (eps 1e-4, maxIter 100000, '
    'notImprovedLim 10, rows normalised). GP: ours is one batch-independent exact GP over the '
    'state, at most 512 training points, refitted every 1000 steps; the reference fits one '
    'exact GPyTorch GP per state dimension (70 Adam iterations each) on up to 2000 points, '
    'refitted every 400 steps, here on 200 points (its first refit; later refits on more '
    'points cost it more, so the amortized ratio is a lower bound). Updates: both 1 SAC update '
    'per step, minibatch 256, 256x256 actor and twin critics, float32; ours with fused Adam, '
    "and the actor's gradient through each sample's minimum critic only (twin_minimum: one "
    "critic's backward instead of two). "
    'Differentiable layer (diff <- full): ours a batched active-set QP with its analytic '
    "backward, its barrier terms in closed form, and the GP estimate at the batch's states "
    'from a memo per stored transition, filled for every stored transition in one pass after '
    "each refit (here the refit on the warm-up's last step, outside the window) and for "
    "transitions stored since by the acting path's own estimate, so that an update predicts "
    "only the newest transition's next state when the update right after its step draws it "
    '(benchmarks/bench_training_full_buffer.py times the pass at a 200 000-transition '
    'buffer); the reference '
    'qpth on the batch of 256 (interior point, backward through its KKT factorisation) and its '
    'GP predicted on the batch, in the critic target and the actor loss. Modular '
    '(modular <- mod): on Unicycle and Cars the '
    'reference only clamps to the input box in the losses (no QP, its GP still predicts the '
    'batch), on PVTOL it solves its QP with the modular constraint set; ours uses no QP in '
    "the losses on Unicycle and Cars, and on PVTOL, as config/pvtol.yaml's "
    '`modular_envelope: true` asks, the differentiable QP of the envelope (the tilt, thrust and '
    'arena bands) in both losses. Buffer '
    'sampling: ours one preallocated table; the reference a Python list of tuples. BLAS: '
    "torch's own for both sides' networks; numpy's OpenBLAS with the kernels rcbf_ros picks "
    'from the CPU flags on both sides (the reference inherits OPENBLAS_CORETYPE from this '
    'process).')
"""Printed with the table."""
FLOOR_TARGET = 1.25
"""The project's speed goal against the floor: step time at most this multiple of it."""
FLOOR_MODES = ('default', 'max-autotune-no-cudagraphs', 'reduce-overhead')
DEFAULT_FLOOR_MODES = ('default', 'max-autotune-no-cudagraphs')
"""The modes tried unless ``--floor-modes`` says otherwise."""
"""torch.compile modes the floor's update may try (reduce-overhead's CUDA graphs do not apply
on CPU)."""


def matmul_gflops(threads: int, size: int = 256, repeats: int = 2000) -> float:
    """Best sustained float32 GFLOP/s of one size^3 product, the update's dominant operation:
    the faster of torch's own matmul (MKL) and the networks' hidden-layer product
    (:func:`rcbf_ros.learning.networks.linear`, oneDNN where torch has it)."""
    torch.set_num_threads(threads)
    a, b = torch.randn(size, size), torch.randn(size, size)
    rates = []
    for product in (lambda: a @ b, lambda: linear(a, b)):
        for _ in range(100):
            product()
        start = time.perf_counter()
        for _ in range(repeats):
            product()
        rates.append(2 * size ** 3 * repeats / (time.perf_counter() - start) / 1e9)
    return max(rates)


def update_gflop(obs_dim: int, n_u: int, hidden: int = 256, batch: int = 256) -> float:
    """Arithmetic of one eager SAC update (GFLOP), counting matmuls only: the least of the
    update's ways.

    Per sample, with A and C the multiply-adds of one actor and one critic forward pass, and
    A_1, C_1 those of their first layers (whose input gradient nothing needs): critic step =
    A (next action) + 2C (target critics) + 2C (critics) + 2C (their weight gradients) +
    2(C - C_1) (their input gradients, but the first layer's); actor step = A + 2C (critics) +
    C (the gradient to the action, through the critic of each sample's minimum:
    ``twin_minimum``) + A (actor weight gradients) + A - A_1 (its input gradients). Total
    4A - A_1 + 11C - 2C_1. The compiled update runs the action's gradient through both
    critics, C more.
    """
    actor_first = obs_dim * hidden
    critic_first = (obs_dim + n_u) * hidden
    actor = actor_first + hidden * hidden + hidden * 2 * n_u
    critic = critic_first + hidden * hidden + hidden
    multiply_adds = 4 * actor - actor_first + 11 * critic - 2 * critic_first
    return 2 * batch * multiply_adds / 1e9


QP_DRAWS, QP_REPEATS = 30, 3
"""The QP's part of the floor: minibatches drawn, calls of each way per minibatch."""


def qp_parts_ms(learner: SafeLearner, *, draws: int = QP_DRAWS,
                repeats: int = QP_REPEATS) -> float:
    """The differentiable QP as one update needs it, in ms: each of ``draws`` minibatches
    timed ``repeats`` times in each of two ways that give the same actions and gradients, its
    best call; the median over the minibatches (:func:`typical_best`). The two ways, which
    alternate: called apart, a forward pass at the next states (the critic target, no
    gradient) and a forward and backward pass at the states (the actor loss); as both
    updates run it, one forward pass of both halves side by side and the backward from the
    states' half. Each at the actor's samples, with the memoised disturbance estimate, on
    batches drawn from the learner's buffer."""
    sac, buffer = learner.sac, learner.buffer
    layer = sac.safety_layer
    assert layer is not None
    noise = torch.Generator().manual_seed(1)
    per_batch = []
    for _ in range(draws):
        index = buffer.sample_index(learner.config.batch_size)
        batch = TransitionBatch(*(t.to(sac.dtype) for t in buffer.gather(index)))
        estimate = buffer.predictions(index, version=learner.gp.version,
                                      predict=learner.disturbance)
        with torch.no_grad():
            following = sac.actor(batch.next_obs, generator=noise).action
            action = sac.actor(batch.obs, generator=noise).action
        action.requires_grad_(True)
        both = torch.cat([estimate.state, estimate.next_state])
        times = []
        for _ in range(repeats):
            action.grad = None
            start = time.perf_counter()
            with torch.no_grad():
                layer(batch.next_state, following,
                      (estimate.next_state[:, 0], estimate.next_state[:, 1]))
            safe = layer(batch.state, action, (estimate.state[:, 0], estimate.state[:, 1]))
            safe.backward(torch.ones_like(safe))
            times.append(time.perf_counter() - start)
            action.grad = None
            start = time.perf_counter()
            safe = layer(torch.cat([batch.state, batch.next_state]),
                         torch.cat([action, following]), (both[:, 0], both[:, 1]))
            safe[:len(action)].backward(torch.ones_like(action))
            times.append(time.perf_counter() - start)
        per_batch.append(times)
    return 1e3 * typical_best(per_batch)


def typical_best(per_batch: list[list[float]]) -> float:
    """The median over minibatches of each one's best time.

    The QP's work depends on the minibatch (how many rows it corrects, how many active-set
    steps they take): one with almost nothing to correct runs much faster than a typical one
    (Unicycle diff, measured: 1.17 ms against a median of 1.60 ms over 30 minibatches' best
    calls), and the training step does a typical one. Each minibatch's best call is its
    speed floor; the median over minibatches its typical work."""
    return statistics.median(min(times) for times in per_batch)


def update_floor(learner: SafeLearner, *, modes: list[str], calls: int) -> dict:
    """:func:`_update_floor.best_update` on 8 minibatches from the learner's buffer."""
    sac = learner.sac
    batches = [TransitionBatch(*(t.to(sac.dtype) for t in learner.buffer.gather(
        learner.buffer.sample_index(learner.config.batch_size)))) for _ in range(8)]
    return best_update(sac, batches, modes=modes, calls=calls)


def measure(system: str, mode: str, model_based: bool, steps: int, warmup: int,
            threads: int, floor_modes: list[str] | None = None,
            floor_calls: int = 200, compile_update: bool = False) -> dict:
    """Ours in-process: ``warmup`` untimed steps, then ``steps`` stamped steps; then, right
    after them, the floor's parts (see the module docstring; ``floor_modes`` None or empty:
    no floor), so that each run's step is held against a floor measured within seconds of
    it. ``compile_update``:
    train with ``SACConfig.compile_update`` (its first update, which compiles, then falls on
    the last warm-up step; ``first_update_s`` is its time)."""
    learner_cfg = LearnerConfig(mode=mode, model_based=model_based, seed=0,
                                start_steps=warmup, update_after=warmup, batch_size=256,
                                gp_refit_interval=warmup, rollout_interval=100)
    run = resolve_run(RunConfig(system=system, episodes=1, max_steps=10 ** 6,
                                record_bag=False, out_dir='/tmp/bench_training',
                                compile_filter=True, learner=learner_cfg))
    if compile_update:
        run = replace(run, learner=replace(
            run.learner, update_after=warmup - 1,
            sac=replace(run.learner.sac, compile_update=True)))
    env, filt, learner, _ = build_run(run)
    torch.set_num_threads(threads)
    obs, info = env.reset(seed=0)
    state = info['state']
    action_times, update_times, filter_times, env_times = [], [], [], []
    stamps, cpu_stamps, refits = [], [], []
    first_update: list[float] = []
    fit = learner.gp.fit

    def timed_fit() -> None:
        start, cpu = time.perf_counter(), time.process_time()
        fit()
        refits.append(Refit(after_step=len(stamps), seconds=time.perf_counter() - start,
                            cpu_seconds=time.process_time() - cpu,
                            points=int(learner.gp.num_data)))

    learner.gp.fit = timed_fit

    def one_step(timed: bool) -> None:
        nonlocal obs, state
        if timed:
            stamps.append(time.perf_counter())
            cpu_stamps.append(time.process_time())
        t0 = time.perf_counter()
        proposal = learner.propose(obs, state)
        t1 = time.perf_counter()
        u_safe = proposal.u_proposed
        if filt is not None:
            u_safe = filt.filter(state, proposal.u_proposed, proposal.disturbance_mean,
                                 proposal.disturbance_std).u_safe
        t2 = time.perf_counter()
        next_obs, reward, terminated, truncated, info = env.step(u_safe)
        t_env = time.perf_counter()
        learner.observe(obs=obs, state=state, u_rl=proposal.u_rl, u_safe=u_safe, reward=reward,
                        next_obs=next_obs, next_state=info['state'], terminated=terminated)
        t3 = time.perf_counter()
        metrics = learner.after_step()
        t4 = time.perf_counter()
        if metrics and not first_update:
            first_update.append(t4 - t3)
        if timed:
            action_times.append(t2 - t0)
            filter_times.append(t2 - t1)
            env_times.append(t_env - t2)
            if metrics:
                update_times.append(t4 - t3)
        obs, state = next_obs, info['state']
        if terminated or truncated:
            obs, info = env.reset()
            state = info['state']

    for _ in range(warmup):
        one_step(False)
    warmup_refits = list(refits)
    refits.clear()
    for _ in range(steps):
        one_step(True)
    stamps.append(time.perf_counter())
    cpu_stamps.append(time.process_time())
    floor = (update_floor(learner, modes=floor_modes, calls=floor_calls) if floor_modes
             else None)
    return {
        'floor': floor,
        'qp_ms': (qp_parts_ms(learner) if floor is not None
                  and learner.sac.through_layer else 0.0),
        'env_ms': 1e3 * statistics.median(env_times),
        'steps_per_s': steady_rate(stamps=stamps, refits=refits, first=0),
        'cpu_steps_per_s': steady_rate(stamps=cpu_stamps, refits=refits, first=0, cpu=True),
        'refit_s': statistics.median(r.seconds for r in warmup_refits + refits),
        'update_ms': 1e3 * statistics.median(update_times) if update_times else float('nan'),
        'action_ms': 1e3 * statistics.median(action_times),
        'filter_ms': 1e3 * statistics.median(filter_times),
        'gflop': update_gflop(env.observation_space.shape[0], learner.system.n_u),
        'first_update_s': first_update[0] if first_update else float('nan'),
    }


def measure_reference(directory: Path, python: Path, system: str, mode: str, steps: int,
                      warmup: int) -> dict:
    """The reference's row: ``run_reference`` reduced to the same quantities as ours."""
    out = run_reference(directory=directory, python=python, system=system, mode=mode,
                        warmup=warmup, steps=steps)
    refits = out['refits']
    if not refits:
        raise ReferenceError(f'reference {system}/{mode}: no GP refit within {warmup} steps')
    filter_ms = [1e3 * wall for wall, _ in out['filter_calls'][warmup:]]
    return {
        'steps_per_s': steady_rate(stamps=out['stamps'], refits=refits, first=warmup),
        'cpu_steps_per_s': steady_rate(stamps=out['cpu_stamps'], refits=refits, first=warmup,
                                       cpu=True),
        'refit_s': statistics.median(r.seconds for r in refits),
        'refit_points': sorted({r.points for r in refits}),
        'update_ms': 1e3 * statistics.median(out['updates']) if out['updates'] else float('nan'),
        'filter_ms': statistics.median(filter_ms) if filter_ms else float('nan'),
    }


def _median(runs: list[dict], key: str) -> float:
    return statistics.median(r[key] for r in runs)


def _ratio(ours: list[dict], ref: list[dict], key: str) -> float:
    return _median(ours, key) / _median(ref, key)


def comparison_row(system: str, mode: str, ours: list[dict], ref: list[dict]) -> str:
    """One row of the comparison table (reference columns empty without reference runs)."""
    head = f'| {system} | {mode} <- {CBF_MODES[mode]} | {_median(ours, "steps_per_s"):.1f} '
    target = TARGETS.get((system, mode))
    target_text = f'>= {target:g}x' if target else ''
    if not ref:
        return head + f'| | | | | | {target_text} | |'
    ratio = _ratio(ours, ref, 'steps_per_s')
    per_repeat = [o['steps_per_s'] / r['steps_per_s'] for o, r in zip(ours, ref)]
    cpu_ratio = _ratio(ours, ref, 'cpu_steps_per_s')
    interval = LearnerConfig().gp_refit_interval
    ours_am = statistics.median(amortized_rate(steps_per_s=o['steps_per_s'],
                                               refit_s=o['refit_s'], every_steps=interval)
                                for o in ours)
    ref_am = statistics.median(amortized_rate(steps_per_s=r['steps_per_s'],
                                              refit_s=r['refit_s'],
                                              every_steps=REFIT_EVERY_STEPS) for r in ref)
    met = '' if target is None else ('met' if ratio >= target else 'not met')
    return (head + f'| {_median(ref, "steps_per_s"):.1f} | {ratio:.1f}x '
            f'({", ".join(f"{x:.1f}" for x in per_repeat)}) | {cpu_ratio:.1f}x '
            f'| {ours_am / ref_am:.1f}x | {_median(ref, "refit_s"):.1f} '
            f'| {target_text} | {met} |')


def floor_row(system: str, name: str, ours: list[dict]) -> str:
    """One row of the own-floor table: each run's step against the floor measured right
    after it; the ratio is the median of those per-run ratios (each shown), the other
    columns medians over the runs."""
    updates = [best_update_ms(run['floor'])[1] for run in ours]
    floors = [update + run['qp_ms'] + run['action_ms'] + run['env_ms']
              for update, run in zip(updates, ours)]
    ratios = [1e3 / run['steps_per_s'] / floor for run, floor in zip(ours, floors)]
    ratio = statistics.median(ratios)
    per_run = f' ({", ".join(f"{r:.2f}" for r in ratios)})' if len(ratios) > 1 else ''
    return (f'| {system} | {name} | {1e3 / _median(ours, "steps_per_s"):.2f} '
            f'| {statistics.median(floors):.2f} | {statistics.median(updates):.2f} '
            f'| {_median(ours, "qp_ms"):.2f} | {_median(ours, "action_ms"):.2f} '
            f'| {_median(ours, "env_ms"):.2f} | {ratio:.2f}x{per_run} '
            f'| <= {FLOOR_TARGET:g}x | {"met" if ratio <= FLOOR_TARGET else "not met"} |')


def best_update_ms(floor: dict) -> tuple[str, float]:
    """The way of running the update (eager or a compile mode) with the shortest best time,
    and that time (ms)."""
    best = {way: time for way, (time, _) in floor['variants'].items()}
    way = min(best, key=best.__getitem__)
    return way, best[way]


def floor_reading(update_floors: dict[str, list[dict]], calls: int) -> str:
    """The floor's method and the update measurements behind it, per system: each way's
    best and median call, as medians over the system's measurements (one after each run)."""
    parts = []
    for key, measured in update_floors.items():
        system, threads = key.split('/')
        names = list(measured[0]['variants'])
        variants = '; '.join(
            f'{name} {statistics.median(m["variants"][name][0] for m in measured):.2f} '
            f'(median {statistics.median(m["variants"][name][1] for m in measured):.2f})'
            for name in names)
        modes = list(measured[0]['compile_s'])
        compile_s = ', '.join(f'{mode} {max(m["compile_s"][mode] for m in measured):.0f} s'
                              for mode in modes)
        agreement = max(max(m['agreement'].values()) for m in measured)
        count = len(measured)
        parts.append(f'{system} ({threads} thread{"s" if threads != "1" else ""}): update ms, '
                     f'best of {calls} calls, median over {count} measurement'
                     f'{"s" if count != 1 else ""}: {variants}; one-off compile, longest: '
                     f"{compile_s} (torch's compile cache on disk shortens it after a first "
                     'run); largest parameter difference to SAC.update after one step '
                     f'{agreement:.1e}.')
    return (
        "Floor: the SAC update's best time, the faster of the eager SAC.update and the "
        'whole update as one function compiled with torch.compile(fullgraph=True) in each mode '
        "tried (the fastest way's best call, each way timed in blocks of "
        f"{FLOOR_BLOCK} consecutive calls, "
        "the ways' blocks alternating; benchmarks/_update_floor.py; the compile is not "
        'timed in; the eager update is the faster where its hidden-layer products through '
        'oneDNN outrun the MKL products of the compiled graph), plus, where '
        'the mode trains through the differentiable QP (diff; PVTOL modular with its envelope '
        'layer), the QP as one update runs it (forward at the next states, forward and '
        f'backward at the states, as two calls or as one of both halves; each of {QP_DRAWS} '
        f'minibatches from the buffer timed {QP_REPEATS} times each way, its best call, the '
        "median over the minibatches: the QP's work depends on the minibatch, how many rows it "
        'corrects), '
        'plus the action '
        '(policy + GP + filter) and the environment step (each the median over the timed '
        "window), measured after each run's window and held against that run's step; "
        'step / floor is the median of those ratios (per run in brackets). "step ms" is the '
        "steady-state step (1000 / steps/s): a mean over the window, where the update's part "
        "of the floor is a best call (the same calls' median lies above it by the spread of "
        "the host's speed: both are listed below). What the step does "
        'beyond the floor: the eager update instead of the compiled one (unless '
        "--compile-update; the eager actor step runs each sample's action gradient through "
        "the critic of its minimum only, the compiled one through both), storing the "
        'transition and the GP pair, drawing the minibatch and its memoised disturbance '
        'estimate, Python between the parts. Target: step / floor <= '
        f'{FLOOR_TARGET:g}x. ' + ' '.join(parts))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--steps', type=int, default=200, help='timed steps per run')
    parser.add_argument('--warmup', type=int, default=600, help='our untimed steps')
    parser.add_argument('--systems', nargs='*', default=['unicycle', 'car_following', 'pvtol'])
    parser.add_argument('--modes', nargs='*', default=['baseline', 'modular', 'diff'],
                        choices=['baseline', 'modular', 'diff'])
    parser.add_argument('--rows', nargs='*', default=None, metavar='SYSTEM/MODE',
                        help='explicit rows (e.g. unicycle/diff); replaces --systems x --modes')
    parser.add_argument('--model-based', action='store_true',
                        help='add our diff + model_based rows (no reference counterpart)')
    parser.add_argument('--threads', type=int, nargs='*', default=[1])
    parser.add_argument('--repeats', type=int, default=2,
                        help='alternating runs per side and row (with --reference)')
    add_reference_arguments(parser)
    parser.add_argument('--reference-warmup', type=int, default=400,
                        help="the reference's untimed steps (its first GP refit is at 400)")
    parser.add_argument('--floor-modes', nargs='*',
                        default=list(DEFAULT_FLOOR_MODES),
                        choices=list(FLOOR_MODES),
                        help="torch.compile modes tried for the floor's update (none: no "
                             'floor)')
    parser.add_argument('--floor-calls', type=int, default=200,
                        help="timed calls per variant of the floor's update")
    parser.add_argument('--compile-update', action='store_true',
                        help='ours trains with SACConfig.compile_update (every row)')
    parser.add_argument('--no-write', action='store_true')
    args = parser.parse_args()
    if min(args.steps, args.warmup, args.repeats, args.floor_calls) < 1:
        parser.error('--steps, --warmup, --repeats and --floor-calls must be >= 1')
    if args.compile_update and args.warmup <= 256:
        parser.error('--compile-update: --warmup must exceed the batch size (256), so that '
                     'the compiling first update falls in the warm-up')
    if args.rows is None:
        rows = [(system, mode) for system in args.systems for mode in args.modes]
    else:
        rows = [tuple(row.split('/', 1)) for row in args.rows]
        for row, pair in zip(args.rows, rows):
            if len(pair) != 2 or pair[1] not in CBF_MODES:
                parser.error(f'--rows: {row!r} is not SYSTEM/MODE with MODE one of '
                             f'{", ".join(CBF_MODES)}')
        args.systems = list(dict.fromkeys(system for system, _ in rows))
    for system in args.systems:
        if system not in ENV_NAMES:
            parser.error(f'--systems: unknown system {system!r}')
    reference = reference_requested(parser, args, minimums=[
        (args.reference_warmup, 400, '--reference-warmup: at least 400 (its first GP refit)')])
    configs = [(system, mode, False) for system, mode in rows]
    if args.model_based:
        configs += [(s, 'diff', True) for s in args.systems if s in ('unicycle', 'pvtol')]
    load_before = os.getloadavg()
    peak = {threads: matmul_gflops(threads) for threads in args.threads}
    compare = ['| system | mode, ours <- reference | ours steps/s | reference steps/s '
               '| ours / reference (per repeat) | CPU-time ratio | ratio, refits amortized '
               '| reference refit s | target | |',
               '|---|---|---:|---:|---:|---:|---:|---:|---|---|']
    detail = ['| system | mode | threads | steps/s | median update ms | update arithmetic ms '
              '| action ms (policy+GP+filter) | filter ms | reference update ms '
              '| reference filter ms |', '|---|---|---:|---:|---:|---:|---:|---:|---:|---:|']
    own_floor = ['| system | mode | step ms | floor ms | update, best ms '
                 '| diff. QP fwd+bwd ms | action ms | env step ms | step / floor | target | |',
                 '|---|---|---:|---:|---:|---:|---:|---:|---:|---|---|']
    floors = {}
    first_updates: list[str] = []
    update_floors: dict[str, list[dict]] = {}
    row_loads = []
    try:
        for system, mode, mb in configs:
            for threads in args.threads:
                paired = reference and threads == 1 and not mb
                ours, ref = [], []
                for _ in range(args.repeats if paired else 1):
                    ours.append(measure(system, mode, mb, args.steps, args.warmup, threads,
                                        floor_modes=args.floor_modes,
                                        floor_calls=args.floor_calls,
                                        compile_update=args.compile_update))
                    if ours[-1]['floor'] is not None:
                        update_floors.setdefault(f'{system}/{threads}', []).append(
                            ours[-1]['floor'])
                    torch.set_num_threads(1)
                    if paired:
                        ref.append(measure_reference(args.reference, args.reference_python,
                                                     system, mode, args.steps,
                                                     args.reference_warmup))
                name = f"{mode}{' + model_based' if mb else ''}"
                if args.compile_update:
                    first_updates.append(f'{system}/{name} ({threads} thread'
                                         f'{"s" if threads != 1 else ""}) '
                                         f'{_median(ours, "first_update_s"):.1f} s')
                    print(f'first update, compiling: {first_updates[-1]}', flush=True)
                floor_ms = 1e3 * ours[0]['gflop'] / peak[threads]
                floors[(system, threads)] = (ours[0]['gflop'], floor_ms)
                ref_cols = (f'| {_median(ref, "update_ms"):.1f} '
                            f'| {_median(ref, "filter_ms"):.2f} |' if ref else '| | |')
                row = (f'| {system} | {name} | {threads} | {_median(ours, "steps_per_s"):.1f} '
                       f'| {_median(ours, "update_ms"):.1f} | {floor_ms:.1f} '
                       f'| {_median(ours, "action_ms"):.2f} | {_median(ours, "filter_ms"):.2f} '
                       + ref_cols)
                detail.append(row)
                print(row, flush=True)
                if ours[0]['floor'] is not None:
                    own_floor.append(floor_row(system, name, ours))
                    print(own_floor[-1], flush=True)
                if threads == 1 and not mb:
                    compare.append(comparison_row(system, mode, ours, ref))
                    print(compare[-1], flush=True)
                row_loads.append(os.getloadavg()[0])
    except ReferenceError as exc:
        sys.exit(f'bench_training: {exc}')
    load_after = os.getloadavg()
    from _results import load_before_after
    load = (load_before_after(load_before, load_after) + '; 1 min after each row '
            f'{min(row_loads):.1f} to {max(row_loads):.1f} (2 cores). On a shared '
            "machine other work stretches both sides' wall time; the alternation spreads it "
            'over both, the per-repeat ratios show how much it moved them, and the CPU-time '
            'ratio is the check (it is not immune either: shared cores and caches slow the '
            'CPU time too).')
    peaks = ', '.join(f'{peak[t]:.0f} GFLOP/s with {t} thread{"s" if t > 1 else ""}'
                      for t in args.threads)
    unicycle = [(t, *floors[('unicycle', t)]) for t in args.threads if ('unicycle', t) in floors]
    bound = ''.join(
        f' Unicycle, {t} thread{"s" if t > 1 else ""}: {gflop:.2f} GFLOP per update, so at '
        f'least {floor:.1f} ms, at most {1e3 / floor:.0f} updates/s even with nothing else '
        'to do.' for t, gflop, floor in unicycle)
    reading = (
        'Reading: "update arithmetic" is the update\'s matmul arithmetic (counted from the '
        'network sizes, see `update_gflop`) at the best float32 matmul rate measured in this run '
        f"({peaks}; one 256x256x256 product, the faster of torch's matmul and the networks' "
        f'hidden-layer product). It bounds every mode from below.{bound} The diff '
        'rows add the differentiable QP (one batched solve of both halves and its backward) '
        'on top. '
        'bfloat16 autocast is not used: it keeps Q values to ~3 significant digits.')
    floor_text = floor_reading(update_floors, args.floor_calls) if update_floors else (
        'Floor not measured (--floor-modes with no mode).')
    if reference:
        verdict = ('Target: ours / reference steady-state steps/s at least the "target" '
                   'column (the project\'s speed goals); "met" is judged on the wall-clock '
                   'median ratio.')
    else:
        verdict = 'Reference comparison skipped (no --reference DIR): its columns are empty.'
    selection = (f'--rows {" ".join(args.rows)}' if args.rows is not None else
                 f'--systems {" ".join(args.systems)} --modes {" ".join(args.modes)}')
    command = (f'python benchmarks/bench_training.py --steps {args.steps} --warmup {args.warmup}'
               f' --repeats {args.repeats} {selection}'
               + (' --model-based' if args.model_based else '')
               + (' --compile-update' if args.compile_update else '')
               + (f' --floor-modes {" ".join(args.floor_modes)}'
                  if list(args.floor_modes) != list(DEFAULT_FLOOR_MODES) else '')
               + (' --reference <Mod-RL-RCBF checkout> --reference-python <its venv>/bin/python'
                  if reference else ''))
    text = '\n'.join(['Ours against the reference, 1 thread each, steady state:', '',
                      *compare, '', verdict, '', load, '', DIFFERENCES, '',
                      'Ours in detail (reference columns: median of its repeats):', '',
                      *detail, '', reading, '',
                      'Ours against its own floor, measured in the same run:', '',
                      *own_floor, '', floor_text]
                     + (['', 'First update, compiling (in the warm-up, not timed in; '
                         "torch's compile cache on disk shortens it after a first run): "
                         + ', '.join(first_updates) + '.'] if first_updates else []))
    print(text)
    if not args.no_write:
        from _results import machine_line, write_section
        title = 'Training speed' + (', compiled update' if args.compile_update else '')
        write_section(title, (
            f'Command: `{command}`. ' + machine_line() + '. Each row alternates a run of ours '
            f'and of the reference, {args.repeats if reference else 1} time(s); ours times '
            f'{args.steps} steps after {args.warmup} warm-up steps, the reference {args.steps} '
            f'steps after {args.reference_warmup}. Method and venv: the docstrings of '
            'benchmarks/bench_training.py and benchmarks/_reference.py.\n\n' + text))


if __name__ == '__main__':
    np.set_printoptions(precision=3)
    main()
