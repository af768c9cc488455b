"""How a node process starts and stops: params files refused at init in one line, a second
signal during clean-up, a SIGINT while the node still imports."""
from __future__ import annotations

import os
from pathlib import Path
import signal
import subprocess
import sys
import textwrap
import time
from typing import Any

import pytest

from rcbf_ros.ros.dds.context import Context, ExternalShutdownException
from rcbf_ros.ros.node_main import INTERRUPTED_EXIT, run_module, run_node

REPO = Path(__file__).resolve().parents[2]


# --- params file -------------------------------------------------------------------------------

@pytest.mark.parametrize('content, expected', [
    (None, 'No such file or directory'),
    ('a: [1\n', 'not valid YAML at line 2, column 1'),
    ('- 1\n', 'top level must map node names'),
])
def test_a_node_refuses_a_bad_params_file_in_one_line_before_joining_dds(tmp_path, capsys,
                                                                        content, expected):
    path = tmp_path / 'params.yaml'
    if content is not None:
        path.write_text(content)
    built = []
    code = run_node('probe', lambda: built.append(1),
                    ['probe', '--ros-args', '--params-file', str(path)])
    assert code == 2 and not built
    lines = capsys.readouterr().err.splitlines()
    assert len(lines) == 1 and lines[0].startswith(f'probe: --params-file {str(path)!r}: ')
    assert expected in lines[0]


@pytest.mark.parametrize('value, key', [('[]', 'obstacles.x'), ('{}', 'system_params')])
def test_an_empty_list_or_map_is_refused_naming_the_key_and_the_cause(
        tmp_path, capsys, ros_domain_id, monkeypatch, value, key):
    """rcl reads ``[]`` and ``{}`` as no value, which a node declaring its overrides cannot
    declare: one line naming the key and why, exit status 2."""
    from rcbf_ros.ros.dds.node import Node
    monkeypatch.setenv('ROS_DOMAIN_ID', str(ros_domain_id))
    path = tmp_path / 'params.yaml'
    name, last = key.split('.') if '.' in key else (key, None)
    nested = f'{name}: {{{last}: {value}}}' if last else f'{name}: {value}'
    path.write_text(f'/**:\n  ros__parameters:\n    gain: 1.0\n    {nested}\n')
    code = run_node('probe', lambda: Node(
        'probe', automatically_declare_parameters_from_overrides=True),
        ['probe', '--ros-args', '--params-file', str(path)], setup_errors=(ValueError,))
    lines = capsys.readouterr().err.splitlines()
    assert code == 2 and lines == [
        f'probe: invalid parameters: {key}: an empty list or map has no type in a params file '
        '(ROS 2 cannot declare it); leave the key out or give values'], lines


def test_rclpys_words_for_an_empty_value_get_the_key_from_the_command_line():
    """rclpy's message names no key: the first key given no value is named."""
    from rcbf_ros.ros.node_main import EMPTY_VALUE, setup_error_text
    rclpys = ValueError('Cannot declare a statically typed parameter with default value of '
                        'type PARAMETER_NOT_SET')
    argv = ['probe', '--ros-args', '-r', '__node:=other', '-p', 'a:=1', '-p', 'b:=[]',
            '-p', 'probe:c:=[]']
    assert setup_error_text(rclpys, 'probe', argv) == f'b: {EMPTY_VALUE}'
    assert setup_error_text(rclpys, 'probe', ['probe']) == str(rclpys)
    assert setup_error_text(ValueError('k_c: must be >= 0'), 'probe', argv) == 'k_c: must be >= 0'


def test_params_files_are_read_when_the_context_is_initialized(tmp_path, ros_domain_id):
    context = Context()
    with pytest.raises(ValueError, match='missing.yaml'):
        context.init(['--ros-args', '--params-file', str(tmp_path / 'missing.yaml')],
                     domain_id=ros_domain_id)
    assert not context.ok() and context.participant is None


# --- signals -----------------------------------------------------------------------------------

def test_a_second_signal_does_not_break_off_the_clean_up(ros_domain_id):
    # A launcher escalates SIGINT to SIGTERM; a node already stopping must finish its clean-up
    # (close a bag, write a checkpoint) rather than die half way with a traceback.
    context = Context()
    context.init([], domain_id=ros_domain_id)
    absorbed = []
    try:
        with pytest.raises(ExternalShutdownException):  # outside spin: raised at once
            os.kill(os.getpid(), signal.SIGTERM)
        assert not context.ok()
        for signum in (signal.SIGINT, signal.SIGTERM):  # during the clean-up
            try:
                os.kill(os.getpid(), signum)
                absorbed.append(signum)
            except (KeyboardInterrupt, ExternalShutdownException):
                pass
    finally:
        context.try_shutdown()
    assert absorbed == [signal.SIGINT, signal.SIGTERM]
    assert signal.getsignal(signal.SIGTERM) != context._on_signal  # handlers given back


def test_a_sigint_while_the_node_module_imports_ends_quietly(tmp_path, monkeypatch):
    (tmp_path / 'slow_import_node.py').write_text('raise KeyboardInterrupt\n')
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setattr(sys, 'argv', list(sys.argv))
    assert run_module(['slow_import_node', '--ros-args']) == INTERRUPTED_EXIT


def test_run_module_calls_the_node_main_with_its_arguments(tmp_path, monkeypatch):
    (tmp_path / 'echo_node.py').write_text(textwrap.dedent("""
        import sys
        def main():
            return len(sys.argv)
    """))
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setattr(sys, 'argv', list(sys.argv))
    before = signal.getsignal(signal.SIGINT)
    assert run_module(['echo_node', 'a', 'b']) == 3
    assert signal.getsignal(signal.SIGINT) is before  # the node's main runs with it


def test_a_sigint_before_the_node_handles_it_ends_quietly(tmp_path, monkeypatch):
    (tmp_path / 'early_node.py').write_text('def main():\n    raise KeyboardInterrupt\n')
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setattr(sys, 'argv', list(sys.argv))
    assert run_module(['early_node']) == INTERRUPTED_EXIT


def test_a_node_process_interrupted_while_importing_prints_no_traceback(tmp_path):
    # Inside torch's C++ start-up a KeyboardInterrupt aborts the process (SIGABRT); the
    # import must not see one at all.
    (tmp_path / 'importing_node.py').write_text(textwrap.dedent(f"""
        import pathlib, time
        pathlib.Path({str(tmp_path / 'importing')!r}).touch()
        try:
            time.sleep(30)  # stands in for importing torch
        except KeyboardInterrupt:
            raise SystemExit('a KeyboardInterrupt reached the import')
        def main():
            return 0
    """))
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(tmp_path), str(REPO)]))
    process = subprocess.Popen([sys.executable, '-m', 'rcbf_ros.ros.node_main', 'importing_node'],
                               env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    while not (tmp_path / 'importing').exists() and process.poll() is None:
        time.sleep(0.01)
    process.send_signal(signal.SIGINT)
    out, err = process.communicate(timeout=30)
    assert (process.returncode, out, err) == (INTERRUPTED_EXIT, '', '')


# --- stopping between callbacks -----------------------------------------------------------------

def test_a_signal_during_a_callback_lets_it_publish_and_runs_no_other(ros_domain_id):
    # rclpy's own handler shuts the context down at once; a callback's next publish then fails
    # with "publisher's context is invalid". Here the callback under way finishes with a valid
    # context, no other callback runs, and only then does the node shut down.
    from rcbf_ros.ros.runtime import get_message, Node, QoSProfile, rclpy
    calls: list[bool] = []
    built: list[Any] = []

    class Talker(Node):
        def __init__(self) -> None:
            super().__init__('talker')
            self.publisher = self.create_publisher(get_message('std_msgs/msg/String'),
                                                   'chatter', QoSProfile(depth=10))
            self.create_timer(0.01, self.tick)
            built.append(self)

        def tick(self) -> None:
            os.kill(os.getpid(), signal.SIGINT)  # Ctrl-C in the middle of this callback
            calls.append(rclpy.ok())
            self.publisher.publish(get_message('std_msgs/msg/String')(data='still valid'))

    before = signal.getsignal(signal.SIGINT)
    code = run_node('talker', Talker, ['talker'])
    assert code == 0
    assert calls == [True]                           # one callback, its context still valid
    assert built and not rclpy.ok()                  # and the shutdown came after it
    assert signal.getsignal(signal.SIGINT) is before  # handlers given back


def test_sigterm_during_a_callback_ends_the_same_way(ros_domain_id):
    from rcbf_ros.ros.runtime import Node, rclpy
    calls: list[bool] = []

    class Worker(Node):
        def __init__(self) -> None:
            super().__init__('worker')
            self.create_timer(0.01, self.tick)

        def tick(self) -> None:
            os.kill(os.getpid(), signal.SIGTERM)
            os.kill(os.getpid(), signal.SIGINT)  # a second signal while stopping: ignored
            calls.append(rclpy.ok())

    assert run_node('worker', Worker, ['worker']) == 0
    assert calls == [True]


def test_a_node_may_ask_to_stop_after_its_work(ros_domain_id):
    from rcbf_ros.ros.node_main import request_stop
    from rcbf_ros.ros.runtime import Node
    exits: list[str] = []

    class Finisher(Node):
        def __init__(self) -> None:
            super().__init__('finisher')
            self.ticks = 0
            self.create_timer(0.01, self.tick)

        def tick(self) -> None:
            self.ticks += 1
            if self.ticks == 3:
                request_stop()

    code = run_node('finisher', Finisher, ['finisher'],
                    on_exit=lambda node: exits.append(f'exit after {node.ticks}'))
    assert code == 0 and exits == ['exit after 3']


# --- a number out of range while the node is built ------------------------------------------

def _overflowing_node() -> Any:
    return int(float('inf'))  # as a period of 1 / 1e-300 s reaching a timer


def test_an_overflow_while_the_node_is_built_is_one_line_saying_where_exit_2(
        capsys, ros_domain_id, monkeypatch):
    monkeypatch.setenv('ROS_DOMAIN_ID', str(ros_domain_id))
    code = run_node('probe', _overflowing_node, ['probe'])
    lines = capsys.readouterr().err.splitlines()
    assert code == 2 and len(lines) == 1, lines
    assert lines[0].startswith('probe: invalid parameters: OverflowError: cannot convert float '
                               'infinity to integer (in _overflowing_node, '
                               'test/unit/test_node_startup_and_stop.py:')
    assert lines[0].endswith(': a number out of range)')


class _Built:
    def destroy_node(self) -> None:
        pass


def test_an_overflow_once_the_node_runs_is_not_taken_for_bad_input(ros_domain_id,
                                                                  monkeypatch):
    monkeypatch.setenv('ROS_DOMAIN_ID', str(ros_domain_id))

    def run(node: Any) -> None:
        raise OverflowError('in a callback')
    with pytest.raises(OverflowError, match='in a callback'):
        run_node('probe', _Built, ['probe'], run=run)
