"""rcbf_ros launch with real nodes over loopback DDS when something goes wrong: a bad params file,
a recorder that cannot record, a sibling SIGKILLed, SIGINT to a launcher started in the
background. Every case ends with the right exit code and without a traceback."""
from __future__ import annotations

import ast
import os
from pathlib import Path
import shlex
import signal
import subprocess
import sys
import threading
import time

from dds_harness import end_process, node_runtime  # this directory: on sys.path for pytest
import pytest

REPO = Path(__file__).resolve().parents[2]
LAUNCH = (sys.executable, '-m', 'rcbf_ros.launch.local')
WAIT_S = 90.0
"""Upper bound for a launch to come up or stop on a loaded machine (a hang, not a speed test)."""

pytestmark = pytest.mark.integration


def _env(domain_id: int) -> dict[str, str]:
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain_id), RCBF_ROS_RUNTIME=node_runtime(),
               PYTHONUNBUFFERED='1')
    env['PYTHONPATH'] = os.pathsep.join(filter(None, [str(REPO), env.get('PYTHONPATH')]))
    return env


class Launch:
    """A launcher process in its own process group, its output collected line by line."""

    def __init__(self, args: list[str], domain_id: int) -> None:
        self.process = subprocess.Popen([*LAUNCH, *args], env=_env(domain_id), cwd=REPO,
                                        stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                        text=True, start_new_session=True)
        self.lines: list[str] = []
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        for line in self.process.stdout:
            self.lines.append(line.rstrip('\n'))

    @property
    def output(self) -> str:
        return '\n'.join(self.lines)

    def wait_for(self, *texts: str) -> None:
        deadline = time.monotonic() + WAIT_S
        while not all(t in self.output for t in texts):
            assert self.process.poll() is None, f'launch ended early:\n{self.output[-3000:]}'
            assert time.monotonic() < deadline, f'never saw {texts}:\n{self.output[-3000:]}'
            time.sleep(0.1)

    def child_pid(self, module: str) -> int:
        for name in os.listdir('/proc'):
            if not name.isdigit():
                continue
            try:
                with open(f'/proc/{name}/stat') as stat:
                    parent = int(stat.read().rsplit(')', 1)[1].split()[1])
                with open(f'/proc/{name}/cmdline') as cmdline:
                    words = cmdline.read().split('\0')
            except (OSError, IndexError, ValueError):
                continue
            if parent == self.process.pid and module in words:
                return int(name)
        raise AssertionError(f'no child running {module}')

    def finish(self) -> int:
        """The exit code; a launch that does not stop by itself fails the test (and is killed)."""
        try:
            code = self.process.wait(timeout=WAIT_S)
        except subprocess.TimeoutExpired:
            # SIGTERM: the launcher stops its children; SIGKILL as a last resort.
            end_process(self.process, sig=signal.SIGTERM, timeout=30.0)
            pytest.fail(f'the launch did not stop:\n{self.output[-3000:]}')
        self._reader.join(timeout=5.0)
        return code


def _last_line(output: str) -> str:
    return [line for line in output.splitlines() if line.startswith('[launch] stopped')][-1]


def _return_codes(output: str) -> dict[str, int]:
    return ast.literal_eval(_last_line(output).split('return codes ')[1].split(';')[0])


def test_a_missing_params_file_is_refused_before_anything_starts(tmp_path, ros_domain_id):
    result = subprocess.run([*LAUNCH, 'unicycle_filter', '--params-file',
                             str(tmp_path / 'missing.yaml')], env=_env(ros_domain_id), cwd=REPO,
                            capture_output=True, text=True, timeout=60)
    assert result.returncode == 2
    assert result.stdout == ''  # not one node line, not even the launcher's summary
    assert result.stderr.splitlines() == [
        f"rcbf_ros launch: --params-file '{tmp_path / 'missing.yaml'}': "
        'No such file or directory']


def test_a_recorder_that_cannot_record_stops_the_launch(tmp_path, ros_domain_id):
    bag = tmp_path / 'bag'
    bag.mkdir()
    (bag / 'metadata.yaml').write_text('rosbag2_bagfile_information: {}\n')
    launch = Launch(['unicycle_filter', '-p', f'recorder:output:={bag}',
                     '-p', 'simulator:max_episodes:=1'], ros_domain_id)
    code = launch.finish()
    output = launch.output
    assert code == 1, output[-3000:]
    recorder = [line for line in launch.lines if line.startswith('[recorder]')]
    assert len(recorder) == 1 and recorder[0].startswith('[recorder] recorder: cannot record: ')
    assert str(bag) in recorder[0]
    assert '[launch] recorder failed: exited with 2' in output
    assert 'Traceback' not in output and 'sending SIGTERM' not in output
    # Every other node stopped when asked, quietly: 0, 130 while it still imported, or killed
    # by SIGINT before Python had started; not SIGABRT from a KeyboardInterrupt inside torch.
    codes = _return_codes(output)
    assert codes.pop('recorder') == 2
    assert set(codes.values()) <= {0, 130, -signal.SIGINT}, output[-3000:]


def test_stopping_after_a_sibling_was_killed_keeps_within_every_limit(tmp_path, ros_domain_id):
    # The recorder reads every topic; SIGKILLed, it leaves the simulator's six reliable writers
    # with samples it will never acknowledge. Stopping must not wait on them past the limit.
    launch = Launch(['unicycle_filter', '-p', f'recorder:output:={tmp_path / "bag"}'],
                    ros_domain_id)
    launch.wait_for('recording /state', 'recording /sim/step', 'recording /cmd_safe')
    time.sleep(1.0)  # traffic in flight
    os.kill(launch.child_pid('rcbf_ros.ros.recorder_node'), signal.SIGKILL)
    code = launch.finish()
    output = launch.output
    assert code == 1, output[-3000:]
    assert '[launch] recorder failed: exited with -9' in output
    assert 'Traceback' not in output, output[-3000:]
    assert 'sending SIGTERM' not in output and 'when asked to stop' not in output, output[-3000:]
    codes = _return_codes(output)
    assert codes == {'recorder': -signal.SIGKILL, 'simulator': 0, 'safety_filter': 0,
                     'nominal_controller': 0, 'scene_markers': 0}


def test_a_launcher_started_in_the_background_stops_on_sigint(tmp_path, ros_domain_id):
    # A shell starts `cmd &` with SIGINT ignored; the launcher must still stop on it.
    out = tmp_path / 'launch.txt'
    command = shlex.join([*LAUNCH, 'unicycle_filter', '--without', 'simulator', '--without',
                        'safety_filter', '--without', 'nominal_controller',
                        '-p', f'recorder:output:={tmp_path / "bag"}'])
    pid_file = tmp_path / 'launch.pid'
    script = f"""
        {command} > {out} 2>&1 &
        pid=$!
        echo $pid > {pid_file}
        for i in $(seq 600); do
            grep -q 'recording all topics' {out} && break
            sleep 0.1
        done
        kill -INT $pid
        wait $pid
    """
    shell = subprocess.Popen(['bash', '-c', script], env=_env(ros_domain_id), cwd=REPO,
                             start_new_session=True)
    try:
        code = shell.wait(timeout=WAIT_S)
    except subprocess.TimeoutExpired:
        os.kill(int(pid_file.read_text()), signal.SIGTERM)
        shell.wait(timeout=30)
        pytest.fail(f'SIGINT did not stop the launcher:\n{out.read_text()[-3000:]}')
    output = out.read_text()
    assert code == 0, output[-3000:]
    assert 'Traceback' not in output
    assert '[recorder]' in output and f'bag {tmp_path / "bag"} closed' in output
    assert _last_line(output).endswith('exit code 0')
