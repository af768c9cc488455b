"""Training speed at a full replay buffer: the mean training step over a whole GP refit period
with 200,000 stored transitions, next to the same period right after the first GP fit.

    python benchmarks/bench_training_full_buffer.py [--rows unicycle/diff ...]
        [--buffer 200000] [--refit-interval 1000] [--repeats 1] [--ways pass demand]
        [--quick] [--no-write]

Ours, in-process, as benchmarks/bench_training.py runs it (1 thread, 1 SAC update per step,
minibatch 256, 256x256 networks, the per-step safety filter and GP estimate), with the
learner's own schedule: a GP refit every ``--refit-interval`` (R) steps, the one at step R
the first. Per row and way, one process:

1. first-fit period: R - 1 steps of random actions (not timed), then R timed steps, the first
   of which refits the GP (on the R transitions stored) and starts the SAC updates; the mean
   step over these R steps, the refit included, is the "first-fit" figure;
2. full buffer: the buffer's 2R - 1 transitions, a real run's so far, are tiled until the
   buffer holds ``--buffer`` transitions, and the GP's residual pairs likewise (a real run's
   GP keeps every pair: its refit selects its at most 512 training points from all of them);
   the learner keeps its networks and schedule, so its next step refits; then R timed steps,
   the "full-buffer" figure, the same mean, the refit included.

Tiled data are distributed as a run's early states, not as a late run's wider ones; what the
step's cost depends on is the count of stored transitions (the GP's prediction costs the same
per state anywhere), which is the quantity under test.

Ways (``--ways``), each row measuring them one after the other, alternating:
``pass``, the learner as it is: after each refit, one pass predicts the new GP's estimate at
every stored transition into the buffer's memo (``ReplayBuffer.fill_predictions``); ``demand``,
that pass switched off: the losses predict each minibatch's stale states on demand, as before
the pass existed. Only modes whose losses see the action through a layer predict (diff; PVTOL
modular with its envelope); elsewhere the ways run the same code, and only the first runs.

Reported per row and way: both figures (ms per step), their ratio against the target
(full-buffer step at most ``TARGET`` x the first-fit step), the same ratio of the process's CPU
time over each period (steadier than the wall clock on a machine other work shares), the GP
refit's time in each period (at the full buffer also its part selecting the training points
among all pairs), the pass's time, the states the GP predicted for the losses per step of
the period, and the hours one seed's training at the ``paper`` budget would take on the
machine (``paper_hours``: its episodes at full length, the step growing linearly from the
first-fit figure to the full-buffer one as the buffer fills; evaluation not included).
``--quick``: R = 40, a 200-transition buffer, minibatch 16, unicycle/diff only unless
``--rows`` says otherwise: a smoke test in seconds, no figure worth reading.
"""
from __future__ import annotations

# First: numpy's BLAS set up as in every rcbf_ros process (rcbf_ros/__init__.py).
import rcbf_ros  # noqa: F401  # isort: skip

import argparse
import math
import os
import statistics
import time

import numpy as np
import torch

from rcbf_ros.experiments.definitions import BUDGETS
from rcbf_ros.training.agent import LearnerConfig, SafeLearner
from rcbf_ros.training.build import build_run, resolve_run, RunConfig

torch.set_num_threads(1)

TARGET = 1.2
"""The goal: the full buffer's mean step at most this multiple of the first-fit period's."""
SYSTEMS = ('unicycle', 'car_following', 'pvtol')
MODES = ('baseline', 'modular', 'diff')
WAYS = ('pass', 'demand')
QUICK = {'buffer': 200, 'refit_interval': 40, 'batch_size': 16, 'rows': ['unicycle/diff']}


class Period:
    """Stamps of one timed period of steps, with the refit, the pass and the predictions in
    it."""

    def __init__(self) -> None:
        self.stamps: list[float] = []
        self.cpu_stamps: list[float] = []
        self.refit_s = 0.0
        self.subset_s = 0.0
        self.fill_s = 0.0
        self.predicted = 0

    def mean_step_ms(self) -> float:
        return 1e3 * (self.stamps[-1] - self.stamps[0]) / (len(self.stamps) - 1)

    def mean_step_cpu_ms(self) -> float:
        """The mean step in the process's CPU time."""
        return 1e3 * (self.cpu_stamps[-1] - self.cpu_stamps[0]) / (len(self.cpu_stamps) - 1)


def run_hours(*, first_ms: float, full_ms: float, steps: int, capacity: int) -> float:
    """Hours of a run of ``steps`` environment steps whose buffer holds ``capacity`` at most,
    the step costing ``first_ms`` near an empty buffer and ``full_ms`` at a full one, linear
    in the stored count in between (the parts that grow with it, the GP's prediction at every
    stored transition and its selection among every pair, are linear in it): the stored
    count is min(t, capacity) at step t."""
    if steps <= 0 or capacity <= 0:
        raise ValueError('steps and capacity must be > 0')
    if steps <= capacity:
        fullness = steps / (2 * capacity)
    else:
        fullness = (capacity / 2 + steps - capacity) / steps
    return steps * (first_ms + (full_ms - first_ms) * fullness) / 1e3 / 3600


def build(system: str, mode: str, *, buffer: int, refit_interval: int,
          batch_size: int) -> tuple:
    """The in-process run of ``system``/``mode`` with the schedule above: (env, filter,
    learner)."""
    config = LearnerConfig(mode=mode, seed=0, start_steps=refit_interval,
                           update_after=refit_interval, batch_size=batch_size,
                           gp_refit_interval=refit_interval, buffer_size=buffer)
    run = resolve_run(RunConfig(system=system, episodes=1, record_bag=False,
                                out_dir='/tmp/bench_training_full_buffer',
                                compile_filter=True, learner=config))
    env, filt, learner, _ = build_run(run)
    return env, filt, learner


def fill_to(learner: SafeLearner, size: int) -> None:
    """Tile the buffer's transitions and the GP's residual pairs until the buffer holds
    ``size`` transitions and the GP as many pairs (a run's GP keeps one per step)."""
    buffer, gp = learner.buffer, learner.gp
    stored = buffer.gather(torch.arange(len(buffer)))
    missing = size - len(buffer)
    if missing > 0:
        tiles = math.ceil(missing / len(buffer))
        rows = {name: torch.cat([value] * tiles)[:missing]
                for name, value in stored._asdict().items()}
        buffer.add(**rows)
    pairs = gp.state_dict()
    x, y = pairs['x'], pairs['y']
    missing = size - gp.num_data
    if missing > 0:
        tiles = math.ceil(missing / len(x))
        gp.add(torch.cat([x] * tiles)[:missing], torch.cat([y] * tiles)[:missing])


def measure(system: str, mode: str, way: str, *, buffer: int, refit_interval: int,
            batch_size: int = 256) -> dict:
    """Both periods of one row and way in one process (module docstring)."""
    env, filt, learner = build(system, mode, buffer=buffer, refit_interval=refit_interval,
                               batch_size=batch_size)
    torch.set_num_threads(1)
    period: Period | None = None
    fit, fill, predict = learner.gp.fit, learner._fill_memo, learner.disturbance
    select = learner.gp.select_training_subset

    def timed_select() -> torch.Tensor:
        start = time.perf_counter()
        chosen = select()
        if period is not None:
            period.subset_s += time.perf_counter() - start
        return chosen

    def timed_fit() -> None:
        start = time.perf_counter()
        fit()
        if period is not None:
            period.refit_s += time.perf_counter() - start

    def timed_fill() -> None:
        if way == 'demand':
            return
        start = time.perf_counter()
        fill()
        if period is not None:
            period.fill_s += time.perf_counter() - start

    def counted_predict(x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        if period is not None:
            period.predicted += x.shape[0]
        return predict(x)

    learner.gp.fit, learner._fill_memo = timed_fit, timed_fill
    learner.gp.select_training_subset = timed_select
    learner.disturbance = counted_predict
    obs, info = env.reset(seed=0)
    state = info['state']

    def one_step() -> None:
        nonlocal obs, state
        proposal = learner.propose(obs, state)
        u_safe = proposal.u_proposed
        if filt is not None:
            u_safe = filt.filter(state, proposal.u_proposed, proposal.disturbance_mean,
                                 proposal.disturbance_std).u_safe
        next_obs, reward, terminated, truncated, info = env.step(u_safe)
        learner.observe(obs=obs, state=state, u_rl=proposal.u_rl, u_safe=u_safe, reward=reward,
                        next_obs=next_obs, next_state=info['state'], terminated=terminated)
        learner.after_step()
        obs, state = next_obs, info['state']
        if terminated or truncated:
            obs, info = env.reset()
            state = info['state']

    def timed_period() -> Period:
        nonlocal period
        period = Period()
        for _ in range(refit_interval):
            period.stamps.append(time.perf_counter())
            period.cpu_stamps.append(time.process_time())
            one_step()
        period.stamps.append(time.perf_counter())
        period.cpu_stamps.append(time.process_time())
        done, period = period, None
        return done

    for _ in range(refit_interval - 1):
        one_step()
    first = timed_period()
    fill_to(learner, buffer)
    assert learner.env_steps % refit_interval == refit_interval - 1
    full = timed_period()
    return {'first': first, 'full': full, 'stored': (refit_interval, len(learner.buffer)),
            'through_layer': learner.sac.through_layer, 'episode_steps': int(env.max_steps)}


def row_text(system: str, mode: str, way: str, runs: list[dict], *, capacity: int) -> str:
    """One table row: medians over the repeats."""
    def median(period: str, value) -> float:
        return statistics.median(value(run[period]) for run in runs)

    first = median('first', Period.mean_step_ms)
    full = median('full', Period.mean_step_ms)
    ratios = [run['full'].mean_step_ms() / run['first'].mean_step_ms() for run in runs]
    ratio = statistics.median(ratios)
    per_run = f' ({", ".join(f"{r:.2f}" for r in ratios)})' if len(ratios) > 1 else ''
    cpu_ratio = statistics.median(run['full'].mean_step_cpu_ms() / run['first'].mean_step_cpu_ms()
                                  for run in runs)
    steps = len(runs[0]['first'].stamps) - 1
    return (f'| {system} | {mode} | {way} | {first:.2f} | {full:.2f} | {ratio:.2f}x{per_run} '
            f'| {cpu_ratio:.2f}x '
            f'| {median("first", lambda p: p.refit_s):.2f} '
            f'| {median("full", lambda p: p.refit_s):.2f} '
            f'({median("full", lambda p: p.subset_s):.2f}) '
            f'| {median("first", lambda p: p.fill_s):.2f} '
            f'| {median("full", lambda p: p.fill_s):.2f} '
            f'| {median("first", lambda p: p.predicted) / steps:.0f} '
            f'| {median("full", lambda p: p.predicted) / steps:.0f} '
            f'| <= {TARGET:g}x | {"met" if ratio <= TARGET else "not met"} '
            f'| {paper_hours(system, runs[0]["episode_steps"], first, full, capacity):.1f} |')


def paper_hours(system: str, episode_steps: int, first_ms: float, full_ms: float,
                capacity: int) -> float:
    """:func:`run_hours` of one seed at the ``paper`` budget: its episodes of the system,
    each run to its full length (an episode ended at the goal is shorter)."""
    steps = BUDGETS['paper'].episodes[system] * episode_steps
    return run_hours(first_ms=first_ms, full_ms=full_ms, steps=steps, capacity=capacity)


def main(argv: list[str] | None = None) -> str:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--rows', nargs='*', default=None, metavar='SYSTEM/MODE',
                        help='rows to run (default: every system and mode)')
    parser.add_argument('--buffer', type=int, default=None,
                        help='stored transitions of the full buffer (default 200000)')
    parser.add_argument('--refit-interval', type=int, default=None,
                        help="steps between GP refits, R (default LearnerConfig's, 1000)")
    parser.add_argument('--repeats', type=int, default=1, help='runs per row and way')
    parser.add_argument('--ways', nargs='*', default=list(WAYS), choices=list(WAYS))
    parser.add_argument('--quick', action='store_true',
                        help='a smoke test: R = 40, 200 transitions, minibatch 16, unicycle/diff')
    parser.add_argument('--no-write', action='store_true')
    args = parser.parse_args(argv)
    defaults = QUICK if args.quick else {'buffer': 200_000,
                                         'refit_interval': LearnerConfig().gp_refit_interval,
                                         'rows': [f'{s}/{m}' for s in SYSTEMS for m in MODES]}
    buffer = args.buffer or defaults['buffer']
    refit_interval = args.refit_interval or defaults['refit_interval']
    if refit_interval < 20 or args.repeats < 1 or not args.ways:
        parser.error('--refit-interval must be >= 20, --repeats >= 1, --ways not empty')
    if buffer < 2 * refit_interval:
        parser.error(f'--buffer must be at least 2 x --refit-interval ({2 * refit_interval})')
    rows = []
    for row in args.rows or defaults['rows']:
        system, _, mode = row.partition('/')
        if system not in SYSTEMS or mode not in MODES:
            parser.error(f'--rows: {row!r} is not SYSTEM/MODE with SYSTEM one of '
                         f'{", ".join(SYSTEMS)} and MODE one of {", ".join(MODES)}')
        rows.append((system, mode))
    load_before = os.getloadavg()
    table = ['| system | mode | way | first-fit step ms | full-buffer step ms '
             '| full / first-fit | the same, CPU time '
             '| GP refit s, first | GP refit s, full (subset selection) '
             '| pass s, first '
             '| pass s, full | states predicted per step, first | the same, full | target '
             '| | paper run h |',
             '|---|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|---|---:|']
    for system, mode in rows:
        runs: dict[str, list[dict]] = {way: [] for way in args.ways}
        for _ in range(args.repeats):
            for way in args.ways:
                runs[way].append(measure(system, mode, way, buffer=buffer,
                                         refit_interval=refit_interval,
                                         batch_size=defaults.get('batch_size', 256)))
                if not runs[way][-1]['through_layer']:
                    break  # no layer in the losses: every way runs the same code
        for way in args.ways:
            if not runs[way]:
                continue
            table.append(row_text(system, mode, way, runs[way], capacity=buffer))
            print(table[-1], flush=True)
    command = ('python benchmarks/bench_training_full_buffer.py'
               + (' --quick' if args.quick else '')
               + f' --buffer {buffer} --refit-interval {refit_interval}'
               + f' --repeats {args.repeats} --ways {" ".join(args.ways)}'
               + f' --rows {" ".join(f"{s}/{m}" for s, m in rows)}')
    from _results import publish_table
    return publish_table('Training speed at a full buffer', script='bench_training_full_buffer.py',
                         command=command, table=table, load_before=load_before,
                         write=not args.no_write)


if __name__ == '__main__':
    np.set_printoptions(precision=3)
    main()
