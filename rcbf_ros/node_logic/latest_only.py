"""One background thread for work that only its latest input needs: a node's long builds.

A node answers on one executor thread; work that takes longer than its answer period (the
filter of a 20,000-row ``obstacles`` message) runs here instead, and only the result is handed
back to the executor. Inputs that arrive while one waits replace it: at most one runs and one
waits, whatever the rate, so neither memory nor the delay grows with the input rate; after
each job the worker rests for a share of the job's time, so that a stream of inputs leaves
the executor its share of the CPU (and of Python's GIL).
"""
from __future__ import annotations

from dataclasses import dataclass
import threading
import time
from typing import Callable, Generic, TypeVar

Job = TypeVar('Job')
Result = TypeVar('Result')


@dataclass(frozen=True)
class Finished(Generic[Job, Result]):
    """One job's outcome, in the order the jobs ran."""

    job: Job
    """What was submitted."""
    result: Result | None
    """What ``work`` returned (None when it raised)."""
    error: str = ''
    """``<ExceptionType>: <message>`` of an exception ``work`` raised ('' when none)."""


class LatestOnlyWorker(Generic[Job, Result]):
    """Runs ``work(job)`` in one daemon thread for the latest job submitted.

    A job submitted while another waits replaces it (the replaced one never runs); the one
    running is finished and its outcome kept for :meth:`take`. ``notify`` is called in the
    worker's thread after each outcome is kept (e.g. a guard condition's ``trigger``, so that
    the executor takes it); it must not block. After a job of t seconds the next one starts no
    sooner than ``rest_ratio`` * t later: the worker runs at most 1 / (1 + ``rest_ratio``) of
    the time.
    """

    def __init__(self, work: Callable[[Job], Result], *, notify: Callable[[], None],
                 rest_ratio: float = 0.0, name: str = 'latest-only') -> None:
        if not rest_ratio >= 0:
            raise ValueError(f'rest_ratio: must be >= 0, got {rest_ratio!r}')
        self._work = work
        self._rest_ratio = float(rest_ratio)
        self._notify = notify
        self._name = name
        self._condition = threading.Condition()
        self._waiting: list[Job] = []
        self._running = False
        self._finished: list[Finished[Job, Result]] = []
        self._closed = False
        self._thread: threading.Thread | None = None
        self.superseded = 0
        """Jobs replaced before they ran."""

    def submit(self, job: Job) -> bool:
        """Queue ``job`` in place of any job still waiting; True if one was replaced. Nothing
        runs after :meth:`close`."""
        with self._condition:
            if self._closed:
                return False
            replaced = bool(self._waiting)
            self.superseded += replaced
            self._waiting[:] = [job]
            if self._thread is None:
                self._thread = threading.Thread(target=self._loop, name=self._name,
                                                daemon=True)
                self._thread.start()
            self._condition.notify()
        return replaced

    def take(self) -> list[Finished[Job, Result]]:
        """The outcomes kept since the last call, oldest first."""
        with self._condition:
            finished, self._finished = self._finished, []
        return finished

    @property
    def busy(self) -> bool:
        """True while a job waits or runs."""
        with self._condition:
            return bool(self._waiting) or self._running

    def wait_idle(self, timeout_s: float) -> bool:
        """Wait up to ``timeout_s`` until no job waits or runs; True if none does."""
        with self._condition:
            return self._condition.wait_for(
                lambda: not self._waiting and not self._running, timeout_s)

    def close(self) -> None:
        """Run nothing more (a job running finishes, its outcome is dropped)."""
        with self._condition:
            self._closed = True
            self._waiting.clear()
            self._condition.notify_all()

    def _loop(self) -> None:
        while True:
            with self._condition:
                self._condition.wait_for(lambda: self._waiting or self._closed)
                if self._closed:
                    return
                job = self._waiting.pop()
                self._running = True
            started = time.monotonic()
            try:
                finished = Finished(job, self._work(job))
            except Exception as exc:  # the work's own defect: kept, never the thread's end
                finished = Finished(job, None, f'{type(exc).__name__}: {exc}')
            with self._condition:
                self._running = False
                self._condition.notify_all()
                if self._closed:
                    return
                self._finished.append(finished)
            try:
                self._notify()
            except Exception:  # pragma: no cover - the executor is gone: nothing to tell
                pass
            rest_s = (time.monotonic() - started) * self._rest_ratio
            if rest_s > 0:
                with self._condition:
                    self._condition.wait_for(lambda: self._closed, rest_s)
