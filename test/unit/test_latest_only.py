"""The latest-only worker: a job submitted while another waits replaces it, the one running is
finished, outcomes come back in order, a defect of the work is kept as an error, nothing runs
after close. Jobs are gated by events, so that no assertion depends on timing."""
from __future__ import annotations

import threading

from hypothesis import given, settings
from hypothesis import strategies as st
import pytest

from rcbf_ros.node_logic.latest_only import LatestOnlyWorker

WAIT_S = 30.0


class GatedWork:
    """``work(job)``: says it started, then waits for its gate (a job of ``'boom'`` raises)."""

    def __init__(self) -> None:
        self.started: list[object] = []
        self.gates: dict[object, threading.Event] = {}
        self.started_event = threading.Condition()
        self.notified = 0

    def gate(self, job: object) -> threading.Event:
        return self.gates.setdefault(job, threading.Event())

    def __call__(self, job: object) -> object:
        with self.started_event:
            self.started.append(job)
            self.started_event.notify_all()
        assert self.gate(job).wait(WAIT_S)
        if job == 'boom':
            raise RuntimeError('a defect\nover two lines')
        return ('built', job)

    def wait_started(self, job: object) -> None:
        with self.started_event:
            assert self.started_event.wait_for(lambda: job in self.started, WAIT_S)

    def notify(self) -> None:
        self.notified += 1


@pytest.fixture
def gated():
    work = GatedWork()
    worker = LatestOnlyWorker(work, notify=work.notify, name='test')
    yield work, worker
    worker.close()
    for gate in work.gates.values():
        gate.set()


def test_jobs_submitted_while_one_runs_leave_only_the_newest(gated):
    work, worker = gated
    assert not worker.submit(1)
    work.wait_started(1)
    assert not worker.submit(2) and worker.submit(3) and worker.submit(4)
    assert worker.busy and worker.superseded == 2
    work.gate(1).set()
    work.wait_started(4)
    work.gate(4).set()
    assert worker.wait_idle(WAIT_S)
    assert work.started == [1, 4]
    assert [(f.job, f.result, f.error) for f in worker.take()] == [
        (1, ('built', 1), ''), (4, ('built', 4), '')]
    assert worker.take() == [] and work.notified == 2 and not worker.busy


def test_a_defect_of_the_work_is_kept_and_the_worker_goes_on(gated):
    work, worker = gated
    work.gate('boom').set()
    work.gate('next').set()
    worker.submit('boom')
    assert worker.wait_idle(WAIT_S)
    worker.submit('next')
    assert worker.wait_idle(WAIT_S)
    first, second = worker.take()
    assert first.result is None and first.error == 'RuntimeError: a defect\nover two lines'
    assert second.result == ('built', 'next') and not second.error


def test_nothing_runs_or_comes_back_after_close(gated):
    work, worker = gated
    worker.submit(1)
    work.wait_started(1)
    worker.submit(2)
    worker.close()
    assert not worker.submit(3)
    work.gate(1).set()
    assert worker.wait_idle(WAIT_S)
    assert work.started == [1] and worker.take() == []


def test_a_negative_rest_is_refused():
    with pytest.raises(ValueError, match='rest_ratio'):
        LatestOnlyWorker(lambda job: job, notify=lambda: None, rest_ratio=-1.0)


@settings(max_examples=25, deadline=None)
@given(batches=st.lists(st.lists(st.integers(), min_size=1, max_size=5), min_size=1,
                        max_size=5))
def test_each_batch_submitted_during_a_job_is_built_as_its_last_job(batches):
    """Batches submitted while the previous batch's survivor runs: the survivors are the
    first job and the last of every later batch, each built once, in order."""
    work = GatedWork()
    worker = LatestOnlyWorker(work, notify=work.notify)
    jobs = [[(b, i, job) for i, job in enumerate(batch)] for b, batch in enumerate(batches)]
    try:
        first, *rest = jobs[0]
        worker.submit(first)
        work.wait_started(first)
        expected, running = [first], first
        for batch in [rest, *jobs[1:]]:
            if not batch:
                continue
            for job in batch:
                worker.submit(job)
            work.gate(running).set()
            running = batch[-1]
            work.wait_started(running)
            expected.append(running)
        work.gate(running).set()
        assert worker.wait_idle(WAIT_S)
        assert work.started == expected
        assert [f.job for f in worker.take()] == expected
    finally:
        worker.close()
        for gate in work.gates.values():
            gate.set()
