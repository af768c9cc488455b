"""Process context of the Cyclone runtime: init/shutdown, signals, and the executor.

One DDS participant per context (as rmw does since ROS 2 Foxy), created by :func:`init` with
USER_DATA ``enclave=/;`` in domain ``ROS_DOMAIN_ID`` (default 0) unless ``domain_id`` is given.

The executor runs subscription callbacks and timers in the thread that calls :func:`spin` or
:func:`spin_once`, one work item at a time, so callbacks never run concurrently. It waits on a
Cyclone ``WaitSet`` (one read condition per subscription, service and client, each publisher's
and subscription's DDS writer or reader for its incompatible-QoS status, one guard condition to
wake it; :class:`NodeWaitSet`) in slices of at most :data:`WAIT_SLICE_S`, because
Python runs signal handlers only between bytecodes of the main thread, and takes samples only
from the readers whose condition the wait reports triggered.

Signals: :func:`init` (from the main thread) installs SIGINT and SIGTERM handlers that shut the
context down. A node spinning in the main thread then sees ``KeyboardInterrupt`` (SIGINT) or
:class:`ExternalShutdownException` (SIGTERM) raised from ``spin`` between callbacks, never in the
middle of one, so ``main()``'s ``finally`` runs and can flush files. A signal arriving outside
``spin`` raises at once, like Python's default SIGINT handler, unless the context is already
shut down: then the node is already on its way out, and a second signal (a launcher escalating
SIGINT to SIGTERM, a second Ctrl-C) must not break off its clean-up half way (SIGKILL still
does).

Loopback: with the loopback configuration in effect (:mod:`rcbf_ros.ros.loopback`), the sockets
Cyclone binds to 0.0.0.0 when the participant is created are bound to the loopback device.
"""
from __future__ import annotations

import collections
import ctypes
import os
import signal
import sys
import threading
import time
from typing import Any, Callable, Sequence

from cyclonedds.core import DDSException, GuardCondition, Policy, Qos, WaitSet
from cyclonedds.domain import DomainParticipant

from rcbf_ros.parameters.arguments import parse_ros_arguments, RosArguments
from rcbf_ros.ros.dds.graph import GraphInfo
from rcbf_ros.ros.loopback import (
    ensure_loopback,
    LOOPBACK_CYCLONEDDS_URI,
    own_socket_fds,
    pin_wildcard_sockets_to_loopback,
)

WAIT_SLICE_S = 0.05
"""Longest single DDS wait; bounds how late a signal is noticed while idle."""
_WAIT_SLICE_NS = int(WAIT_SLICE_S * 1e9)


class ExternalShutdownException(Exception):
    """The context was shut down from outside (SIGTERM), like rclpy.executors'."""


def delete_entity(entity: Any) -> None:
    """Delete a Cyclone entity now instead of at garbage collection (idempotent)."""
    if entity is not None:
        entity.__del__()


class Context:
    """A ROS-like context: DDS participant, global ``--ros-args``, nodes, shutdown state."""

    def __init__(self) -> None:
        self.participant: DomainParticipant | None = None
        self.graph: GraphInfo | None = None
        """This participant's ``ros_discovery_info`` entry and the graph (while initialized)."""
        self.domain_id: int = 0
        self.arguments: RosArguments = RosArguments()
        self._ok = False
        self._nodes: list[Any] = []
        self._lock = threading.RLock()
        self._pending_signal: int | None = None
        self.stopped_by_signal: int | None = None
        """The signal that shut this context down (None: none did)."""
        self._previous_handlers: dict[int, Any] = {}
        self.spinning_threads: set[int] = set()

    def init(self, args: Sequence[str] | None = None, domain_id: int | None = None) -> None:
        with self._lock:
            if self._ok:
                raise RuntimeError('rclpy.init() has already been called for this context')
            self.arguments = parse_ros_arguments(args)  # reads the params files, as rcl does
            if domain_id is None:
                text = os.environ.get('ROS_DOMAIN_ID', '').strip() or '0'
                try:
                    domain_id = int(text)
                except ValueError as exc:
                    raise ValueError(f'ROS_DOMAIN_ID must be an integer, got {text!r}') from exc
            if not 0 <= domain_id <= 232:
                raise ValueError(f'domain_id must be in 0..232, got {domain_id}')
            self.domain_id = domain_id
            self.participant = _create_participant(domain_id)
            self.graph = GraphInfo(self.participant, read_builtin=self.read_builtin)
            self._pending_signal = self.stopped_by_signal = None
            self._ok = True
            if threading.current_thread() is threading.main_thread():
                for signum in (signal.SIGINT, signal.SIGTERM):
                    self._previous_handlers[signum] = signal.signal(signum, self._on_signal)

    def ok(self) -> bool:
        return self._ok

    def add_node(self, node: Any) -> None:
        with self._lock:
            self._nodes.append(node)

    def remove_node(self, node: Any) -> None:
        with self._lock:
            if node in self._nodes:
                self._nodes.remove(node)

    def _wake_all(self) -> None:
        for node in list(self._nodes):
            node._wake()

    def _mark_shutdown(self) -> None:
        self._ok = False
        self._wake_all()

    def shutdown(self) -> None:
        with self._lock:
            if not self._ok and self.participant is None:
                raise RuntimeError('rclpy.shutdown() called on a context that is not initialized')
            self._mark_shutdown()
            for signum, handler in self._previous_handlers.items():
                try:
                    signal.signal(signum, handler)
                except ValueError:  # not the main thread; leave ours, it only sets flags
                    pass
            self._previous_handlers.clear()
            for node in list(self._nodes):
                node.destroy_node()
            if self.graph is not None:
                self.graph.close()
                self.graph = None
            delete_entity(self.participant)
            self.participant = None

    def try_shutdown(self) -> None:
        if self._ok or self.participant is not None:
            self.shutdown()

    def _on_signal(self, signum: int, frame: Any) -> None:
        if not self._ok:  # already stopping: let the clean-up finish
            return
        self._pending_signal = self.stopped_by_signal = signum
        self._mark_shutdown()
        if threading.get_ident() not in self.spinning_threads:
            self.raise_pending_signal()

    def raise_pending_signal(self) -> None:
        """Raise the exception of a signal received since the last call, if any."""
        signum, self._pending_signal = self._pending_signal, None
        if signum is not None:
            raise signal_exception(signum)

    def read_builtin(self, reader: Any, condition: Any, count: int) -> list[Any]:
        """``reader.read(N=count, condition=condition)`` of a Cyclone built-in topic reader.

        Cyclone builds those samples through Python callbacks; when a signal's handler raises
        inside one, Cyclone reports a plain ``Exception``: this raises the signal's own
        exception instead (``KeyboardInterrupt`` or :class:`ExternalShutdownException`).
        """
        try:
            return reader.read(N=count, condition=condition)
        except Exception as exc:
            if self.stopped_by_signal is None:
                raise
            raise signal_exception(self.stopped_by_signal) from exc


def signal_exception(signum: int) -> BaseException:
    """What a spinning node raises for a signal: KeyboardInterrupt for SIGINT, else
    :class:`ExternalShutdownException`."""
    if signum == signal.SIGINT:
        return KeyboardInterrupt()
    return ExternalShutdownException(f'received signal {signal.Signals(signum).name}')


default_context = Context()


def _create_participant(domain_id: int) -> DomainParticipant:
    """A participant with USER_DATA ``enclave=/;``, its receive sockets kept on loopback."""
    loopback = ensure_loopback() == LOOPBACK_CYCLONEDDS_URI
    before = set(own_socket_fds()) if loopback and os.path.isdir('/proc/self/fd') else set()
    participant = DomainParticipant(domain_id, qos=Qos(Policy.Userdata(b'enclave=/;')))
    if loopback:
        unpinned = pin_wildcard_sockets_to_loopback(skip_inodes=before)
        if unpinned:
            ports = ', '.join(str(s.port) for s in unpinned)
            print(f'warning: Cyclone DDS sockets on 0.0.0.0 (ports {ports}) could not be bound '
                  'to the loopback device', file=sys.stderr)
    return participant


class NodeWaitSet:
    """A node's Cyclone ``WaitSet`` with its wake-up guard condition: a wait says which of the
    attached conditions are triggered.

    Each condition is attached with its own entity handle as the attach value, which
    ``dds_waitset_wait`` reports for every triggered condition, so that the executor takes
    samples only from the readers that hold some (and resets the guard only when it was set)
    instead of asking every reader, service and client after every wake-up.
    """

    def __init__(self, participant: DomainParticipant) -> None:
        self.waitset = WaitSet(participant)
        self.guard = GuardCondition(participant)
        self._triggered = (ctypes.c_void_p * 8)()
        self._count = 0
        self.attach(self.guard)

    def attach(self, condition: Any) -> None:
        """Wait on ``condition`` too (a read or guard condition)."""
        ret = self.waitset._waitset_attach(self.waitset._ref, condition._ref, condition._ref)
        if ret < 0:
            raise DDSException(ret, f'Occurred when attaching {condition!r} to a wait set')
        self._count += 1
        if self._count > len(self._triggered):
            self._triggered = (ctypes.c_void_p * (2 * self._count))()

    def detach(self, condition: Any) -> None:
        """Stop waiting on ``condition``."""
        ret = self.waitset._waitset_detach(self.waitset._ref, condition._ref)
        if ret < 0:
            raise DDSException(ret, f'Occurred when detaching {condition!r} from a wait set')
        self._count -= 1

    def wait(self, timeout_ns: int) -> list[int]:
        """Block until a condition triggers or ``timeout_ns`` passed (0: do not block); the
        entity handles of the triggered conditions (empty on timeout)."""
        triggered = self._triggered
        count = self.waitset._waitset_wait(self.waitset._ref, triggered, len(triggered),
                                           timeout_ns)
        if count < 0:
            raise DDSException(count, 'Occurred while waiting in a wait set')
        return triggered[:count]

    def close(self) -> None:
        """Delete the wait set and the guard condition (idempotent)."""
        delete_entity(self.waitset)
        delete_entity(self.guard)


def _collect_work(node: Any, triggered: list[int]) -> None:
    """Move due timers and the samples of the triggered readers of ``node`` into its ready
    queue: timers, then subscriptions (in creation order), then the incompatible-QoS warnings
    of triggered publishers and subscriptions, then triggered guard conditions, then services
    and clients. A service whose replies wait for their client is looked at on every pass."""
    ready = node._ready
    if node._timers:
        now = time.monotonic_ns()
        for timer in node._timers:
            if timer._due(now):
                ready.append(timer._fire)
    if triggered:
        guard = node._guard
        if guard is not None and guard._ref in triggered:
            guard.take()
        graph = node.context.graph
        condition = None if graph is None else graph.condition
        if condition is not None and condition._ref in triggered:
            graph.drain()
        for subscription in node._subscriptions:
            condition = subscription._condition  # None once destroyed (from another thread)
            if condition is not None and condition._ref in triggered:
                ready.extend(subscription._take_ready())
        events = node._event_endpoints
        for handle in triggered:
            endpoint = events.get(handle)
            if endpoint is not None:
                ready.extend(endpoint._take_incompatible_qos())
    ready.extend(condition.callback for condition in node._guard_conditions if condition._take())
    for endpoint in node._service_endpoints:
        condition = endpoint._condition
        if endpoint._pending or (triggered and condition is not None
                                 and condition._ref in triggered):
            ready.extend(endpoint._take_ready())


def _next_timer_ns(node: Any) -> int | None:
    deadlines = [t._next_ns for t in node._timers if not t._canceled and t._on_steady_clock()]
    return min(deadlines) if deadlines else None


def _wait_for_work(node: Any, deadline: int | None) -> None:
    """Wait (in slices of :data:`WAIT_SLICE_S`) until ``node`` has work ready, the deadline
    (monotonic ns; None: none) passed, or the context shut down."""
    context = node.context
    while True:
        now = time.monotonic_ns()
        limit = now + _WAIT_SLICE_NS
        if deadline is not None and deadline < limit:
            limit = deadline
        if node._timers:
            next_timer = _next_timer_ns(node)
            if next_timer is not None and next_timer < limit:
                limit = next_timer
        triggered = node._waitset.wait(max(limit - now, 0))
        context.raise_pending_signal()
        if not context.ok() or node._waitset is None:
            return
        _collect_work(node, triggered)
        if node._ready or (deadline is not None and time.monotonic_ns() >= deadline):
            return


def spin_once(node: Any, *, timeout_sec: float | None = None) -> None:
    """Run at most one callback of ``node``, waiting up to ``timeout_sec`` (None: forever)."""
    context = node.context
    ident = threading.get_ident()
    if not node._spin_lock.acquire(blocking=False):
        raise RuntimeError(f'node {node.get_name()!r} is already spinning in another thread')
    context.spinning_threads.add(ident)
    try:
        context.raise_pending_signal()
        if not context.ok() or node._waitset is None:
            return
        if not node._ready:
            _wait_for_work(node, None if timeout_sec is None
                           else time.monotonic_ns() + int(timeout_sec * 1e9))
        if node._ready:
            work: Callable[[], None] = node._ready.popleft()
            work()
        context.raise_pending_signal()
    finally:
        context.spinning_threads.discard(ident)
        node._spin_lock.release()


def spin(node: Any) -> None:
    """Run ``node``'s callbacks until the context shuts down (returns) or a signal (raises)."""
    context = node.context
    while context.ok() and node._waitset is not None:
        spin_once(node, timeout_sec=None)
    context.raise_pending_signal()


def new_ready_queue() -> collections.deque:
    """The per-node queue of work items (callables) taken from DDS but not yet run."""
    return collections.deque()
