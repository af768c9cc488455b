"""TrainingRun: one lifecycle for both entry points (no middleware, no episodes played).

The learner node and ``rcbf_ros train`` differ only in their EntryPoint; here each opens,
records and checkpoints a run the other one resumes, and both word a refusal and a stop with
their own way to resume.
"""
from __future__ import annotations

import errno
import json
from pathlib import Path

import pytest

from rcbf_ros.learning.sac import SACConfig
from rcbf_ros.training.agent import LearnerConfig
from rcbf_ros.training.build import build_run, RunConfig, RunSetupError
from rcbf_ros.training.checkpoint import CheckpointError, identity_of
from rcbf_ros.training.run import EntryPoint, NODE, TRAINER, TrainingRun
from rcbf_ros.training.run_files import load_payload


def tiny(out: Path, **learner):
    """A learner of small networks and its run in ``out``."""
    config = LearnerConfig(**{'mode': 'baseline', 'sac': SACConfig(hidden_sizes=(8, 8)),
                              **learner})
    run = RunConfig(system='unicycle', episodes=2, max_steps=10, out_dir=str(out),
                    record_bag=False, learner=config)
    return build_run(run)[2]


def opened(out: Path, entry: EntryPoint, learner, *, resume: bool, lines: list[str]):
    run = TrainingRun(out, entry=entry, system_name='unicycle', resume=resume,
                      checkpoint_every=1, settings={'by': entry.made_by}, log=lines.append)
    return run, run.open(identity_of(learner, 'unicycle'))


def row(episode: int) -> dict:
    return {'episode': episode, 'ret': float(episode), 'steps': 10}


@pytest.mark.parametrize('first, second', [(NODE, TRAINER), (TRAINER, NODE)])
def test_a_run_of_one_entry_point_is_resumed_by_the_other(tmp_path, first, second):
    out = tmp_path / 'run'
    learner = tiny(out)
    lines: list[str] = []
    run, checkpoint = opened(out, first, learner, resume=False, lines=lines)
    assert checkpoint is None and lines == []
    learner.env_steps = 20  # as if two episodes of 10 steps were played
    env_rng = {'bit_generator': 'PCG64'} if first.restores_env else None
    for episode in range(2):
        run.record(row(episode))
        assert run.checkpoint_due()
        run.save_checkpoint(learner, env_rng=env_rng)
    run.finish(learner, env_rng=env_rng)
    assert (out / 'policy.pt').exists()
    assert load_payload(out / 'checkpoint.pt')['made_by'] == first.made_by

    again = tiny(out)
    run, checkpoint = opened(out, second, again, resume=True, lines=lines)
    assert checkpoint is not None and checkpoint.episode == run.episodes == 2
    # The node cannot restore the trainer's env generator: its simulator keeps its own.
    note = '' if second.restores_env else '; the simulator keeps its own episode generator'
    assert lines == [f'resumed at episode 2 of a run of {first.made_by} from '
                     f"{out / 'checkpoint.pt'}{note}"]
    run.restore(again, checkpoint)
    assert again.env_steps == 20
    again.env_steps = 30  # one more episode
    run.record(row(2))
    run.finish(again, env_rng=None)
    payload = load_payload(out / 'checkpoint.pt')
    assert payload['made_by'] == second.made_by and payload['episode'] == 3
    assert payload['run'] == {'by': second.made_by}
    rows = [json.loads(line) for line in (out / 'metrics.jsonl').read_text().splitlines()]
    assert [r['episode'] for r in rows] == [0, 1, 2]


def test_a_finish_without_new_steps_keeps_the_checkpoint_as_it_is(tmp_path):
    out = tmp_path / 'run'
    learner = tiny(out)
    run, _ = opened(out, NODE, learner, resume=False, lines=[])
    run.record(row(0))
    run.save_checkpoint(learner, env_rng=None)
    before = (out / 'checkpoint.pt').stat().st_ino  # a write replaces the file
    run.finish(learner, env_rng=None)
    assert (out / 'checkpoint.pt').stat().st_ino == before


@pytest.mark.parametrize('entry, refusal, resume', [
    (TRAINER, 'resume it (--resume) or choose another directory', '--resume'),
    (NODE, 'set resume:=true to continue it or choose another out_dir', 'resume:=true')])
def test_each_entry_point_says_how_to_resume(tmp_path, entry, refusal, resume):
    out = tmp_path / 'run'
    learner = tiny(out)
    run, _ = opened(out, entry, learner, resume=False, lines=[])
    full = OSError(errno.ENOSPC, 'No space left on device', str(out / 'metrics.jsonl'))
    assert run.stopped(full) == (f"{out / 'metrics.jsonl'}: No space left on device; the run "
                                 'stopped (no checkpoint written yet)')
    run.record(row(0))
    run.save_checkpoint(learner, env_rng=None)
    assert run.stopped(full).endswith(f'(checkpoint.pt holds 1 episode(s); {resume} continues '
                                      'from it)')
    with pytest.raises(RunSetupError) as refused:
        opened(out, entry, learner, resume=False, lines=[])
    assert str(refused.value) == (f'out_dir: {out} already holds a run (checkpoint.pt, '
                                  f'metrics.jsonl); {refusal}')


def test_a_learner_of_another_observation_size_is_refused_before_loading(tmp_path):
    """The node learns the observation's size at the first step: restore checks it then."""
    out = tmp_path / 'run'
    learner = tiny(out)
    run, _ = opened(out, TRAINER, learner, resume=False, lines=[])
    run.record(row(0))
    run.save_checkpoint(learner, env_rng=None)
    identity = {**identity_of(learner, 'unicycle'), 'obs_dim': None}
    resumed = TrainingRun(out, entry=NODE, system_name='unicycle', resume=True,
                          checkpoint_every=1, settings={}, log=lambda _: None)
    checkpoint = resumed.open(identity)
    other = tiny(out)
    other.sac.obs_dim += 1  # what the node's first step would have said
    with pytest.raises(CheckpointError, match='was made with obs_dim 7; this run has obs_dim 8'):
        resumed.restore(other, checkpoint)
