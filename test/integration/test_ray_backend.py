"""The experiment runner on a real Ray: a local instance, and an existing cluster by address.

Either way a run trains in a Ray worker process and must give what the sequential path gives
(same seed, same code, same machine: the same numbers), and finished runs are skipped. A local
instance listens on loopback only and runs its workers at the caller's priority. Skipped
without the optional ray (the test extra has it).
"""
from __future__ import annotations

import json
import os
from pathlib import Path
import signal
import socket
import subprocess
import sys
import time

import pytest

from rcbf_ros.cli.main import main as cli_main
from rcbf_ros.experiments.definitions import Budget, RunSpec
from rcbf_ros.experiments.evaluate import evaluate_job
from rcbf_ros.experiments.runner import (
    LOCAL_RAY_ENV,
    parallel_map,
    ray_available,
    run_all,
    select_backend,
)

pytestmark = [pytest.mark.integration,
              pytest.mark.skipif(not ray_available(), reason='needs the optional ray')]

TIMING = {'wall_s', 'steps_per_s', 'eval_wall_s'}


def _tiny_specs() -> list[RunSpec]:
    budget = Budget(name='tiny', episodes={'unicycle': 1}, max_steps={'unicycle': 30},
                    start_steps=10, update_after=10, batch_size=8, gp_refit_interval=20,
                    hidden_sizes=(8, 8), record_bag=False)
    return [RunSpec('unicycle', 'modular', seed, budget) for seed in (0, 1)]


def _timeless(rows: list[dict]) -> list[dict]:
    """``rows`` without their wall-clock fields."""
    return [{k: v for k, v in row.items() if k not in TIMING} for row in rows]


def _rows(path: Path) -> list[dict]:
    """A JSON-lines file's rows without the wall-clock fields."""
    return _timeless([json.loads(line) for line in path.read_text().splitlines()
                      if line.strip()])


def test_a_local_instance_trains_and_evaluates_in_workers_on_loopback(tmp_path):
    assert select_backend(use_ray=True, address=None) == 'ray'
    specs = _tiny_specs()
    sequential = run_all(specs, tmp_path / 'seq', log=lambda _: None)
    assert {r['pid'] for r in sequential} == {os.getpid()}
    import ray
    try:
        results = run_all(specs, tmp_path / 'ray', backend='ray', num_cpus=2,
                          log=lambda _: None)
        # Every node of the instance (there is one) is on 127.0.0.1, and its workers run at
        # this process's priority (Ray's default niceness is 15).
        assert {node['NodeManagerAddress'] for node in ray.nodes()} == {'127.0.0.1'}
        assert [r['status'] for r in results] == ['ran', 'ran']
        assert os.getpid() not in {r['pid'] for r in results}
        # (the workers stay alive, idle, after their tasks)
        assert {os.getpriority(os.PRIO_PROCESS, r['pid']) for r in results} == \
            {os.getpriority(os.PRIO_PROCESS, 0)}
        for spec in specs:
            assert _rows(spec.run_dir(tmp_path / 'ray') / 'metrics.jsonl') == \
                _rows(spec.run_dir(tmp_path / 'seq') / 'metrics.jsonl')
        # The transfer evaluation as Ray tasks: the rows of the same evaluation in this process.
        jobs = [(str(spec.run_dir(tmp_path / 'ray')), (0, 1), 15, 'learned') for spec in specs]
        remote = parallel_map(evaluate_job, jobs, backend='ray')
        local = [evaluate_job((str(spec.run_dir(tmp_path / 'seq')), (0, 1), 15, 'learned'))
                 for spec in specs]
        assert [_timeless(rows) for rows in remote] == [_timeless(rows) for rows in local]
        assert all(len(rows) == 2 for rows in remote)
        again = run_all(specs, tmp_path / 'ray', backend='ray', num_cpus=2, log=lambda _: None)
        assert [r['status'] for r in again] == ['skipped', 'skipped']
    finally:
        ray.shutdown()


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(('127.0.0.1', 0))
        return int(sock.getsockname()[1])


def test_the_cli_runs_an_experiment_on_an_existing_cluster_by_address(tmp_path):
    """A Ray head started apart (`ray start --head`, as on a cluster), the CLI pointed at it
    with --address from another process; the same command without it is the reference."""
    port = _free_port()
    env = {**os.environ, **LOCAL_RAY_ENV,
           'RAY_AUTH_MODE': 'token',  # what `ray start` enables; its drivers must say so too
           'RAY_GRACEFUL_SHUTDOWN_DRAIN_TIMEOUT_S': '0'}
    # `ray start` on this interpreter: Ray refuses a driver whose Python differs from the
    # head's, even in the patch version (the ray script may start another Python).
    head_log = tmp_path / 'head.log'
    with head_log.open('w') as log:
        head = subprocess.Popen(
            [sys.executable, '-m', 'ray.scripts.scripts', 'start', '--head', f'--port={port}',
             '--num-cpus=2', '--include-dashboard=false', '--disable-usage-stats', '--block'],
            env=env, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
    command = ['experiment', 'transfer', '--budget', 'smoke', '--systems', 'unicycle',
               '--methods', 'modular', '--episodes', '1', '--max-steps', '30',
               '--layouts', '2', '--eval-max-steps', '15', '--seeds', '2', '--no-report']
    try:
        deadline = time.monotonic() + 120
        while 'block forever' not in head_log.read_text():
            assert head.poll() is None, head_log.read_text()
            assert time.monotonic() < deadline, head_log.read_text()
            time.sleep(0.5)
        driver = subprocess.Popen(
            [sys.executable, '-m', 'rcbf_ros', *command, '--address', f'127.0.0.1:{port}',
             '--out', str(tmp_path / 'cluster')],
            env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        out, err = driver.communicate(timeout=500)
        assert driver.returncode == 0, out[-2000:] + err[-3000:]
    finally:
        os.killpg(head.pid, signal.SIGTERM)
        try:
            head.wait(timeout=60)
        except subprocess.TimeoutExpired:
            os.killpg(head.pid, signal.SIGKILL)
            head.wait()
    assert cli_main([*command, '--out', str(tmp_path / 'seq')]) == 0
    cluster_runs = sorted((tmp_path / 'cluster').rglob('metrics.jsonl'))
    assert len(cluster_runs) == 2
    for metrics in cluster_runs:
        run = metrics.parent
        twin = tmp_path / 'seq' / run.relative_to(tmp_path / 'cluster')
        assert _rows(metrics) == _rows(twin / 'metrics.jsonl')
        assert _rows(run / 'transfer_learned_L2_T15.jsonl') == \
            _rows(twin / 'transfer_learned_L2_T15.jsonl')
        # Trained by a worker of the cluster, not by the CLI process that asked for it.
        worker = json.loads((run / 'summary.json').read_text())['pid']
        assert worker not in (driver.pid, head.pid, os.getpid())
        assert json.loads((twin / 'summary.json').read_text())['pid'] == os.getpid()


def test_an_address_that_is_not_a_ray_cluster_ends_with_exit_2(tmp_path, capsys):
    """A port that accepts TCP but serves no Ray passes the reach check; Ray's refusal must
    still end the command as a usage error naming --address, not a traceback."""
    with socket.socket() as impostor:
        impostor.bind(('127.0.0.1', 0))
        impostor.listen()
        port = impostor.getsockname()[1]
        status = cli_main(['experiment', 'transfer', '--budget', 'smoke', '--systems',
                           'unicycle', '--methods', 'modular', '--no-report',
                           '--address', f'ray://127.0.0.1:{port}', '--out', str(tmp_path)])
    assert status == 2
    assert '--address' in capsys.readouterr().err
    assert not list(tmp_path.rglob('metrics.jsonl'))
