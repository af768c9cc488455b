"""When the safety_filter node answers, and with what: one object for the node and the refilter.

The node (:mod:`rcbf_ros.ros.safety_filter_node`) answers at three kinds of events, and
``rcbf_ros refilter`` (:mod:`rcbf_ros.bag.refilter`) replays a bag through the same rules:

- a proposal: always answered (:func:`~rcbf_ros.node_logic.safety_filter.decide_held`);
- a new state or observation-source message: with ``refilter_on_state`` the proposal in force
  filtered again (:func:`~rcbf_ros.node_logic.safety_filter.refilter_due`);
- a call of the hold timer (``control_period_s`` > 0): answered when no answer would otherwise
  go out within ``control_period_s`` (:func:`~rcbf_ros.node_logic.safety_filter.hold_due`,
  :func:`~rcbf_ros.node_logic.safety_filter.decide_hold`).

States and timer calls go unanswered once the fail-safe of a stale proposal has gone out for
``stop_pub_timeout`` (:meth:`AnswerRules.quiet_from_ns`), and the node goes quiet too until the
next proposal, as collision_monitor does; never before the fail-safe went out, whatever the
timing (a ``stop_pub_timeout`` of 0, states rarer than it): the base holds the fail-safe, not a
command of the controller that went quiet.

With a sampled-data margin every decision refuses a state older than ``latency_s``
(:func:`~rcbf_ros.node_logic.safety_filter.state_age_limit_s`). :class:`AnswerRules` keeps
what these rules read (the proposal in force, the latest state, the time of the latest answer)
and the counts; the caller keeps its clock, its messages and what it does with a decision.
"""
from __future__ import annotations

from typing import Any, Callable

from rcbf_ros.node_logic.safety_filter import (
    ActiveFilter,
    decide_held,
    decide_hold,
    Decision,
    HeldProposal,
    hold_due,
    ProposalSample,
    reason_key,
    refilter_due,
    state_age_limit_s,
    StateSample,
)
from rcbf_ros.node_logic.sources import ObservationSources


class AnswerRules:
    """The answering state of one safety filter: what is held, what was answered, when.

    Each event method takes the filter in force (``active``: one whole
    :class:`~rcbf_ros.node_logic.safety_filter.ActiveFilter`, as the node swaps it) and the
    time of the event (``now_ns``: the node's monotonic clock, the refilter's log time); it
    returns the decision to publish, or None when the event is not answered. A decision
    returned counts as an answer made at ``now_ns``; an answer made otherwise (a caller's own
    fail-safe after a defect) is recorded with :meth:`answered`.
    """

    def __init__(self, sources: ObservationSources | None = None, *,
                 stamp_clock: Callable[[], int] | None = None) -> None:
        """Args:
            sources: the observation sources whose points each decision places
                (:meth:`~rcbf_ros.node_logic.sources.ObservationSources.sense`; None: none).
            stamp_clock: the clock (ns) a message's header stamp is aged against at a
                decision (an Odometry's, a source's): the node's ROS clock; None: the
                event's own time (``now_ns``), as the refilter's log time is both.
        """
        self.sources = sources
        self.stamp_clock = stamp_clock
        self.held: HeldProposal | None = None
        """The proposal in force (the latest one read), answered again at states and ticks."""
        self._latest_state: StateSample | None = None
        self.last_answer_ns: int | None = None
        """When the latest answer, of any kind, was made (None: none yet)."""
        self.proposals = 0
        """Proposals received (each answered)."""
        self.refilters = 0
        """Answers made at a new state or source message (``refilter_on_state``)."""
        self.holds = 0
        """Answers made by the hold timer (``control_period_s`` > 0)."""
        self.proposed_ns: int | None = None
        """When the latest proposal arrived (a defective one too; None: none yet)."""
        self.quiet = 0
        """States, source messages and timer calls left unanswered by :meth:`quiet_from_ns`."""
        self.quiet_ns: int | None = None
        """When a state, source message or timer call was last left unanswered by
        :meth:`quiet_from_ns` (None: never): an answer after it owes nothing to the one before
        (no ``control_period_s`` was kept meanwhile: the base held the fail-safe)."""
        self.stale_limit_s: float | None = None
        """The ``max_proposal_age_s`` in force when the proposal in force was first answered
        stale (None: not yet): a limit raised later does not make it fresh again (a command
        of a controller gone quiet never drives the robot again; a new proposal does)."""
        self.fail_safe_since_ns: int | None = None
        """When the unbroken run of fail-safe answers that the latest answer ends began (None:
        the latest answer was not the fail-safe, or none was made yet)."""

    @property
    def latest_state(self) -> StateSample | None:
        """The latest ``state`` message (a bad one too: it says why). Setting a good one
        also gives the sources the robot's pose at its stamp
        (:meth:`~rcbf_ros.node_logic.sources.ObservationSources.note_state`): its header
        stamp, or, for a state without one, its receipt on :attr:`stamp_clock` (the sources'
        stamps are aged on it). A proposal's own state, which the decision takes as the
        robot's at the proposal's receipt, is given at that receipt (:meth:`propose`), in
        its place among the state messages' poses."""
        return self._latest_state

    @latest_state.setter
    def latest_state(self, sample: StateSample | None) -> None:
        self._latest_state = sample
        if sample is not None and sample.state is not None:
            self._note_pose(sample.state, sample.stamp_ns, sample.received_ns)

    def _note_pose(self, state: Any, stamp_ns: int | None, received_ns: int) -> None:
        """Give the sources the robot's pose in ``state`` at ``stamp_ns`` (a header stamp),
        or, without one, at its receipt ``received_ns`` on :attr:`stamp_clock`. A header
        stamp of 0 or farther than the poses' cache from that clock (a driver that leaves it
        unset, a base stamping on its own boot clock) is taken as the receipt too: the
        scans' stamps are aged on that clock all the same."""
        sources = self.sources
        if sources is None:
            return
        now_ns = received_ns if self.stamp_clock is None else self.stamp_clock()
        if stamp_ns is None or stamp_ns <= 0 or abs(stamp_ns - now_ns) > sources.poses.cache_ns:
            stamp_ns = now_ns
        sources.note_state(state, stamp_ns=stamp_ns, now_ns=now_ns)

    def answered(self, now_ns: int, *, fail_safe: bool | None = None) -> None:
        """An answer went out at ``now_ns`` (whatever made it); ``fail_safe``: whether it was
        the fail-safe (None: as the rules' own decision at ``now_ns`` said)."""
        self.last_answer_ns = now_ns
        if fail_safe is not None:
            self._note_fail_safe(fail_safe, now_ns)

    def _note_fail_safe(self, fail_safe: bool, now_ns: int) -> None:
        if not fail_safe:
            self.fail_safe_since_ns = None
        elif self.fail_safe_since_ns is None:
            self.fail_safe_since_ns = now_ns

    def propose(self, sample: ProposalSample | None, *, now_ns: int,
                active: ActiveFilter) -> Decision | None:
        """A proposal arriving at ``now_ns``: counted, held as the proposal in force and
        answered (always).

        ``sample`` None: one that could not be read (a defect): counted, nothing held (nothing
        is answered again until the next proposal), and None: the caller answers it with the
        fail-safe saying why."""
        self.proposals += 1
        self.held = None
        self.proposed_ns = now_ns
        self.stale_limit_s = None
        if sample is None:
            return None
        self.held = HeldProposal(sample=sample, received_ns=now_ns)
        proposal = sample.proposal
        if proposal is not None and proposal.state is not None:  # the state decided on
            self._note_pose(proposal.state, None, now_ns)
        return self._answer(decide_held(held=self.held, again=False,
                                        safety_filter=active.safety_filter,
                                        **self._arguments(active, now_ns)),
                            now_ns)

    def refilter(self, *, now_ns: int, active: ActiveFilter) -> Decision | None:
        """A new state (set :attr:`latest_state` first) or source message at ``now_ns``: the
        proposal in force filtered again when a re-filter is due (``refilter_on_state``, at
        least ``refilter_min_period_s`` after the latest answer), else None."""
        settings, held = active.settings, self.held
        if held is None or not refilter_due(
                enabled=settings.refilter_on_state, held=held,
                last_answer_ns=self.last_answer_ns, now_ns=now_ns,
                min_period_s=settings.refilter_min_period_s):
            return None
        if self._gone_quiet(now_ns, active):
            return None
        self.refilters += 1
        return self._answer(decide_held(held=held, again=True,
                                        safety_filter=active.safety_filter,
                                        **self._arguments(active, now_ns)),
                            now_ns, active)

    def hold(self, *, now_ns: int, timer_period_s: float | None, active: ActiveFilter
             ) -> Decision | None:
        """A call of the hold timer (period ``timer_period_s``; None: no timer) at ``now_ns``:
        when the next call would come more than ``control_period_s`` after the latest answer,
        the proposal in force answered again at the newest state (the fail-safe when none is
        held), else None."""
        control_period_s = active.config.control_period_s
        if timer_period_s is None or not hold_due(
                control_period_s=control_period_s, timer_period_s=timer_period_s,
                last_answer_ns=self.last_answer_ns, now_ns=now_ns):
            return None
        if self._gone_quiet(now_ns, active):
            return None
        self.holds += 1
        return self._answer(decide_hold(held=self.held, safety_filter=active.safety_filter,
                                        control_period_s=control_period_s,
                                        **self._arguments(active, now_ns)),
                            now_ns, active)

    def quiet_from_ns(self, active: ActiveFilter) -> int | None:
        """The time after which states and timer calls go unanswered until the next proposal:
        ``stop_pub_timeout`` after the latest proposal went stale (``max_proposal_age_s``
        after its arrival) or after the fail-safe answers began, whichever is later; None
        while the latest answer is not the fail-safe (a quiet node leaves the base holding
        the fail-safe, never a command) and before the first proposal."""
        if self.proposed_ns is None or self.fail_safe_since_ns is None:
            return None
        settings = active.settings
        stale_ns = self.proposed_ns + round(self._max_age_s(active) * 1e9)
        return max(stale_ns, self.fail_safe_since_ns) + round(settings.stop_pub_timeout * 1e9)

    def _gone_quiet(self, now_ns: int, active: ActiveFilter) -> bool:
        """Whether ``now_ns`` is past :meth:`quiet_from_ns` (counted in :attr:`quiet`)."""
        quiet_from = self.quiet_from_ns(active)
        if quiet_from is None or now_ns <= quiet_from:
            return False
        self.quiet += 1
        self.quiet_ns = now_ns
        return True

    def _answer(self, decision: Decision, now_ns: int,
                active: ActiveFilter | None = None) -> Decision:
        self.last_answer_ns = now_ns
        self._note_fail_safe(decision.fail_safe, now_ns)
        if (active is not None and self.stale_limit_s is None and decision.fail_safe
                and reason_key(decision.reason) == 'stale proposal'):
            self.stale_limit_s = active.settings.max_proposal_age_s
        return decision

    def _max_age_s(self, active: ActiveFilter) -> float:
        """The ``max_proposal_age_s`` the proposal in force is held to: the one in force, or
        the one it went stale under where that is less (:attr:`stale_limit_s`)."""
        limit = active.settings.max_proposal_age_s
        return limit if self.stale_limit_s is None else min(limit, self.stale_limit_s)

    def _arguments(self, active: ActiveFilter, now_ns: int) -> dict[str, Any]:
        """What :func:`decide_held` takes besides the proposal, for a decision at ``now_ns``
        with ``active``: the newest state, the age limits (``latency_s`` with a sampled-data
        margin; a stamp aged on :attr:`stamp_clock`), the static disturbance, the sensor
        points' callback."""
        settings, config, sources, sense = active.settings, active.config, self.sources, None
        stamp_now_ns = now_ns if self.stamp_clock is None else self.stamp_clock()
        if sources is not None:
            safety_filter = active.safety_filter

            def sense(state: Any) -> str:
                return sources.sense(safety_filter, state, now_ns=now_ns,
                                     stamp_now_ns=stamp_now_ns)
        return dict(
            latest_state=self.latest_state, now_ns=now_ns,
            max_state_age_s=settings.max_state_age_s,
            max_proposal_age_s=self._max_age_s(active),
            static_mean=active.static_mean, static_std=active.static_std,
            slack_tolerance=settings.slack_tolerance, sense=sense,
            latency_s=state_age_limit_s(control_period_s=config.control_period_s,
                                        latency_s=config.latency_s),
            stamp_now_ns=stamp_now_ns)
