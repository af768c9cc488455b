"""A large ``obstacles`` message over real Cyclone DDS (loopback): its filter is built off the
executor, so the filter in force keeps answering meanwhile, and of several quick messages the
newest ends in force.

A controller proposes at 100 Hz, each proposal numbered in its angular rate; ``filter_info``
says which proposal an answer answers (``u_rl``) and how many barriers answered it (``h``).
Not a timed test: the assertion counts the answers, to proposals sent after the message, that
the old filter made before the first answer of the new one. A build of 20,000 rows takes far
longer than the few proposal periods the slack allows (over 100 ms on a fast machine), and
with the build on the executor those proposals wait for it and are answered by the new
filter.
"""
from __future__ import annotations

import threading
import time
from typing import Any

from dds_harness import stop  # this directory: on sys.path for pytest
import numpy as np
import pytest
from test_safety_filter_node import _sections, _start_filter, _wait_matched, Probe
from test_safety_filter_node_runtime_changes import _array, _obstacles_publisher

pytestmark = pytest.mark.integration

FAR = [-3.0, 0.0, 0.0]
STEP = 1e-4
"""A proposal's number k is in its angular rate, k * STEP."""
OLD_BARRIERS = 5   # config/unicycle.yaml's obstacles
BIG = 20_000       # OBSTACLE_LIMIT: the longest build a message can ask for
SLACK = 5
"""Answers by the old filter to proposals sent after the message, at least; with the build on
the executor there are none but the few taken with the message."""


@pytest.fixture
def probe(ros_domain_id):
    instance = Probe(ros_domain_id)
    yield instance
    instance.close()


def _rows(count: int) -> list[float]:
    """``count`` circles of radius 0.2 far ahead of FAR, in a grid."""
    index = np.arange(count)
    return np.column_stack([5.0 + index % 200, 5.0 + index // 200,
                            np.full(count, 0.2)]).ravel().tolist()


class Controller:
    """States and numbered proposals at 100 Hz, in a thread."""

    def __init__(self, probe: Probe) -> None:
        from rcbf_ros.messages.conversions import sections_to_msg
        self._to_msg = sections_to_msg
        self.state_pub = probe.publisher('std_msgs/msg/Float64MultiArray', '/state')
        self.proposal_pub = probe.publisher('std_msgs/msg/Float64MultiArray', '/cmd_proposed')
        self.sent = 0
        self._running = True
        self._thread = threading.Thread(target=self._run, daemon=True)

    def start(self) -> None:
        self._thread.start()

    def _run(self) -> None:
        while self._running:
            self.state_pub.publish(self._to_msg({'state': FAR}))
            self.proposal_pub.publish(self._to_msg({'u': [1.0, (self.sent + 1) * STEP]}))
            self.sent += 1
            time.sleep(0.01)

    def stop(self) -> None:
        self._running = False
        self._thread.join(timeout=5)


def _answers(probe: Probe) -> list[tuple[int, int]]:
    """(proposal number, barriers) of every answer so far."""
    return [(round(info['u_rl'][1] / STEP), len(info.get('h', ())))
            for info in probe.wait_for('/filter_info', 0)]


def _wait(probe: Probe, process: Any, accept: Any, what: str) -> list[tuple[int, int]]:
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline:
        answers = _answers(probe)
        if accept(answers):
            return answers
        assert process.poll() is None, stop(process, timeout=10)
        time.sleep(0.02)
    raise AssertionError(f'{what}: {len(_answers(probe))} answers, the last {answers[-3:]}')


def test_the_filter_in_force_answers_while_a_big_set_is_built(ros_domain_id, probe):
    process = _start_filter(ros_domain_id)
    controller = None
    try:
        probe.subscribe('std_msgs/msg/Float64MultiArray', '/filter_info', _sections)
        obstacles_pub = _obstacles_publisher(probe)
        controller = Controller(probe)
        probe.start()
        for publisher in (controller.state_pub, controller.proposal_pub, obstacles_pub):
            _wait_matched(publisher, process)
        controller.start()
        _wait(probe, process, lambda a: sum(b == OLD_BARRIERS for _, b in a) >= 10,
              'answers by the filter at start')
        published_after = controller.sent   # proposals numbered above it follow the message
        obstacles_pub.publish(_array(_rows(BIG)))
        answers = _wait(probe, process, lambda a: any(b == BIG for _, b in a),
                        'an answer by the 20,000 obstacles')
        first_new = next(i for i, (_, b) in enumerate(answers) if b == BIG)
        meanwhile = [k for k, b in answers[:first_new]
                     if k > published_after and b == OLD_BARRIERS]
        assert len(meanwhile) >= SLACK, (len(meanwhile), answers[first_new - 5:first_new + 1])

        # several quick messages: the newest ends in force
        for count in (BIG, BIG // 2, 7):
            obstacles_pub.publish(_array(_rows(count)))
        answers = _wait(probe, process, lambda a: a[-1][1] == 7, 'an answer by the 7 obstacles')
        settled = len(answers)
        _wait(probe, process, lambda a: len(a) >= settled + 20, 'answers after the last set')
        assert all(b == 7 for _, b in _answers(probe)[settled - 1:])
    finally:
        if controller is not None:
            controller.stop()
        output = stop(process, timeout=10)
    assert 'Traceback' not in output, output[-3000:]
    assert output.count('filter updated from the obstacles topic') >= 2
