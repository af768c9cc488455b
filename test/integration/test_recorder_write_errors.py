"""The recorder process under a file size limit (``RLIMIT_FSIZE``, ``ulimit -f``), fed over
loopback DDS: one error line, no traceback, the node runs on, a bag every reader takes as it is,
and exit status 1 once stopped."""
from __future__ import annotations

from pathlib import Path
import resource
import signal
import subprocess
import sys
import time

from dds_harness import end_process, subprocess_env  # this directory: on sys.path for pytest
import pytest
from rosbags.highlevel import AnyReader
from test_recorder import _STREAMING_PUBLISHER

from rcbf_ros.bag.recover import main as bag_command
from rcbf_ros.messages.typestore import jazzy_typestore

pytestmark = pytest.mark.integration

LIMIT = 40_000
WAIT_S = 60.0


def _limited() -> None:
    signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    resource.setrlimit(resource.RLIMIT_FSIZE, (LIMIT, LIMIT))


def test_recorder_under_a_file_size_limit_stops_recording_and_runs_on(
        tmp_path: Path, ros_domain_id: int, capsys) -> None:
    bag = tmp_path / 'bag'
    log_path = tmp_path / 'recorder.log'
    with open(log_path, 'w') as log:
        recorder = subprocess.Popen(
            [sys.executable, '-m', 'rcbf_ros.ros.recorder_node', '--ros-args',
             '-p', f'output:={bag}', '-p', 'flush_period_s:=0.2', '-p', 'chunk_size:=4096',
             '-p', 'discovery_period_s:=0.3', '-p', "topics:=['/state']"],
            env=subprocess_env(ros_domain_id), stdout=log, stderr=subprocess.STDOUT,
            preexec_fn=_limited)
    publisher = subprocess.Popen([sys.executable, '-c', _STREAMING_PUBLISHER],
                                 env=subprocess_env(ros_domain_id), stdout=subprocess.DEVNULL,
                                 stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + WAIT_S
        while 'recording stopped' not in log_path.read_text():
            assert recorder.poll() is None, log_path.read_text()
            assert time.monotonic() < deadline, log_path.read_text()
            time.sleep(0.2)
        time.sleep(0.5)  # it runs on, not recording
        assert recorder.poll() is None, log_path.read_text()
        code = end_process(recorder, sig=signal.SIGINT)
    finally:
        end_process(recorder, sig=signal.SIGKILL)
        end_process(publisher, sig=signal.SIGKILL)
    text = log_path.read_text()
    assert code == 1, text
    assert 'Traceback' not in text, text
    errors = [line for line in text.splitlines() if 'EFBIG' in line]
    assert len(errors) == 1, text
    assert 'recording stopped: cannot write' in errors[0] and str(bag) in errors[0]
    assert 'goes on without recording' in errors[0]

    (mcap,) = bag.glob('*.mcap')
    assert mcap.stat().st_size <= LIMIT and (bag / 'metadata.yaml').is_file()
    with AnyReader([bag], default_typestore=jazzy_typestore()) as reader:
        states = [list(reader.deserialize(raw, c.msgtype).data)
                  for c, _, raw in reader.messages()]
    # Of 40 kB, all but the last chunk (4 kB) and the closing records (~3 kB) hold messages of
    # ~70 bytes each in the file.
    assert len(states) > 300
    assert states == [[float(i), 2.0 * i] for i in range(len(states))]
    capsys.readouterr()
    assert bag_command(['check', str(bag)]) == 0
    assert f'intact, {len(states)} messages' in capsys.readouterr().out
