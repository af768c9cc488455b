"""A training run survives a kill, a resume never destroys what is on disk, and no checkpoint
or policy file can run code when it is read."""
from __future__ import annotations

import json
import os
from pathlib import Path
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
import torch

from rcbf_ros.cli.main import main as cli_main
from rcbf_ros.training import run as run_module
from rcbf_ros.training.build import RunConfig, RunSetupError
from rcbf_ros.training.checkpoint import write_checkpoint
from rcbf_ros.training.loop import train
from rcbf_ros.training.run_files import (
    check_plain,
    load_payload,
    next_bag_dir,
    reconcile_metrics,
    save_payload,
    SUPERSEDED,
    UnsafeFileError,
)

TINY = ['--system', 'unicycle', '--mode', 'baseline', '--max-steps', '40', '--start-steps',
        '20', '--update-after', '20', '--batch-size', '16']


def rows_of(path: Path) -> list[dict]:
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


def snapshot(directory: Path) -> dict[str, bytes]:
    """Every file under ``directory`` (relative path -> bytes)."""
    return {str(p.relative_to(directory)): p.read_bytes()
            for p in sorted(directory.rglob('*')) if p.is_file()}


def bag_steps(bag: Path) -> int:
    from rosbags.highlevel import AnyReader
    with AnyReader([bag]) as reader:
        return sum(c.msgcount for c in reader.connections if c.topic == '/cmd_safe')


class Mkdir:
    """A crafted pickle: loading it with a general unpickler creates ``path`` (a stand-in for
    any command)."""

    def __init__(self, path: Path) -> None:
        self.path = path

    def __reduce__(self):
        return (os.mkdir, (str(self.path),))


# --------------------------------------------------------------------------- crash and resume
def test_sigkill_mid_run_then_resume_keeps_every_finished_episode(tmp_path):
    """`rcbf_ros train` killed with SIGKILL (no handler runs) once an episode has finished:
    --resume continues from the checkpoint (or, killed before it, from episode 0); every row
    on disk at the kill is kept (in metrics.jsonl, or, past the checkpoint, in
    metrics_superseded.jsonl) and the killed run's bag is left alone."""
    out = tmp_path / 'run'
    proc = subprocess.Popen(
        [sys.executable, '-m', 'rcbf_ros', 'train', *TINY, '--episodes', '50',
         '--out', str(out)], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
        env=dict(os.environ, OMP_NUM_THREADS='1'))
    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and proc.poll() is None:
            metrics = out / 'metrics.jsonl'
            if metrics.exists() and metrics.read_text():
                break
            time.sleep(0.02)
        assert proc.poll() is None, 'the run ended before it could be killed'
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=30)
    killed_lines = (out / 'metrics.jsonl').read_text().splitlines(keepends=True)
    killed_bag = snapshot(out / 'bag_0000')
    checkpoint = out / 'checkpoint.pt'
    done = int(load_payload(checkpoint)['episode']) if checkpoint.exists() else 0
    assert killed_lines and done < 50

    assert cli_main(['train', *TINY, '--episodes', str(done + 1), '--out', str(out),
                     '--resume']) == 0
    lines = (out / 'metrics.jsonl').read_text().splitlines(keepends=True)
    assert [json.loads(line)['episode'] for line in lines] == list(range(done + 1))
    superseded = out / SUPERSEDED
    moved = superseded.read_text().splitlines(keepends=True) if superseded.exists() else []
    # Rows the checkpoint holds stay as they were; any later one (the kill fell between a row
    # and its checkpoint) moved aside, unchanged.
    assert lines[:done] == killed_lines[:done]
    assert moved == killed_lines[done:]
    assert snapshot(out / 'bag_0000') == killed_bag
    assert bag_steps(out / 'bag_0001') == json.loads(lines[-1])['steps']


def test_resume_without_a_checkpoint_starts_at_episode_0_and_keeps_the_files(tmp_path, capsys):
    """A run killed before its first checkpoint: --resume says so, starts over at episode 0
    into a new bag, and the earlier attempt's row and bag stay on disk."""
    out = tmp_path / 'run'
    assert cli_main(['train', *TINY, '--episodes', '1', '--out', str(out)]) == 0
    (out / 'checkpoint.pt').unlink()
    earlier_row = (out / 'metrics.jsonl').read_text()
    earlier_bag = snapshot(out / 'bag_0000')
    capsys.readouterr()

    assert cli_main(['train', *TINY, '--episodes', '1', '--out', str(out), '--resume']) == 0
    printed = capsys.readouterr().out
    assert f'no checkpoint in {out}: starting at episode 0 (the files there are kept)' in printed
    assert "metrics.jsonl: cut back to the checkpoint's 0 episode(s); 1 later row(s) moved to " \
           f'{SUPERSEDED}' in printed
    assert [r['episode'] for r in rows_of(out / 'metrics.jsonl')] == [0]
    assert (out / SUPERSEDED).read_text() == earlier_row
    assert snapshot(out / 'bag_0000') == earlier_bag
    assert bag_steps(out / 'bag_0001') == rows_of(out / 'metrics.jsonl')[0]['steps']


def test_out_of_an_existing_run_without_resume_is_refused_and_untouched(tmp_path, capsys):
    out = tmp_path / 'run'
    assert cli_main(['train', *TINY, '--episodes', '1', '--out', str(out)]) == 0
    before = snapshot(out)
    capsys.readouterr()
    assert cli_main(['train', *TINY, '--episodes', '2', '--out', str(out)]) == 2
    printed = capsys.readouterr()
    err = printed.err
    assert printed.out == '' and err.count('\n') == 1 and 'Traceback' not in err
    assert err.startswith(f'error: out_dir: {out} already holds a run (checkpoint.pt, ')
    assert 'resume it (--resume) or choose another directory' in err
    assert snapshot(out) == before
    # The same without a bag, where nothing else would have stopped it.
    bare = tmp_path / 'bare'
    assert cli_main(['train', *TINY, '--episodes', '1', '--no-bag', '--out', str(bare)]) == 0
    before = snapshot(bare)
    assert cli_main(['train', *TINY, '--episodes', '1', '--no-bag', '--out', str(bare)]) == 2
    assert snapshot(bare) == before


def test_every_start_of_a_run_records_into_a_bag_of_its_own(tmp_path):
    """Resumed twice from the same checkpoint (the first resume was killed before its own
    checkpoint): three bags, none rewritten, the last holding the episode played last."""
    out = tmp_path / 'run'
    run = RunConfig(system='unicycle', episodes=1, max_steps=40, out_dir=str(out),
                    learner=_tiny_learner())
    train(run, log=lambda _: None)
    checkpoint = (out / 'checkpoint.pt').read_bytes()
    train(RunConfig(**{**run.__dict__, 'episodes': 2, 'resume': True}), log=lambda _: None)
    first_two = snapshot(out)
    (out / 'checkpoint.pt').write_bytes(checkpoint)  # as if killed before its checkpoint
    history = train(RunConfig(**{**run.__dict__, 'episodes': 2, 'resume': True}),
                    log=lambda _: None)
    assert sorted(p.name for p in out.glob('bag_*')) == ['bag_0000', 'bag_0001', 'bag_0002']
    for name, data in first_two.items():
        if name.startswith('bag_'):
            assert snapshot(out)[name] == data, name
    assert bag_steps(out / 'bag_0000') == bag_steps(out / 'bag_0002') == 40
    assert [r['episode'] for r in history] == [0, 1]
    assert [r['episode'] for r in rows_of(out / SUPERSEDED)] == [1]
    assert next_bag_dir(out).name == 'bag_0003'


def test_checkpoint_every_is_a_flag_checked_at_start(tmp_path, capsys, monkeypatch):
    out = tmp_path / 'run'
    assert cli_main(['train', *TINY, '--episodes', '1', '--checkpoint-every', '0',
                     '--out', str(out)]) == 2
    assert '--checkpoint-every: must be >= 1, got 0' in capsys.readouterr().err
    assert not out.exists()
    written = []

    def spy(path, **entries):
        written.append(entries['episode'])
        return write_checkpoint(path, **entries)

    monkeypatch.setattr(run_module, 'write_checkpoint', spy)
    # Every 2 episodes of 3: after episode 2, and on exit.
    assert cli_main(['train', *TINY, '--episodes', '3', '--no-bag', '--checkpoint-every', '2',
                     '--out', str(out)]) == 0
    assert written == [2, 3]
    # The default: after every episode (the last one is not written twice).
    written.clear()
    assert cli_main(['train', *TINY, '--episodes', '2', '--no-bag',
                     '--out', str(tmp_path / 'default')]) == 0
    assert written == [1, 2]


# --------------------------------------------------------------------------- untrusted files
def test_crafted_pickle_is_refused_everywhere_and_never_runs(tmp_path, capsys):
    from rcbf_ros.experiments.evaluate import load_trained_learner
    from rcbf_ros.training.policy_io import load_policy
    run_dir = tmp_path / 'run'
    assert cli_main(['train', *TINY, '--episodes', '1', '--no-bag', '--out', str(run_dir)]) == 0
    marker = tmp_path / 'ran'
    torch.save({'actor': Mkdir(marker), 'obs_dim': 7}, run_dir / 'policy.pt')
    torch.save({'learner': Mkdir(marker), 'episode': 1, 'history': []},
               run_dir / 'checkpoint.pt')
    policy, checkpoint = run_dir / 'policy.pt', run_dir / 'checkpoint.pt'

    with pytest.raises(UnsafeFileError, match=f'^{policy}: refused to load: it holds more '
                       r'than tensors and plain data \(it asks for posix.mkdir\)$'):
        load_payload(policy)
    with pytest.raises(UnsafeFileError, match=f'^policy_path: {policy}: refused to load'):
        load_policy(policy)
    with pytest.raises(ValueError, match=f'^{checkpoint}: refused to load'):
        load_trained_learner(run_dir)
    with pytest.raises(RunSetupError, match=f'^resume: {checkpoint}: refused to load'):
        train(RunConfig(system='unicycle', episodes=2, max_steps=40, out_dir=str(run_dir),
                        record_bag=False, resume=True, learner=_tiny_learner()),
              log=lambda _: None)
    capsys.readouterr()
    assert cli_main(['train', *TINY, '--episodes', '2', '--out', str(run_dir), '--resume']) == 2
    err = capsys.readouterr().err
    assert err == f'error: resume: {checkpoint}: refused to load: it holds more than tensors ' \
                  'and plain data (it asks for posix.mkdir)\n'
    assert not marker.exists()
    # The file is what it claims: a general unpickler runs it.
    torch.load(policy, weights_only=False)
    assert marker.is_dir()


def test_the_projects_files_hold_only_plain_data_and_read_back(tmp_path):
    out = tmp_path / 'run'
    assert cli_main(['train', *TINY, '--mode', 'diff', '--model-based', '--episodes', '1',
                     '--no-bag', '--out', str(out)]) == 0
    for name in ('checkpoint.pt', 'policy.pt'):
        check_plain(load_payload(out / name))
    state = load_payload(out / 'checkpoint.pt')['learner']
    assert state['buffer']['size'] == 40 and state['model_buffer'] is not None


def test_save_payload_refuses_anything_but_tensors_and_plain_data(tmp_path):
    path = tmp_path / 'x.pt'
    with pytest.raises(TypeError, match=r'^x.pt.a\[1\]: a numpy.ndarray is not a tensor or '
                                        'plain data$'):
        save_payload(path, {'a': [1, np.zeros(2)]})
    with pytest.raises(TypeError, match=r'^x.pt.b: key \(1, 2\) is a tuple$'):
        save_payload(path, {'b': {(1, 2): 0}})
    assert not path.exists() and not list(tmp_path.iterdir())
    save_payload(path, {'t': torch.ones(2), 'n': None, 'l': [1, 2.0, 'x', (True,)]})
    assert load_payload(path)['l'] == [1, 2.0, 'x', (True,)]


def test_damaged_files_are_named(tmp_path):
    path = tmp_path / 'checkpoint.pt'
    save_payload(path, {'a': torch.ones(3)})
    path.write_bytes(path.read_bytes()[:200])
    with pytest.raises(ValueError, match=f'^{path}: not a readable torch file'):
        load_payload(path)
    with pytest.raises(FileNotFoundError, match='no such file'):
        load_payload(tmp_path / 'none.pt')


def test_reconcile_metrics_cuts_back_atomically_and_keeps_the_cut_rows(tmp_path):
    path = tmp_path / 'metrics.jsonl'
    history = [{'episode': 0, 'ret': 1.5}]
    # A torn last line (killed mid-write) is kept aside as it was.
    path.write_text(json.dumps(history[0]) + '\n' + '{"episode": 1, "ret": 2.0}\n{"epi')
    assert reconcile_metrics(path, history=history) == 2
    assert rows_of(path) == history
    assert (tmp_path / SUPERSEDED).read_text() == '{"episode": 1, "ret": 2.0}\n{"epi\n'
    assert sorted(p.name for p in tmp_path.iterdir()) == ['metrics.jsonl', SUPERSEDED]
    # Fewer rows than the checkpoint holds (a lost file): written back from it.
    path.unlink()
    assert reconcile_metrics(path, history=history) == 0 and rows_of(path) == history
    stamp = path.stat().st_mtime_ns
    assert reconcile_metrics(path, history=history) == 0 and path.stat().st_mtime_ns == stamp


def _tiny_learner():
    from rcbf_ros.learning.sac import SACConfig
    from rcbf_ros.training.agent import LearnerConfig
    return LearnerConfig(mode='baseline', start_steps=20, update_after=20, batch_size=16,
                         sac=SACConfig(hidden_sizes=(32, 32)))


def test_experiment_runner_restarts_a_run_killed_before_its_first_checkpoint(tmp_path):
    """The runner trains what is not complete with resume, so a run directory that a kill
    left without a checkpoint restarts (keeping its row aside) instead of being refused."""
    from rcbf_ros.experiments.definitions import Budget, RunSpec
    from rcbf_ros.experiments.runner import run_all, run_status
    spec = RunSpec('unicycle', 'modular', 0, Budget(
        name='tiny', episodes={'unicycle': 1}, max_steps={'unicycle': 30}, start_steps=10,
        update_after=10, batch_size=8, gp_refit_interval=20, hidden_sizes=(8, 8),
        record_bag=False))
    run_dir = spec.run_dir(tmp_path)
    run_dir.mkdir(parents=True)
    row = json.dumps({'episode': 0, 'ret': 1.0}) + '\n'
    (run_dir / 'metrics.jsonl').write_text(row)
    assert run_status(spec, tmp_path) == 'missing'
    assert [r['status'] for r in run_all([spec], tmp_path, log=lambda _: None)] == ['ran']
    assert [r['episode'] for r in rows_of(run_dir / 'metrics.jsonl')] == [0]
    assert (run_dir / SUPERSEDED).read_text() == row
