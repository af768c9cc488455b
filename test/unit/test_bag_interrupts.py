"""Ctrl-C or SIGTERM at any moment of a recording loses no message whose write returned: under
:func:`rcbf_ros.bag.interrupts.interrupts_raise` a signal waits for the bag write it lands in."""
from __future__ import annotations

import contextlib
import errno
import json
import os
from pathlib import Path
import signal
import subprocess
import sys
import textwrap
import threading

import pytest

from rcbf_ros.bag import interrupts

#: Writes messages until a signal, sent after a random delay, stops them; closes the bag and
#: reads it back. Small zstd chunks: a chunk is closed every few messages, so the signal often
#: lands while one is compressed and written out.
_TRIALS = textwrap.dedent("""
    import json, os, random, signal, sys, tempfile, threading
    from pathlib import Path
    from mcap.reader import make_reader
    from rcbf_ros.bag import BagWriter, BagWriterConfig
    from rcbf_ros.bag.interrupts import interrupts_raise
    trials, seed = int(sys.argv[1]), int(sys.argv[2])
    rng = random.Random(seed)
    root = Path(tempfile.mkdtemp())
    results = []
    signal.signal(signal.SIGINT, signal.default_int_handler)  # a background run ignores it
    with interrupts_raise():
        for trial in range(trials):
            bag = BagWriter(root / f'b{trial}', config=BagWriterConfig(
                chunk_size=600, compression='zstd'))
            bag.add_topic('/x', 'std_msgs/msg/Float64MultiArray')
            returned = 0
            signum = rng.choice([signal.SIGINT, signal.SIGTERM])
            timer = threading.Timer(rng.uniform(0.0, 0.02), os.kill, (os.getpid(), signum))
            try:
                timer.start()
                while True:
                    bag.write_message('/x', {'data': [float(returned)] * 8}, returned)
                    returned += 1
            except KeyboardInterrupt:
                pass
            timer.join()
            bag.close()
            with open(root / f'b{trial}' / f'b{trial}_0.mcap', 'rb') as stream:
                times = [m.log_time for _, _, m in make_reader(stream).iter_messages()]
            results.append([returned, times == list(range(len(times)))
                            and len(times) in (returned, returned + 1)])
    print(json.dumps(results))
""")


def test_a_signal_during_writes_loses_no_message_whose_write_returned():
    out = subprocess.run([sys.executable, '-c', _TRIALS, '150', '7'], capture_output=True,
                         text=True, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    results = json.loads(out.stdout)
    assert len(results) == 150
    # Every message is there, in order: those whose write returned and, when the signal landed
    # in a write, that one too (it finished before the interrupt was raised).
    lost = [returned for returned, kept in results if not kept]
    assert not lost
    written = [returned for returned, _ in results]
    assert max(written) > 50  # signals landed after many chunks had been written out


def test_a_signal_inside_nested_sections_is_raised_as_the_outermost_ends():
    with pytest.raises(KeyboardInterrupt):
        with interrupts.held:
            with interrupts.held:
                interrupts.on_interrupt(2, None)
                reached = True
            assert reached  # the inner end does not raise
    assert interrupts.held.depth == 0 and interrupts.held.pending is None
    with pytest.raises(KeyboardInterrupt):
        interrupts.on_interrupt(2, None)  # outside a section: at once


def test_another_thread_s_section_does_not_hold_the_main_thread_s_signal():
    inside, leave = threading.Event(), threading.Event()

    def writer():
        with interrupts.held:
            inside.set()
            leave.wait(10)
    thread = threading.Thread(target=writer)
    thread.start()
    inside.wait(10)
    try:
        with pytest.raises(KeyboardInterrupt):
            interrupts.on_interrupt(2, None)
    finally:
        leave.set()
        thread.join()


def test_a_sigint_the_process_ignores_stays_ignored_and_the_handlers_come_back():
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    before_term = signal.getsignal(signal.SIGTERM)
    try:
        with interrupts.interrupts_raise():
            assert signal.getsignal(signal.SIGINT) == signal.SIG_IGN
            assert signal.getsignal(signal.SIGTERM) is interrupts.on_interrupt
        assert signal.getsignal(signal.SIGTERM) is before_term
        signal.signal(signal.SIGINT, signal.default_int_handler)
        with interrupts.interrupts_raise(signal.SIGINT):
            assert signal.getsignal(signal.SIGINT) is interrupts.on_interrupt
        assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
    finally:
        signal.signal(signal.SIGINT, previous)


def test_a_count_left_behind_does_not_hold_the_next_blocks_signals():
    interrupts.held.depth = 3  # as an interrupt between the count and a section's end leaves
    try:
        with interrupts.interrupts_raise(signal.SIGINT):
            with pytest.raises(KeyboardInterrupt):
                interrupts.on_interrupt(signal.SIGINT, None)
    finally:
        interrupts.held.depth, interrupts.held.pending = 0, None


def test_an_interrupt_while_a_run_s_bag_registers_its_topics_closes_the_bag(tmp_path,
                                                                            monkeypatch):
    from rcbf_ros.bag import bag_info, BagWriter
    from rcbf_ros.training.recorder import RunRecorder
    calls = []
    add_topic = BagWriter.add_topic

    def interrupted(self, *args, **kwargs):
        calls.append(args[0])
        if len(calls) == 3:
            raise KeyboardInterrupt
        return add_topic(self, *args, **kwargs)
    monkeypatch.setattr(BagWriter, 'add_topic', interrupted)
    with pytest.raises(KeyboardInterrupt):
        RunRecorder(tmp_path / 'bag')
    assert (tmp_path / 'bag' / 'metadata.yaml').is_file()  # closed: footer and metadata
    assert sorted(bag_info(tmp_path / 'bag', allow_cut_short=False).topics) == sorted(calls[:2])


def _failing_write(fail_at: int):
    """``os.pwrite`` that, at its ``fail_at``-th call, takes a SIGINT and then fails with ENOSPC
    (a Ctrl-C landing in the write that meets a full disk)."""
    import errno
    import os
    calls = [0]
    pwrite = os.pwrite

    def write(fd, data, offset):
        calls[0] += 1
        if calls[0] == fail_at:
            os.kill(os.getpid(), signal.SIGINT)
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return pwrite(fd, data, offset)
    return write


def test_a_signal_held_by_a_write_that_fails_lets_the_error_out(tmp_path, monkeypatch):
    from rcbf_ros.bag import BagWriter, BagWriterConfig
    from rcbf_ros.bag import writer as writer_module
    from rcbf_ros.bag.writer import BagWriteError
    signal.signal(signal.SIGINT, signal.default_int_handler)
    monkeypatch.setattr(writer_module.os, 'pwrite', _failing_write(3))
    bag = BagWriter(tmp_path / 'b', config=BagWriterConfig(chunk_size=64, compression='none'))
    bag.add_topic('/x', 'std_msgs/msg/Float64MultiArray')
    with pytest.raises(BagWriteError) as failed:  # not the KeyboardInterrupt it held
        with interrupts.interrupts_raise(signal.SIGINT):
            for i in range(100):
                bag.write_message('/x', {'data': [1.0] * 8}, i)
    assert failed.value.errno == errno.ENOSPC and interrupts.held.owed is None
    # the stop is not lost: where the program handles the error and goes on, it comes at the
    # end of the block
    bag = BagWriter(tmp_path / 'c', config=BagWriterConfig(chunk_size=64, compression='none'))
    bag.add_topic('/x', 'std_msgs/msg/Float64MultiArray')
    monkeypatch.setattr(writer_module.os, 'pwrite', _failing_write(2))
    with pytest.raises(KeyboardInterrupt):
        with interrupts.interrupts_raise(signal.SIGINT):
            with contextlib.suppress(BagWriteError):
                for i in range(100):
                    bag.write_message('/x', {'data': [1.0] * 8}, i)
            reached = True
    assert reached and interrupts.held.owed is None


def test_ctrl_c_in_a_train_bag_write_on_a_full_disk_exits_1_saying_so(tmp_path):
    # The disk is full: the run stops with the write's error (exit 1, one line), not as if
    # Ctrl-C had stopped a run whose files were all written (130).
    out = tmp_path / 'run'
    code = textwrap.dedent(f"""
        import os, runpy, sys
        sys.path.insert(0, {str(Path(__file__).parent)!r})
        from test_bag_interrupts import _failing_write
        os.pwrite = _failing_write(2)
        sys.argv = ['rcbf_ros', 'train', '--system', 'unicycle', '--mode', 'baseline',
                    '--max-steps', '30', '--start-steps', '20', '--update-after', '20',
                    '--batch-size', '16', '--episodes', '1', '--out', {str(out)!r}]
        runpy.run_module('rcbf_ros', run_name='__main__')
    """)
    done = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True,
                          timeout=180, env=dict(os.environ, OMP_NUM_THREADS='1'))
    assert done.returncode == 1, done.stderr[-3000:]
    (line,) = done.stderr.splitlines()
    assert line.startswith('error: ') and 'No space left on device' in line, line
