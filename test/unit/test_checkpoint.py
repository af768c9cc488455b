"""checkpoint.pt as one format: what a resume compares, hostile files refused in one line, and
atomic writes that leave the previous file whole when the disk is full."""
from __future__ import annotations

import errno
import os
from pathlib import Path
import re
import resource
import shutil
import signal
import tempfile

from hypothesis import given, HealthCheck, settings
from hypothesis import strategies as st
import pytest
import torch

from rcbf_ros.cli.main import main as cli_main
from rcbf_ros.learning.sac import SACConfig
from rcbf_ros.training import loop
from rcbf_ros.training import run as run_module
from rcbf_ros.training.agent import LearnerConfig, SafeLearner
from rcbf_ros.training.build import build_run, RunConfig, RunSetupError
from rcbf_ros.training.checkpoint import (
    CheckpointError,
    describe_difference,
    identity_of,
    read_checkpoint,
    SETTINGS,
    SHAPES,
)
from rcbf_ros.training.loop import train
from rcbf_ros.training.run_files import (
    describe_write_error,
    load_payload,
    RunWriteError,
    save_payload,
    write_atomically,
)

HIDDEN = (16, 16)


def tiny_learner(**extra) -> LearnerConfig:
    fields = dict(mode='baseline', start_steps=20, update_after=20, batch_size=16,
                  sac=SACConfig(hidden_sizes=HIDDEN))
    fields.update(extra)
    return LearnerConfig(**fields)


def tiny_run(out: Path, **extra) -> RunConfig:
    fields = dict(system='unicycle', episodes=1, max_steps=30, out_dir=str(out),
                  record_bag=False, learner=tiny_learner())
    fields.update(extra)
    return RunConfig(**fields)


@pytest.fixture(scope='module')
def base_identity() -> dict:
    _, _, learner, _ = build_run(tiny_run(Path('unused')))
    return identity_of(learner, 'unicycle')


@pytest.fixture(scope='module')
def one_episode(tmp_path_factory) -> Path:
    """A finished 1-episode run of ``rcbf_ros train`` (copy it before resuming)."""
    out = tmp_path_factory.mktemp('base') / 'run'
    train(tiny_run(out), log=lambda _: None)
    return out


def copy_of(run: Path, tmp_path: Path) -> Path:
    target = tmp_path / 'run'
    shutil.copytree(run, target)
    return target


# --------------------------------------------------------------------------- what is compared
def _changed(key: str, value):
    if isinstance(value, bool):
        return not value
    if isinstance(value, (int, float)):
        return value + 1
    if isinstance(value, str):
        return value + '_other'
    return [*value, 1.0]


@settings(max_examples=60, deadline=None)
@given(changed=st.sets(st.sampled_from(SETTINGS + SHAPES)),
       unknown=st.sets(st.sampled_from(SETTINGS + SHAPES)))
def test_a_resume_names_every_run_setting_that_differs(base_identity, changed, unknown):
    """Differences in run settings are named (all of them, both values); shapes that follow
    from the settings only when no setting differs; an entry either side lacks is skipped."""
    stored = {k: (_changed(k, v) if k in changed else v) for k, v in base_identity.items()}
    for key in unknown:
        stored[key] = None
    compared = changed - unknown
    message = describe_difference(stored, base_identity)
    if not compared:
        assert message == ''
        return
    named = [k for k in SETTINGS if k in compared] or [k for k in SHAPES if k in compared]
    assert '\n' not in message and message.startswith('was made with ')
    made, this = message[len('was made with '):].split('; this run has ')
    for key in SETTINGS + SHAPES:
        pattern = rf'(^|, ){key} '
        assert bool(re.search(pattern, made)) is (key in named), (key, message)
        assert bool(re.search(pattern, this)) is (key in named), (key, message)


plain = st.recursive(
    st.none() | st.booleans() | st.integers(-3, 10) | st.floats(allow_nan=False)
    | st.text(max_size=8),
    lambda inner: st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=6), inner,
                                                                max_size=3),
    max_leaves=8)


ENTRIES = ('learner', 'episode', 'history', 'identity', 'env_rng', 'made_by', 'run')


@st.composite
def checkpoint_payloads(draw) -> dict:
    """A well-formed checkpoint's entries with one or two replaced by any plain data, or one
    left out: each wrong entry among right ones."""
    done = draw(st.integers(0, 2))
    payload = {'learner': {}, 'episode': done, 'history': [{'episode': i} for i in range(done)],
               'identity': None, 'env_rng': None}
    payload.update(draw(st.dictionaries(st.sampled_from(ENTRIES), plain, max_size=2)))
    for entry in draw(st.sets(st.sampled_from(ENTRIES), max_size=1)):
        payload.pop(entry, None)
    return payload


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(payload=checkpoint_payloads())
def test_any_plain_file_is_read_or_refused_in_one_line(base_identity, payload):
    """Whatever plain data a checkpoint holds, reading it for a resume either succeeds with
    well-formed entries or raises CheckpointError: one line naming the file."""
    with tempfile.TemporaryDirectory() as directory:
        path = Path(directory) / 'checkpoint.pt'
        save_payload(path, payload)
        try:
            checkpoint = read_checkpoint(path, identity=base_identity)
        except CheckpointError as exc:
            assert str(exc).startswith(f'resume: {path}') and '\n' not in str(exc)
        else:
            assert isinstance(checkpoint.learner, dict)
            assert checkpoint.episode == len(checkpoint.history) >= 0
            assert checkpoint.env_rng is None or isinstance(checkpoint.env_rng, dict)


def test_a_checkpoint_older_than_its_identity_is_still_checked(tmp_path, base_identity):
    """A checkpoint written before it recorded its identity: the learner's own configuration
    and buffer widths still tell mode, network and shapes."""
    _, _, learner, _ = build_run(tiny_run(tmp_path))
    path = tmp_path / 'checkpoint.pt'
    save_payload(path, {'learner': learner.state_dict(), 'episode': 0, 'history': [],
                        'env_rng': None, 'run': {'system': 'unicycle'}})
    assert read_checkpoint(path, identity=base_identity).episode == 0
    other = {**base_identity, 'hidden_sizes': [64, 64], 'obs_dim': 9}
    with pytest.raises(CheckpointError, match=r'^resume: \S+ was made with hidden_sizes '
                                              r'\[16, 16\]; this run has hidden_sizes '
                                              r'\[64, 64\]$'):
        read_checkpoint(path, identity=other)
    with pytest.raises(CheckpointError, match='was made with system unicycle; this run has '
                                              'system pvtol$'):
        read_checkpoint(path, identity={**base_identity, 'system': 'pvtol'})


# --------------------------------------------------------------------------- rcbf_ros train
@pytest.mark.parametrize('change, named', [
    (dict(system='pvtol'), 'system unicycle'),
    (dict(system='car_following'), 'system unicycle'),
    (dict(learner=tiny_learner(mode='diff')), 'mode baseline'),
    (dict(learner=tiny_learner(sac=SACConfig(hidden_sizes=(32, 32)))),
     'hidden_sizes [16, 16]'),
    (dict(learner=tiny_learner(buffer_size=5000)), 'buffer_size 200000'),
    (dict(learner=tiny_learner(policy_min=(0.0, -1.0), policy_max=(1.0, 1.0))),
     'policy_low [0.0, -2.5], policy_high [2.5, 2.5]'),
])
def test_a_resume_with_other_settings_is_refused_before_any_tensor_is_loaded(
        one_episode, tmp_path, monkeypatch, change, named):
    out = copy_of(one_episode, tmp_path)
    before = {p.name: p.read_bytes() for p in out.iterdir()}

    def never(self, state):
        raise AssertionError('a tensor was loaded before the settings were compared')

    monkeypatch.setattr(SafeLearner, 'load_state_dict', never)
    with pytest.raises(RunSetupError) as refused:
        train(tiny_run(out, episodes=2, resume=True, **change), log=lambda _: None)
    line = str(refused.value)
    assert line.startswith(f"resume: {out / 'checkpoint.pt'} was made with {named}; this run "
                           'has ') and '\n' not in line
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before


def test_the_cli_refuses_another_system_in_one_line_exit_2(one_episode, tmp_path, capsys):
    out = copy_of(one_episode, tmp_path)
    assert cli_main(['train', '--system', 'pvtol', '--mode', 'baseline', '--episodes', '2',
                     '--max-steps', '30', '--no-bag', '--out', str(out), '--resume']) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"error: resume: {out / 'checkpoint.pt'} was made with system "
                          'unicycle') and err.count('\n') == 1 and 'Traceback' not in err


def test_a_write_failing_mid_run_closes_the_bag_and_writes_nothing_more(tmp_path, monkeypatch):
    """The bag's disk fills during episode 2: the run stops with RunWriteError naming the
    file, closes its bag, and leaves episode 1's checkpoint as it was (no policy, no plots,
    no second attempt at a checkpoint)."""
    out = tmp_path / 'run'
    calls = {'step': 0, 'close': 0}
    real_step, real_close = loop.RunRecorder.step, loop.RunRecorder.close

    def step(self, *args, **kwargs):
        calls['step'] += 1
        if calls['step'] == 45:
            raise OSError(errno.ENOSPC, 'No space left on device',
                          str(out / 'bag_0000' / 'bag_0000_0.mcap'))
        return real_step(self, *args, **kwargs)

    def close(self):
        calls['close'] += 1
        return real_close(self)

    monkeypatch.setattr(loop.RunRecorder, 'step', step)
    monkeypatch.setattr(loop.RunRecorder, 'close', close)
    checkpoints = []
    real_write = run_module.write_checkpoint
    monkeypatch.setattr(run_module, 'write_checkpoint',
                        lambda path, **kw: checkpoints.append(kw['episode']) or
                        real_write(path, **kw))
    with pytest.raises(RunWriteError) as stopped:
        train(tiny_run(out, episodes=3, record_bag=True), log=lambda _: None)
    assert str(stopped.value) == (
        f"{out / 'bag_0000' / 'bag_0000_0.mcap'}: No space left on device; the run stopped "
        '(checkpoint.pt holds 1 episode(s); --resume continues from it)')
    assert calls['close'] == 1 and checkpoints == [1]
    assert load_payload(out / 'checkpoint.pt')['episode'] == 1
    assert not (out / 'policy.pt').exists() and not list(out.glob('*.png'))
    assert not list(out.rglob('*.partial'))


# --------------------------------------------------------------------------- atomic writes
def test_a_write_past_the_file_size_limit_leaves_the_old_file_and_no_partial(tmp_path):
    path = tmp_path / 'checkpoint.pt'
    write_atomically(path, b'old contents')
    soft, hard = resource.getrlimit(resource.RLIMIT_FSIZE)
    previous = signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    resource.setrlimit(resource.RLIMIT_FSIZE, (4096, hard))
    try:
        with pytest.raises(OSError) as failed:
            save_payload(path, {'w': torch.zeros(10_000)})
    finally:
        resource.setrlimit(resource.RLIMIT_FSIZE, (soft, hard))
        signal.signal(signal.SIGXFSZ, previous)
    assert failed.value.errno == errno.EFBIG
    assert describe_write_error(failed.value) == f'{path}: File too large'
    assert path.read_bytes() == b'old contents'
    assert sorted(os.listdir(tmp_path)) == ['checkpoint.pt']
