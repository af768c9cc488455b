"""Run an experiment's training runs: sequentially, or as Ray tasks; finished runs are skipped.

A run is *complete* when its directory holds ``summary.json`` written after training, a
``metrics.jsonl`` with one row per planned episode, and ``policy.pt``. A run with a checkpoint
but fewer rows is *resumed* from its checkpoint (``RunConfig.resume``); anything else starts
fresh. So calling the runner again after a crash or Ctrl-C redoes only what is missing.

Parallelism is Ray's (``pip install ray``, optional): with ``--ray`` (a local instance,
``--num-cpus`` workers, listening on loopback only) or ``--address`` (an existing cluster) every
run becomes one Ray task of one CPU. Without Ray installed, ``--ray`` falls back to the
sequential path with a warning; ``--address`` is an error (the user asked for a cluster we
cannot reach), and so is an address where nothing answers (``check_reachable``) or that Ray
refuses: both end the command with exit status 2 and a message naming ``--address``.
"""
from __future__ import annotations

import importlib.util
import json
import os
from pathlib import Path
import socket
import time
from typing import Any, Callable, Literal, Sequence, TypeVar

from rcbf_ros.experiments.definitions import RunSpec

Backend = Literal['sequential', 'ray']
LOCAL_RAY_SWITCH = 'RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER'
LOCAL_RAY_ENV = {LOCAL_RAY_SWITCH: '0', 'RAY_worker_niceness': '0'}
"""Environment of a local Ray instance (a value the user set is kept):

- no cluster, so every server on 127.0.0.1 (Ray's own switch, named for the platforms where
  it is the default);
- workers at the caller's priority. Ray starts them at niceness 15, which on a machine shared
  with other work (the nodes, another run) starves the runs: beside two busy processes on
  2 cores two short runs took 23 times as long as in the caller (benchmarks/bench_ray.py).
"""
T = TypeVar('T')
R = TypeVar('R')


class ClusterError(RuntimeError):
    """The cluster named by ``--address`` could not be joined (a usage error, not a crash)."""


def ray_available() -> bool:
    """Whether the optional ``ray`` package can be imported."""
    return importlib.util.find_spec('ray') is not None


def select_backend(*, use_ray: bool, address: str | None,
                   log: Callable[[str], None] = print) -> Backend:
    """``ray`` when asked for (``use_ray`` or ``address``) and importable, else ``sequential``.

    Raises:
        RuntimeError: naming ``--address`` when a cluster address is given but Ray is absent
            or nothing answers at it (``check_reachable``).
        ValueError: naming ``--address`` when the address does not parse.
    """
    if not (use_ray or address):
        return 'sequential'
    if ray_available():
        if address:
            check_reachable(address)
        return 'ray'
    if address:
        raise RuntimeError(f'--address: {address!r} needs the optional ray package '
                           "(pip install 'rcbf_ros[ray]'); it is not installed")
    log('warning: --ray given but ray is not installed; running sequentially')
    return 'sequential'


def parse_address(address: str) -> tuple[str, int] | None:
    """``(host, port)`` of a Ray cluster address: ``host:port``, ``ray://host:port`` (a Ray
    client server) or ``[v6 address]:port``; ``None`` for Ray's ``auto`` and ``local``, which
    name no endpoint.

    Raises:
        ValueError: naming ``--address`` when the address has no host or no port number.
    """
    text = address.strip()
    if text in ('auto', 'local'):
        return None
    _, sep, rest = text.partition('://')
    endpoint = rest if sep else text
    host, colon, port = endpoint.rpartition(':')
    host = host.removeprefix('[').removesuffix(']')
    if not colon or not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise ValueError(f'--address: {address!r} is not host:port (e.g. 127.0.0.1:6379 or '
                         'ray://head:10001)')
    return host, int(port)


def check_reachable(address: str, timeout_s: float = 5.0) -> None:
    """Fail fast when nothing accepts a TCP connection at a cluster address.

    Ray's own ``init`` retries an unreachable head without end (measured: still waiting after
    300 s), which for a mistyped address looks like a hung experiment. Only TCP is checked: a
    port that accepts connections but is not Ray's is left to Ray.

    Raises:
        ValueError: naming ``--address`` when it does not parse (``parse_address``).
        ClusterError: naming ``--address`` when the connection is refused or times out.
    """
    endpoint = parse_address(address)
    if endpoint is None:
        return
    try:
        with socket.create_connection(endpoint, timeout=timeout_s):
            pass
    except OSError as exc:
        raise ClusterError(
            f'--address: nothing answers at {address!r} ({exc.strerror or exc}); start the '
            'head there (`ray start --head --port=PORT`) or correct the address') from exc


def parallel_map(fn: Callable[[T], R], items: Sequence[T], *, backend: Backend,
                 address: str | None = None, num_cpus: int | None = None) -> list[R]:
    """``[fn(item) for item in items]``, as one Ray task per item on the ``ray`` backend.

    ``fn`` must be a module-level function (Ray pickles it by reference).
    """
    if backend == 'sequential' or len(items) == 0:
        return [fn(item) for item in items]
    if not address:
        # A local instance serves this machine only, so its servers listen on loopback. Ray
        # binds to the machine's outward address unless told that it is not part of a cluster:
        # its processes read the variable from the environment they inherit, this one read it
        # when ray was first imported (perhaps before this call).
        for name, value in LOCAL_RAY_ENV.items():
            os.environ.setdefault(name, value)
        if os.environ[LOCAL_RAY_SWITCH] == '0':
            importlib.import_module('ray._private.ray_constants').ENABLE_RAY_CLUSTER = False
    import ray  # optional dependency, checked by select_backend
    if not ray.is_initialized():
        if address:
            try:
                ray.init(address=address)
            except (ConnectionError, ValueError) as exc:  # what Ray raises for a bad address
                raise ClusterError(f'--address: Ray could not join {address!r}: {exc}') from exc
        else:
            # 'local': always a new instance of our own, never one found on the machine.
            ray.init(address='local', num_cpus=num_cpus, include_dashboard=False)
    task = ray.remote(num_cpus=1)(fn)
    return list(ray.get([task.remote(item) for item in items]))


# --------------------------------------------------------------------------- completeness
def metrics_rows(run_dir: Path) -> list[dict[str, Any]]:
    """The run's per-episode rows (empty when there is no metrics file)."""
    path = Path(run_dir) / 'metrics.jsonl'
    if not path.exists():
        return []
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


def run_status(spec: RunSpec, root: str | Path) -> Literal['complete', 'partial', 'missing']:
    """``complete`` (skip), ``partial`` (resume from the checkpoint) or ``missing``."""
    run_dir = spec.run_dir(root)
    rows = metrics_rows(run_dir)
    if ((run_dir / 'summary.json').exists() and (run_dir / 'policy.pt').exists()
            and len(rows) >= spec.episodes):
        return 'complete'
    if (run_dir / 'checkpoint.pt').exists() and rows:
        return 'partial'
    return 'missing'


def summarize_rows(rows: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """Totals of a run: episodes, env steps, returns, goals, violations, wall time."""
    if not rows:
        return {'episodes': 0}
    steps = sum(int(r['steps']) for r in rows)
    wall = sum(float(r['wall_s']) for r in rows)
    return {
        'episodes': len(rows), 'env_steps': steps,
        'final_return': float(rows[-1]['ret']), 'best_return': max(float(r['ret']) for r in rows),
        'goals_reached': sum(bool(r['goal_reached']) for r in rows),
        'safety_violations': sum(int(r['violations']) for r in rows),
        'fail_safe_steps': sum(int(r.get('fail_safe', 0)) for r in rows),
        'max_slack': max(float(r['max_slack']) for r in rows),
        'episode_wall_s': wall, 'steps_per_s': steps / wall if wall > 0 else 0.0,
    }


# --------------------------------------------------------------------------- one run
def train_run(job: tuple[RunSpec, str]) -> dict[str, Any]:
    """Train one run (resuming a partial one) and write its ``summary.json``.

    Module-level so that Ray can ship it; returns the summary with ``status``.
    """
    from rcbf_ros.training.loop import train
    spec, root = job
    status = run_status(spec, root)
    run_dir = spec.run_dir(root)
    if status == 'complete':
        summary = json.loads((run_dir / 'summary.json').read_text())
        return {**summary, 'status': 'skipped'}
    start = time.perf_counter()
    # Without a checkpoint, resume starts at episode 0 and keeps what a killed attempt left
    # (a fresh start would refuse a directory that holds a run).
    config = spec.run_config(root, resume=True)
    train(config, log=lambda line: None)
    summary = {
        'system': spec.system, 'method': spec.method, 'seed': spec.seed,
        'budget': spec.budget.name, 'planned_episodes': spec.episodes,
        **summarize_rows(metrics_rows(run_dir)),
        'wall_s': time.perf_counter() - start,
        # Where it ran: the machine and process (a Ray task's worker, or the caller).
        'host': socket.gethostname(), 'pid': os.getpid(),
    }
    (run_dir / 'summary.json').write_text(json.dumps(summary, indent=2))
    return {**summary, 'status': 'resumed' if status == 'partial' else 'ran'}


def run_all(specs: Sequence[RunSpec], root: str | Path, *, backend: Backend = 'sequential',
            address: str | None = None, num_cpus: int | None = None,
            log: Callable[[str], None] = print) -> list[dict[str, Any]]:
    """Train every run that is not complete; returns one summary per spec (same order), each
    with ``status`` ``ran`` | ``resumed`` | ``skipped``."""
    root = str(root)
    pending = [s for s in specs if run_status(s, root) != 'complete']
    log(f'{len(specs)} runs, {len(specs) - len(pending)} already complete, '
        f'{len(pending)} to train ({backend})')
    done = {id(s): r for s, r in zip(pending, parallel_map(
        train_run, [(s, root) for s in pending], backend=backend, address=address,
        num_cpus=num_cpus))}
    out = []
    for spec in specs:
        result = done.get(id(spec)) or train_run((spec, root))
        log(f"  {spec.system}/{spec.method}/seed{spec.seed}: {result['status']}, "
            f"{result.get('episodes', 0)} episodes, "
            f"{result.get('safety_violations', 0)} violations")
        out.append(result)
    return out
