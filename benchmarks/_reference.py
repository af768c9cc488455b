"""Times the authors' SAC-RCBF code (Mod-RL-RCBF) from outside, unmodified, in its own venv.

Two halves in one file:

- the driver, run as a script by the reference's interpreter (``--reference-python``); it
  imports nothing from rcbf_ros. It runs the reference's own ``main.py`` (``runpy``, as
  ``python main.py ...`` would, in a temporary working directory so its output folder goes
  there) and only wraps callables from outside, without editing any of its files:

  * each environment's ``step`` (``build_env.build_env`` is replaced in its module before
    ``main.py`` star-imports it, and wraps the step of each environment it builds): a stamp on
    entry, so consecutive stamps bracket
    one whole iteration of its training loop (SAC updates, action with GP + QP, env step,
    buffer push, GP data append, and a GP refit when one falls there); after the requested
    number of steps the wrapper ends the run;
  * ``DynamicsModel.fit_gp_model`` (the GP refit): start, end, and how many points it fits;
  * ``RCBF_SAC.update_parameters`` (one SAC update, wall time of each call after the warm-up)
    and ``CBFQPLayer.get_safe_action`` at batch 1 (the per-step QP: constraint assembly, row
    normalisation, qpth, clamp; wall and process CPU time of each call).

  Each step stamp is taken twice: ``time.perf_counter`` and ``time.process_time``.

  It prints one line ``REFERENCE_RESULT <json>`` at the end.

- the parent side (``run_reference``, ``parse_result``, ``steady_rate``, ``amortized_rate``,
  and the benchmarks' ``--reference`` arguments: ``add_reference_arguments``,
  ``reference_requested``), imported by the benchmarks; pure functions apart from the
  subprocess.

The reference's ``main.py`` is given ``--eval ''``: its argparse reads that flag with
``type=bool``, so only the empty string turns the evaluation episodes off (they would
otherwise run inside the timed window, after every 5th episode). ``--start_steps`` is set to
the warm-up so that the policy acts in the timed window, as in ours. ``--filter-only`` sets
``--start_steps`` and ``--batch_size`` beyond the run instead: random actions through its
filter and no SAC update, for the per-call filter times.
"""
from __future__ import annotations

import argparse
from collections.abc import Sequence
from dataclasses import dataclass
import json
import os
from pathlib import Path
import subprocess
import sys
import time

RESULT_TAG = 'REFERENCE_RESULT '
"""Prefix of the driver's one result line on stdout."""
ENV_NAMES = {'unicycle': 'Unicycle', 'car_following': 'SimulatedCars', 'pvtol': 'Pvtol'}
"""Our system names -> the reference's ``--env_name``."""
CBF_MODES = {'baseline': 'baseline', 'modular': 'mod', 'diff': 'full'}
"""Our training modes -> the reference's ``--cbf_mode``."""
REFIT_EVERY_STEPS = 400
"""The reference's refit schedule: a GP data point every 2nd step, a refit every
``gp_model_size / 10`` = 200 points (defaults), for its first ``gp_max_episodes`` episodes."""


class ReferenceError(RuntimeError):
    """The reference run failed; the message is one line saying why."""


class _Done(BaseException):
    """Ends the reference's training loop once enough steps are stamped (not an Exception, so
    nothing in the reference can swallow it)."""


# ---------------------------------------------------------------- parent side (pure logic)
@dataclass(frozen=True)
class Refit:
    """One GP refit of the reference: it ran between step stamps ``after_step`` and the next."""

    after_step: int
    seconds: float
    cpu_seconds: float
    points: int


def steady_rate(*, stamps: list[float], refits: list[Refit], first: int,
                cpu: bool = False) -> float:
    """Steps/s over the loop iterations from stamp ``first`` to the last, refits taken out.

    ``stamps[i]`` is the entry into the (i+1)-th env step; iteration i spans stamps[i] to
    stamps[i + 1]. A refit recorded after step k (k stamps so far) lies in iteration k - 1.
    ``cpu``: the stamps are process CPU times; take out the refits' CPU seconds.
    """
    if first < 0 or first >= len(stamps) - 1:
        raise ValueError(f'first: need 0 <= first < {len(stamps) - 1}, got {first}')
    n = len(stamps) - 1 - first
    excluded = sum(r.cpu_seconds if cpu else r.seconds for r in refits
                   if first <= r.after_step - 1 < len(stamps) - 1)
    elapsed = stamps[-1] - stamps[first] - excluded
    if elapsed <= 0:
        raise ValueError('stamps: no time left once the refits are taken out')
    return n / elapsed


def amortized_rate(*, steps_per_s: float, refit_s: float, every_steps: int) -> float:
    """Steps/s with one refit of ``refit_s`` seconds spread over each ``every_steps`` steps."""
    if steps_per_s <= 0 or every_steps <= 0 or refit_s < 0:
        raise ValueError('amortized_rate: rates and intervals must be positive')
    return 1.0 / (1.0 / steps_per_s + refit_s / every_steps)


def parse_result(stdout: str) -> dict:
    """The driver's result from its stdout (the last ``REFERENCE_RESULT`` line)."""
    lines = [line for line in stdout.splitlines() if line.startswith(RESULT_TAG)]
    if not lines:
        raise ReferenceError('reference driver printed no result line')
    try:
        result = json.loads(lines[-1][len(RESULT_TAG):])
    except json.JSONDecodeError as exc:
        raise ReferenceError(f'reference driver result is not JSON: {exc}') from None
    for key in ('stamps', 'cpu_stamps', 'refits', 'updates', 'filter_calls'):
        if key not in result:
            raise ReferenceError(f'reference driver result lacks {key!r}')
    result['refits'] = [Refit(**r) for r in result['refits']]
    return result


def check_reference(*, directory: Path, python: Path) -> None:
    """Fail with one line if DIR is not the reference's tree or PYTHON is not executable."""
    if not (directory / 'main.py').is_file() or not (directory / 'rcbf_sac').is_dir():
        raise ReferenceError(f'--reference: {directory} has no main.py and rcbf_sac/ '
                             "(the authors' Mod-RL-RCBF tree)")
    if not os.access(python, os.X_OK):
        raise ReferenceError(f'--reference-python: {python} is not an executable')


def add_reference_arguments(parser: argparse.ArgumentParser) -> None:
    """``--reference DIR`` and ``--reference-python PATH`` of a benchmark comparing with it."""
    parser.add_argument('--reference', type=Path, default=None,
                        help="the authors' Mod-RL-RCBF source tree (outside this repository)")
    parser.add_argument('--reference-python', type=Path, default=None,
                        help="python of the reference's venv")


def reference_requested(parser: argparse.ArgumentParser, args: argparse.Namespace, *,
                        minimums: Sequence[tuple[int, int, str]] = ()) -> bool:
    """Whether to compare with the reference: True when ``--reference`` is given and usable.

    Without ``--reference`` it prints that the comparison is skipped and returns False. With it,
    a missing ``--reference-python``, a ``(value, least, message)`` of ``minimums`` with
    ``value < least``, or a tree or interpreter :func:`check_reference` refuses ends the
    benchmark through ``parser.error`` (one line, exit 2) before anything is timed.
    """
    if args.reference is None:
        print('Reference comparison skipped: no --reference DIR given.', flush=True)
        return False
    if args.reference_python is None:
        parser.error('--reference needs --reference-python (the python of its venv)')
    for value, least, message in minimums:
        if value < least:
            parser.error(message)
    try:
        check_reference(directory=args.reference, python=args.reference_python)
    except ReferenceError as exc:
        parser.error(str(exc))
    return True


def run_reference(*, directory: Path, python: Path, system: str, mode: str, warmup: int,
                  steps: int, seed: int = 12345, filter_only: bool = False,
                  timeout_s: float = 1800.0) -> dict:
    """Run the driver in the reference's venv, 1 thread; returns ``parse_result``'s dict."""
    check_reference(directory=directory, python=python)
    if system not in ENV_NAMES:
        raise ReferenceError(f'system: the reference has no counterpart of {system!r}')
    if mode not in CBF_MODES:
        raise ReferenceError(f'mode: the reference has no counterpart of {mode!r}')
    env = {**os.environ, 'OMP_NUM_THREADS': '1', 'MKL_NUM_THREADS': '1',
           'OPENBLAS_NUM_THREADS': '1', 'PYTHONHASHSEED': '0'}
    env.pop('PYTHONPATH', None)
    command = [str(python), str(Path(__file__).resolve()), '--dir', str(directory),
               '--env', ENV_NAMES[system], '--cbf-mode', CBF_MODES[mode],
               '--warmup', str(warmup), '--steps', str(steps), '--seed', str(seed)]
    if filter_only:
        command.append('--filter-only')
    try:
        done = subprocess.run(command, capture_output=True, text=True, env=env,
                              timeout=timeout_s, check=False)
    except subprocess.TimeoutExpired:
        raise ReferenceError(f'reference run timed out after {timeout_s:.0f} s') from None
    if done.returncode != 0:
        tail = (done.stderr.strip().splitlines() or ['no stderr'])[-1]
        raise ReferenceError(f'reference run exited {done.returncode}: {tail}')
    return parse_result(done.stdout)


# ---------------------------------------------------------------- driver (reference venv)
def _drive(args: argparse.Namespace) -> dict:
    """Run the reference's main.py with the wraps described in the module docstring."""
    import runpy
    import tempfile

    import torch
    torch.set_num_threads(1)
    directory = str(Path(args.dir).resolve())
    sys.path.insert(0, directory)
    import build_env
    from rcbf_sac.diff_cbf_qp import CBFQPLayer
    from rcbf_sac.dynamics import DynamicsModel
    from rcbf_sac.sac_cbf import RCBF_SAC

    total = args.warmup + args.steps + 1
    stamps: list[float] = []
    cpu_stamps: list[float] = []
    refits: list[dict] = []
    updates: list[float] = []
    filter_calls: list[tuple[float, float]] = []

    original_build = build_env.build_env

    def timed_build(*a, **k):
        environment = original_build(*a, **k)
        step = environment.step

        def timed_step(action):
            stamps.append(time.perf_counter())
            cpu_stamps.append(time.process_time())
            if len(stamps) >= total:
                raise _Done
            return step(action)

        environment.step = timed_step
        return environment

    build_env.build_env = timed_build

    fit = DynamicsModel.fit_gp_model

    def timed_fit(self, *a, **k):
        points = min(self.history_counter, self.max_history_count)
        start, cpu = time.perf_counter(), time.process_time()
        out = fit(self, *a, **k)
        refits.append({'after_step': len(stamps), 'seconds': time.perf_counter() - start,
                       'cpu_seconds': time.process_time() - cpu, 'points': int(points)})
        return out

    DynamicsModel.fit_gp_model = timed_fit

    update = RCBF_SAC.update_parameters

    def timed_update(self, *a, **k):
        start = time.perf_counter()
        out = update(self, *a, **k)
        if len(stamps) > args.warmup:
            updates.append(time.perf_counter() - start)
        return out

    RCBF_SAC.update_parameters = timed_update

    safe = CBFQPLayer.get_safe_action

    def timed_safe(self, state_batch, *a, **k):
        wall, cpu = time.perf_counter(), time.process_time()
        out = safe(self, state_batch, *a, **k)
        if state_batch.dim() == 1 or state_batch.shape[0] == 1:
            filter_calls.append((time.perf_counter() - wall, time.process_time() - cpu))
        return out

    CBFQPLayer.get_safe_action = timed_safe

    huge = str(10 ** 9)
    argv = ['main.py', '--env_name', args.env, '--cbf_mode', args.cbf_mode, '--seed',
            str(args.seed), '--eval', '', '--max_episodes', huge]
    if args.filter_only:  # random actions, no SAC update: the per-step filter alone
        argv += ['--start_steps', huge, '--batch_size', huge]
    else:
        argv += ['--start_steps', str(args.warmup)]
    sys.argv = argv
    with tempfile.TemporaryDirectory() as scratch:
        os.chdir(scratch)
        try:
            runpy.run_path(str(Path(directory) / 'main.py'), run_name='__main__')
        except _Done:
            pass
    if len(stamps) < total:
        raise SystemExit(f'reference: its training loop ended after {len(stamps)} of '
                         f'{total} steps')
    return {'stamps': stamps, 'cpu_stamps': cpu_stamps, 'refits': refits, 'updates': updates,
            'filter_calls': filter_calls, 'warmup': args.warmup,
            'env': args.env, 'cbf_mode': args.cbf_mode, 'torch': torch.__version__,
            'threads': torch.get_num_threads()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--dir', required=True, help="the reference's source tree")
    parser.add_argument('--env', required=True, choices=sorted(ENV_NAMES.values()))
    parser.add_argument('--cbf-mode', required=True, choices=sorted(CBF_MODES.values()))
    parser.add_argument('--warmup', type=int, required=True)
    parser.add_argument('--steps', type=int, required=True)
    parser.add_argument('--seed', type=int, default=12345)
    parser.add_argument('--filter-only', action='store_true')
    args = parser.parse_args()
    real_stdout = sys.stdout
    sys.stdout = sys.stderr  # the reference's own prints stay off the result channel
    try:
        result = _drive(args)
    finally:
        sys.stdout = real_stdout
    print(RESULT_TAG + json.dumps(result), flush=True)


if __name__ == '__main__':
    main()
