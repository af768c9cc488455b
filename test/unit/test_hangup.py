"""SIGHUP (a terminal closing, a dropped ssh connection) asks a node to stop as SIGTERM does: the
callback under way finishes, the exit work runs, status 0; where the process started with
SIGHUP ignored (nohup) it stays ignored."""
from __future__ import annotations

import os
import signal
from typing import Any

import pytest

from rcbf_ros.ros.node_main import request_stop, run_node, stop_signals


def _worker(ticks: list[bool], *, hang_up_at: int, stop_at: int | None = None) -> Any:
    from rcbf_ros.ros.runtime import Node, rclpy

    class Worker(Node):
        def __init__(self) -> None:
            super().__init__('worker')
            self.create_timer(0.01, self.tick)

        def tick(self) -> None:
            if len(ticks) == hang_up_at:
                os.kill(os.getpid(), signal.SIGHUP)
            ticks.append(rclpy.ok())
            if stop_at is not None and len(ticks) >= stop_at:
                request_stop()
    return Worker


def test_a_hangup_during_a_callback_stops_the_node_with_its_exit_work(ros_domain_id):
    ticks: list[bool] = []
    exits: list[str] = []
    unhandled: list[int] = []  # a hangup the node did not take lands here, not in pytest's death
    before = signal.signal(signal.SIGHUP, lambda signum, frame: unhandled.append(signum))
    try:
        code = run_node('worker', _worker(ticks, hang_up_at=2, stop_at=6), ['worker'],
                        on_exit=lambda node: exits.append(node.get_name()))
        given_back = signal.getsignal(signal.SIGHUP)
    finally:
        signal.signal(signal.SIGHUP, before)
    assert code == 0 and not unhandled
    assert ticks == [True] * 3        # the callback under way finished, no other ran
    assert exits == ['worker']        # the exit work ran
    assert given_back.__name__ == '<lambda>'  # the handler it had before, given back


def test_a_hangup_stays_ignored_where_the_process_ignores_it(ros_domain_id):
    ticks: list[bool] = []
    previous = signal.signal(signal.SIGHUP, signal.SIG_IGN)  # as nohup starts a process
    try:
        assert signal.SIGHUP not in stop_signals()
        code = run_node('worker', _worker(ticks, hang_up_at=2, stop_at=6), ['worker'])
        assert signal.getsignal(signal.SIGHUP) == signal.SIG_IGN
    finally:
        signal.signal(signal.SIGHUP, previous)
    assert code == 0 and len(ticks) == 6  # went on past the hangup until it asked to stop


@pytest.mark.parametrize('handler', [signal.SIG_DFL, lambda *_: None])
def test_a_hangup_is_a_stop_signal_unless_ignored(handler):
    previous = signal.signal(signal.SIGHUP, handler)
    try:
        assert stop_signals() == (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)
    finally:
        signal.signal(signal.SIGHUP, previous)
