"""safety_filter: the RCBF-QP in front of any controller (``ros2 run rcbf_ros safety_filter``).

The node keeps subscriptions, parameters and timing: each proposal's bytes go to the message
edge (:mod:`rcbf_ros.node_logic.filter_edge`), the checked sample to the decision
(:mod:`rcbf_ros.node_logic.safety_filter`), the decision back to the edge for the bytes of
``cmd_safe``, ``filter_info`` and diagnostics in one pass; the node publishes them, the
command first. With ``refilter_on_state`` each state or source message answers the proposal
in force again, the same way; with ``control_period_s`` > 0 a timer answers it again when no
answer went out within that period. Parameter changes build a whole new filter and
swap it in between two callbacks; an ``obstacles`` message's filter is built in a worker
thread (the latest message only) while the filter in force keeps answering. Topics, the
fail-closed handling of bad samples and the parameters: docs/SAFETY_FILTER.md and
``safety_filter --help``.
"""
from __future__ import annotations

import dataclasses
import gc
import os
import sys
import time
from typing import Any, Mapping, NamedTuple, Sequence

import numpy as np

from rcbf_ros.core.config import FilterConfig
from rcbf_ros.core.filter import SafetyFilter
from rcbf_ros.messages import conversions
from rcbf_ros.node_logic import safety_filter as logic
from rcbf_ros.node_logic.answer_rules import AnswerRules
from rcbf_ros.node_logic.filter_edge import Answer, FilterEdge, INPUT_COUNT_KEYS
from rcbf_ros.node_logic.filter_edge import array_sections as _array_sections  # noqa: F401
from rcbf_ros.node_logic.filter_edge import one_line as _one_line
from rcbf_ros.node_logic.interface import bound_text, DIAGNOSTIC_ARRAY
from rcbf_ros.node_logic.latest_only import Finished, LatestOnlyWorker
from rcbf_ros.node_logic.safety_filter_interface import INTERFACE, NODE_NAME, TF_MESSAGE
from rcbf_ros.node_logic.sources import ObservationSources, SENSOR_MESSAGES, topic_refusal
from rcbf_ros.node_logic.tf_buffer import DEFAULT_CACHE_S
from rcbf_ros.node_logic.time_budget import TimeBudget
from rcbf_ros.ros.console import console_line
from rcbf_ros.ros.node_main import declare_specs, run_node, spin
from rcbf_ros.ros.runtime import (
    Clock,
    ClockType,
    deserialize_message,
    DurabilityPolicy,
    get_message,
    HistoryPolicy,
    Node,
    Parameter,
    QoSProfile,
    ReliabilityPolicy,
    USING_RCLPY,
)
from rcbf_ros.ros.tf2_buffer import start_tf2, Tf2


class SafetyFilterNode(Node):
    """Parameters -> FilterConfig -> SafetyFilter; proposal in, safe command + details out."""

    def __init__(self, node_name: str = NODE_NAME, *, cli_args: Sequence[str] | None = None
                 ) -> None:
        """Declare and validate every parameter, build the filter, create the endpoints.

        Args:
            cli_args: this node's own command line, after the process's; as in rclpy, only
                the words after ``--ros-args`` count (``['--ros-args', '--params-file', path]``).

        Raises:
            ValueError: a parameter is invalid (the message names the key).
        """
        super().__init__(node_name, cli_args=cli_args,
                         automatically_declare_parameters_from_overrides=True)
        params = self._declared_parameters()
        try:
            self._active = self._build(params)
            self._check_topics()
        except Exception as exc:  # a value no check foresaw is the user's error too: one line
            # (said once, by the process's exit line: node_main.run_node)
            raise (exc if isinstance(exc, ValueError) else ValueError(_one_line(exc))) from None
        self.system = str(params.get('system'))
        self._pending: tuple[list[Any], logic.ActiveFilter | None, bool] | None = None
        self._change_source = ''
        self._prebuilt: _ObstaclesBuild | None = None
        """The filter of the ``obstacles`` message being stored, built in the worker."""
        self._build_budget = TimeBudget(share=BUILD_TIME_SHARE, burst_s=BUILD_TIME_BURST_S)
        """The executor time the filters built for parameter sets may take
        (:meth:`_check_parameter_change`)."""
        self.add_pre_set_parameters_callback(self._warn_refused)
        self.add_on_set_parameters_callback(self._check_parameter_change)
        self.add_post_set_parameters_callback(self._apply_parameter_change)
        self._clock = self.get_clock()
        self._last_ok_diagnostics_ns: int | None = None
        self._throttle = logic.LogThrottle(self.settings.log_throttle_s)
        self.input_counts = dict.fromkeys(INPUT_COUNT_KEYS, 0)
        """Cumulative ``dropped_samples``, ``refused_proposals``, ``refused_states``."""
        self.late_answers = 0
        """Answers that came more than ``control_period_s`` after the previous one."""
        self._last_published_ns: int | None = None
        """When the latest answer was published (monotonic ns; :meth:`_note_late_answer`):
        the answering rules' time of the latest answer is set before it is published."""

        qos = QoSProfile(
            depth=self.settings.qos_depth, history=HistoryPolicy.KEEP_LAST,
            reliability=(ReliabilityPolicy.RELIABLE if self.settings.qos_reliable
                         else ReliabilityPolicy.BEST_EFFORT))
        array_type = get_message(conversions.FLOAT64_MULTIARRAY)
        command_type = get_message(conversions.COMMAND_MESSAGES[self.settings.command_type])
        state_type = get_message(conversions.STATE_MESSAGES[self.settings.state_type])
        self._cmd_pub = self.create_publisher(command_type, 'cmd_safe', qos)
        self._info_pub = self.create_publisher(array_type, 'filter_info', qos)
        self._diag_pub = self.create_publisher(
            get_message(DIAGNOSTIC_ARRAY), 'diagnostics', qos)
        # Bytes in and out (message types and sizes are read-only: fixed at start).
        self._edge = FilterEdge(
            state_type=self.settings.state_type, command_type=self.settings.command_type,
            system=self.system, n_x=self.filter.n_x, n_u=self.filter.n_u,
            deserialize=deserialize_message, get_message=get_message)
        self.create_subscription(state_type, 'state', self._on_state, qos, raw=True)
        self.create_subscription(command_type, 'cmd_proposed', self._on_proposal, qos, raw=True)
        obstacles_qos = QoSProfile(depth=1, history=HistoryPolicy.KEEP_LAST,
                                   reliability=ReliabilityPolicy.RELIABLE,
                                   durability=DurabilityPolicy.TRANSIENT_LOCAL)
        self._obstacles_built = self.create_guard_condition(self._on_obstacles_built)
        self._obstacle_builds: LatestOnlyWorker[_ObstaclesJob, _ObstaclesBuild] = \
            LatestOnlyWorker(self._build_obstacles, notify=self._obstacles_built.trigger,
                             rest_ratio=OBSTACLES_REST_RATIO, name='obstacles')
        self.create_subscription(array_type, 'obstacles', self._take_obstacles, obstacles_qos,
                                 raw=True)
        self._sources = self._subscribe_sources()
        self._rules = AnswerRules(self._sources,
                                  stamp_clock=lambda: self._clock.now().nanoseconds)
        """When to answer and with what: the proposal in force, the latest state, the latest
        answer's time and the counts (monotonic clock)."""
        self._subscribe_tf()
        self._hold_timer: Any = None
        self._hold_period_s: float | None = None
        self._arm_hold_timer()
        problem = self.config.problem
        self.get_logger().info(
            f'{problem.n_barriers} barriers on {self.system} (n_x = {self.filter.n_x}, '
            f'n_u = {self.filter.n_u}); state_type {self.settings.state_type}, command_type '
            f'{self.settings.command_type}; fail-safe action {self.filter.fail_safe_action}')

    # the answering state ----------------------------------------------------------------------
    @property
    def _latest_state(self) -> logic.StateSample | None:
        """The latest ``state`` message (:attr:`AnswerRules.latest_state`)."""
        return self._rules.latest_state

    @_latest_state.setter
    def _latest_state(self, sample: logic.StateSample | None) -> None:
        self._rules.latest_state = sample

    @property
    def proposals_received(self) -> int:
        """Proposals received (each answered)."""
        return self._rules.proposals

    @property
    def refilters(self) -> int:
        """Answers made at a new state or source message (``refilter_on_state``)."""
        return self._rules.refilters

    @property
    def holds(self) -> int:
        """Answers made by the hold timer (``control_period_s`` > 0, :func:`logic.hold_due`)."""
        return self._rules.holds

    # the active filter ------------------------------------------------------------------------
    @property
    def settings(self) -> logic.NodeSettings:
        """The node's own settings (of the active filter)."""
        return self._active.settings

    @property
    def config(self) -> FilterConfig:
        """The filter's configuration (of the active filter)."""
        return self._active.config

    @property
    def filter(self) -> SafetyFilter:
        """The safety filter in use (replaced as a whole when the parameters change)."""
        return self._active.safety_filter

    def _build(self, params: dict[str, Any], probe_states: Sequence[Any] = (),
               changed: Sequence[str] = ()) -> logic.ActiveFilter:
        """The filter of ``params``, checked as at start (ValueError naming the key)."""
        active = logic.build_active_filter(params=params, probe_states=probe_states,
                                           changed=changed)
        if active.settings.state_type == 'odometry':
            conversions.check_odometry_support(active.params.get('system'))
        return active

    def _declared_parameters(self) -> dict[str, Any]:
        """Declare every known parameter (:func:`declare_specs`); read all back.

        Each declaration gets the description and range of its spec in :data:`INTERFACE` (what
        ``--help`` prints), read-only where it is fixed at start, dynamically typed so that any
        YAML type is accepted; a key of the filter's families that no spec names is described
        as :data:`logic.READ_ONLY_DESCRIPTION`; other overrides (a shared params file's keys
        for other nodes) are left as given. Parameters the overrides declared are declared
        again with their descriptor and value, except one outside its declared range, which
        declare_specs leaves as it was: it is refused here, the key first (ValueError: one
        line, exit 2).
        """
        declare_specs(self, INTERFACE.parameters, dynamic_typing=True, dynamic_overrides=True,
                      read_only=logic.is_read_only, others=_other_description)
        for name, parameter in self.get_parameters_by_prefix('').items():
            if logic.feeds_the_filter(name) and not self.describe_parameter(name).description:
                refusal = _range_refusal(name, parameter.value)
                if refusal:  # left as the override declared it: say why, the key first
                    raise ValueError(refusal)
        return self._parameter_values()

    def _parameter_values(self) -> dict[str, Any]:
        """Every declared parameter's value (unset ones dropped)."""
        return logic.collect_parameters({name: parameter.value for name, parameter
                                         in self.get_parameters_by_prefix('').items()})

    # changes at runtime ------------------------------------------------------------------------
    def _warn_refused(self, parameters: list[Any]) -> list[Any]:
        """Pre-set callback: a WARN for every parameter of a set that its descriptor refuses
        before any on-set callback sees it (read-only, or a number outside its declared range);
        the list goes on unchanged. Never raises."""
        for parameter in parameters:
            try:
                why = self._descriptor_refusal(parameter)
            except Exception as exc:
                why = f'{parameter.name}: {_one_line(exc)}'
            if why:
                self.get_logger().warning(f'parameter change refused: {why}')
        return parameters

    def _descriptor_refusal(self, parameter: Any) -> str:
        """Why the declared descriptor of ``parameter`` refuses its new value, naming it ('' if
        it does not)."""
        name = parameter.name
        if name not in self.get_parameters_by_prefix(''):  # undeclared: the runtime says so
            return ''
        if logic.is_read_only(name):
            return f'{name} is {logic.READ_ONLY_DESCRIPTION}'
        return _range_refusal(name, parameter.value)

    def _check_parameter_change(self, parameters: list[Any]) -> Any:
        """On-set callback: build the filter the change would give; refuse it if that fails.

        The filter is kept for :meth:`_apply_parameter_change`, which swaps it in once the
        parameters are stored (a later on-set callback may still refuse them).
        """
        result = get_message('rcl_interfaces/msg/SetParametersResult')(successful=True)
        self._pending = None
        prebuilt, self._prebuilt = self._prebuilt, None
        if prebuilt is not None:  # an obstacles message's: built and compared in the worker
            self._pending = (parameters, prebuilt.candidate, True)
            return result
        if not any(logic.feeds_the_filter(p.name) for p in parameters):
            return result
        try:
            changes = {p.name: p.value for p in parameters}
            merged = logic.merged_parameters(current=self._parameter_values(), changes=changes)
            if logic.same_parameters(merged, self._active.params):
                self._pending = (parameters, None, False)
                return result
            # an obstacles message's set (rebuilt here when the parameters changed meanwhile)
            # is paced by its worker: never refused for the budget, charged all the same
            started = (self._build_budget.work_clock() if self._change_source
                       else self._build_budget.admit())
            if started is None:  # a stream of sets: each build holds the answers back
                raise _OverBudget(f'{_names(parameters)}: not set, '
                                  f'{self._build_budget.refusal()}; set it again in a moment')
            try:
                probes = self._probe_states()
                self._pending = (parameters, self._build(merged, probes,
                                                         [p.name for p in parameters]), False)
            finally:
                self._build_budget.charge(started)
        except Exception as exc:  # refused whole; whatever the value, the node runs on
            result.successful = False
            # a ValueError names the key itself; an unforeseen error: name the keys set
            text = (str(exc) if isinstance(exc, ValueError)
                    else f'{_names(parameters)}: {_one_line(exc)}')
            result.reason = _cut(' '.join(text.split()))
            line = f'parameter change refused: {result.reason} (the filter is unchanged)'
            if isinstance(exc, _OverBudget):  # a stream of them: through the log throttle
                self._log(logic.WARN, line, time.monotonic_ns())
            elif not self._change_source:  # an obstacles message says so itself, as an ERROR
                self.get_logger().warning(line)
        return result

    def _apply_parameter_change(self, parameters: list[Any]) -> None:
        """Post-set callback: the parameters are stored; swap in the filter built for them.

        Never raises (a callback's exception would end the node's spin): an unforeseen error
        leaves the old filter in force and says so."""
        try:
            self._swap_in(parameters)
        except Exception as exc:
            self.get_logger().error(f'parameters stored but not applied, the filter is '
                                    f'unchanged: {_one_line(exc)}')

    def _probe_states(self) -> tuple[Any, ...]:
        """The state a new filter must be able to filter at: the latest one while it is fresh
        and within the filter in force's ``input_bounds.state`` (a state that filter refuses
        is a glitch of the state source, not a reason to refuse a parameter)."""
        latest, settings = self._latest_state, self.settings
        if latest is None or latest.state is None or logic.state_age_s(
                sample=latest, now_ns=time.monotonic_ns()) > settings.max_state_age_s:
            return ()
        bound = settings.input_bounds.state
        return (latest.state,) if all(abs(v) <= bound for v in latest.state) else ()

    def _swap_in(self, parameters: list[Any]) -> None:
        """Swap in the filter built for ``parameters`` (see :meth:`_apply_parameter_change`)."""
        pending, self._pending = self._pending, None
        compared = False
        if pending is not None and pending[0] is parameters:
            _, candidate, compared = pending
        elif any(logic.feeds_the_filter(p.name) for p in parameters):
            try:  # set without the on-set check (none seen): build from what is stored now
                candidate = self._build(self._parameter_values())
            except Exception as exc:
                self.get_logger().error(f'parameters stored but not applied, the filter is '
                                        f'unchanged: {_one_line(exc)}')
                return
        else:
            return
        if candidate is None or (not compared and logic.same_parameters(candidate.params,
                                                                         self._active.params)):
            return
        old, self._active = self._active, candidate  # the one swap
        self._arm_hold_timer()
        if old.settings.log_throttle_s != candidate.settings.log_throttle_s:
            self._throttle = logic.LogThrottle(candidate.settings.log_throttle_s)
        source = f' from the {self._change_source} topic' if self._change_source else ''
        self.get_logger().info(f'filter updated{source}: '
                               f'{logic.describe_changes(old=old.params, new=candidate.params)}')

    def _take_obstacles(self, data: bytes) -> None:
        """The ``obstacles`` subscription: the sample's filter is built in the worker thread
        while the filter in force answers; a newer sample replaces one whose build has not
        started (only the latest is built). :meth:`_on_obstacles_built` stores the result."""
        self._obstacle_builds.submit(self._obstacles_job(data))

    def _on_obstacles(self, data: bytes) -> None:
        """An ``obstacles`` sample (CDR bytes) built and stored at once, in this thread: the
        new obstacle set, or an ERROR and the old set kept."""
        job = self._obstacles_job(data)
        self._store_obstacles(Finished(job, self._build_obstacles(job)))

    def _obstacles_job(self, data: bytes) -> _ObstaclesJob:
        """What a build of ``data`` needs of the node, read now (on the executor)."""
        return _ObstaclesJob(data=data, base=self._active, probes=self._probe_states())

    def _build_obstacles(self, job: _ObstaclesJob) -> _ObstaclesBuild:
        """The obstacle parameters of ``job``'s sample and the filter they give over the
        parameters of the job (None: the same as in force), or why it is refused. Runs in the
        worker thread: reads only the job and the read-only edge. Never raises."""
        try:
            changes = self._edge.read_obstacles(job.data)
        except Exception as exc:  # a bad message or a defect
            return _ObstaclesBuild({}, None, str(exc) if isinstance(exc, ValueError)
                                   else _one_line(exc))
        try:
            merged = logic.merged_parameters(current=job.base.params, changes=changes)
            if logic.same_parameters(merged, job.base.params):
                return _ObstaclesBuild(changes, None)
            return _ObstaclesBuild(changes, self._build(merged, job.probes, list(changes)))
        except Exception as exc:  # as a parameter set's refusal: a ValueError names the key
            text = (str(exc) if isinstance(exc, ValueError)
                    else f'{", ".join(changes)}: {_one_line(exc)}')
            return _ObstaclesBuild(changes, None, _cut(' '.join(text.split())))

    def _on_obstacles_built(self) -> None:
        """The worker finished a build (its guard condition, on the executor): store it."""
        for finished in self._obstacle_builds.take():
            self._store_obstacles(finished)

    def _store_obstacles(self, finished: Finished[_ObstaclesJob, _ObstaclesBuild]) -> None:
        """Store a built obstacle set (the one swap, between two answers; the filter comes
        prebuilt unless the parameters changed since the build started: then it is built
        here, as a parameter set's), or an ERROR and the old set kept. Never raises."""
        build = finished.result
        try:
            if build is None:  # a defect of the build
                raise RuntimeError(finished.error)
            if build.error:
                raise ValueError(build.error)
            prebuilt: _ObstaclesBuild | None = build
            active = self._active
            if finished.job.base is not active:  # changed since the build started
                if all(active.params.get(k) == v for k, v in build.changes.items()):
                    return  # this set is in force already
                if build.candidate is None or not _same_but(
                        finished.job.base.params, active.params, build.changes):
                    prebuilt = None  # built for other parameters: built again, here
            elif build.candidate is None:
                return  # the same obstacles as in force
            self._change_source, self._prebuilt = 'obstacles', prebuilt
            try:
                result = self.set_parameters_atomically([
                    Parameter(name, Parameter.Type.DOUBLE_ARRAY, values)
                    for name, values in build.changes.items()])
            finally:
                self._change_source, self._prebuilt = '', None
            if not result.successful:
                raise ValueError(result.reason)
        except Exception as exc:  # a bad message or a defect: never kills the node
            text = str(exc) if isinstance(exc, ValueError) else _one_line(exc)
            self.get_logger().error(f'obstacles message refused, the obstacles are unchanged: '
                                    f'{" ".join(text.split())}')

    def destroy_node(self) -> Any:
        """Stop the obstacles worker (a build still running is dropped), then the node."""
        builds = getattr(self, '_obstacle_builds', None)
        if builds is not None:
            builds.close()
        return super().destroy_node()

    # observation sources ---------------------------------------------------------------------
    def _check_topics(self) -> None:
        """Refuse two of the node's names that clash (:func:`topic_refusal`: its topics, the
        middleware's and the sources', resolved as this node resolves them: ``cmd_proposed``
        remapped onto ``cmd_safe``, ``state`` onto ``/tf``, a source onto ``/rosout``), and
        declare every key of every source with the value in force (read-only, described), so
        that ``ros2 param get`` shows a defaulted key and ``ros2 param set`` says it is
        read-only.

        Raises:
            ValueError: one line naming both names (exit 2).
        """
        config = self.config.sources
        refusal = topic_refusal(config, [topic.name for topic in INTERFACE.topics],
                                self.resolve_topic_name)
        if refusal:
            raise ValueError(refusal)
        if config is None:
            return
        patterns = [spec for spec in INTERFACE.parameters if spec.pattern]
        specs = []
        for name, params in config.sources:
            for key in dataclasses.fields(params):
                full = f'{name}.{key.name}'
                spec = next(s for s in patterns if s.matches(full))
                specs.append(dataclasses.replace(spec, name=full,
                                                 default=getattr(params, key.name)))
        declare_specs(self, specs, dynamic_typing=True, read_only=logic.is_read_only,
                      others=None)

    def _subscribe_sources(self) -> ObservationSources | None:
        """One subscription per observation source (``observation_sources``, fixed at
        start): sensor-data QoS (best effort, keep last 5) unless ``<name>.best_effort`` is
        false."""
        config = self.config.sources
        self._tf_budget = TimeBudget(share=TF_TIME_SHARE, burst_s=TF_TIME_BURST_S)
        """The executor time ``/tf`` may take (:meth:`_on_tf`, tf2_ros's listener)."""
        self._tf2: Tf2 | None = None
        """tf2_ros at work for the sources (None: our buffer, or no sources)."""
        if config is None:
            return None
        self._tf2 = self._start_tf2()
        sources = ObservationSources(config, tf=self._tf2 and self._tf2.lookup)
        if self._tf2 is not None:
            self._tf2.feed.counts = sources.tf_counts
        for name, params in config.sources:
            qos = QoSProfile(depth=5, history=HistoryPolicy.KEEP_LAST,
                             reliability=(ReliabilityPolicy.BEST_EFFORT if params.best_effort
                                          else ReliabilityPolicy.RELIABLE))
            kind = SENSOR_MESSAGES[params.type]
            self.create_subscription(
                get_message(kind), params.topic,
                lambda data, name=name: self._on_source(name, data), qos, raw=True)
            self.get_logger().info(f'source {name}: {kind} on {params.topic}')
        return sources

    @staticmethod
    def _tf_qos() -> tuple[QoSProfile, QoSProfile]:
        """tf2_ros's listener QoS of ``/tf`` (reliable; keep last 100) and of ``/tf_static``
        (reliable; keep last 1 and transient-local)."""
        return (QoSProfile(depth=100, history=HistoryPolicy.KEEP_LAST,
                           reliability=ReliabilityPolicy.RELIABLE,
                           durability=DurabilityPolicy.VOLATILE),
                QoSProfile(depth=1, history=HistoryPolicy.KEEP_LAST,
                           reliability=ReliabilityPolicy.RELIABLE,
                           durability=DurabilityPolicy.TRANSIENT_LOCAL))

    def _start_tf2(self) -> Tf2 | None:
        """On rclpy with tf2_ros importable: tf2_ros's Buffer and TransformListener (its own
        ``/tf`` and ``/tf_static`` subscriptions) for the sources' lookups; else None, our
        buffer. Says once which one answers."""
        why = 'the Cyclone runtime'
        if USING_RCLPY:
            dynamic, static = self._tf_qos()
            started = start_tf2(self, self._on_tf2, qos=dynamic, static_qos=static,
                                budget=self._tf_budget)
            if not isinstance(started, str):
                self.get_logger().info('tf: tf2_ros Buffer and TransformListener (cache '
                                       f'{DEFAULT_CACHE_S:g} s) on /tf and /tf_static')
                return started
            why = started
        self.get_logger().info(f"tf: the filter's own buffer on /tf and /tf_static ({why})")
        return None

    def _subscribe_tf(self) -> None:
        """With observation sources and our buffer, ``/tf`` and ``/tf_static`` with tf2_ros's
        listener QoS (:meth:`_tf_qos`): a source's frame is known only from its messages, so
        any may need tf. With tf2_ros (:meth:`_start_tf2`) its listener has them."""
        if self._sources is None or self._tf2 is not None:
            return
        tf_type = get_message(TF_MESSAGE)
        dynamic, static = self._tf_qos()
        self.create_subscription(tf_type, '/tf', lambda data: self._on_tf(data, False), dynamic,
                                 raw=True)
        self.create_subscription(tf_type, '/tf_static', lambda data: self._on_tf(data, True),
                                 static, raw=True)

    def _on_tf2(self, topic: str, reason: str) -> None:
        """After tf2_ros's listener took a message (through the feed): a WARN (through the log
        throttle) for what was refused. Never raises."""
        if not reason:
            return
        now_ns = time.monotonic_ns()
        try:
            self._log(logic.WARN, f'{topic} refused: {reason}', now_ns)
        except Exception as exc:  # a defect, not an input
            self._log_safely(f'{topic}: internal error: {_one_line(exc)}', now_ns)

    def _on_tf(self, data: bytes, static: bool) -> None:
        """A ``/tf`` or ``/tf_static`` message (CDR bytes): its transforms kept, a WARN (through
        the log throttle) for what was refused. A ``/tf`` message that comes while ``/tf`` has
        taken more than its share of the executor (:data:`TF_TIME_SHARE`,
        :data:`TF_TIME_BURST_S`) is refused unread and counted in ``tf.refused``: a flood
        of large messages would otherwise hold every answer back for as long as its queue lasts
        (``/tf_static`` is kept to one message at a time by its keep-last-1 queue). Never
        raises."""
        now_ns = time.monotonic_ns()
        topic = '/tf_static' if static else '/tf'
        try:
            sources: Any = self._sources  # never None here: /tf is read only for sources

            def reading() -> str:
                return sources.read_tf(data, static=static,
                                       now_ns=self._clock.now().nanoseconds)
            reason = reading() if static else self._tf_budget.read(reading, sources.tf_counts)
            if reason:
                self._log(logic.WARN, f'{topic} refused: {reason}', now_ns)
        except Exception as exc:  # a defect, not an input
            self._log_safely(f'{topic}: internal error: {_one_line(exc)}', now_ns)

    def _on_source(self, name: str, data: bytes) -> None:
        """A message of source ``name`` (CDR bytes): its points kept, or one line saying why
        it was refused (the fail-safe until a message is read). Never raises."""
        now_ns = time.monotonic_ns()
        try:
            reason = self._sources.read(name, data, received_ns=now_ns)  # type: ignore[union-attr]
            if reason:
                self._log(logic.ERROR, f'source {name}: message refused: {reason}', now_ns)
        except Exception as exc:  # a defect, not an input
            self._log_safely(f'source {name}: internal error: {_one_line(exc)}', now_ns)
        self._refilter(now_ns)

    def _counts(self) -> dict[str, int]:
        """The input counts of the diagnostics and ``late_answers``, with each source's
        (``<name>.messages``,
        ``.refused``, ``.stale``, ``.untransformed``) and tf's (``tf.messages``,
        ``tf.refused``, ``tf.transforms_refused``)."""
        counts = {**self.input_counts, LATE_ANSWERS: self.late_answers}
        if self._sources is None:
            return counts
        for name, values in self._sources.counts().items():
            counts.update({f'{name}.{key}': value for key, value in values.items()})
        counts.update({f'tf.{key}': value for key, value in self._sources.tf_counts.items()})
        return counts

    # callbacks ---------------------------------------------------------------------------------
    def _on_state(self, data: bytes) -> None:
        """A ``state`` sample (CDR bytes): the latest state, or a bad one that says why."""
        now_ns = time.monotonic_ns()
        try:
            sample = self._state_sample(data, now_ns, self._active)
        except Exception as exc:  # a defect, not an input (docs/SAFETY_FILTER.md)
            sample = logic.StateSample(received_ns=now_ns, state=None,
                                       error=f'internal error: {_one_line(exc)}')
        self._latest_state = sample
        if sample.state is None:
            self._log(logic.ERROR, f'bad state: {sample.error}', now_ns)
        self._refilter(now_ns)

    def _state_sample(self, data: bytes, now_ns: int,
                      active: logic.ActiveFilter) -> logic.StateSample:
        """The state sample of one ``state`` message, counted when dropped or refused."""
        sample, count = self._edge.read_state(data, received_ns=now_ns,
                                              frame_id=active.settings.state_frame_id,
                                              child_frame_id=active.robot_frame_id)
        if count:
            self.input_counts[count] += 1
        return sample

    def _on_proposal(self, data: bytes) -> None:
        """A ``cmd_proposed`` sample (CDR bytes): answered with one command, always; held as
        the proposal in force (none after an internal error: nothing is re-filtered then)."""
        now_ns = time.monotonic_ns()
        rules, header = self._rules, None
        active = self._active  # one filter for the whole answer, whatever changes meanwhile
        try:
            try:
                sample = self._read_proposal(data, active)
            except Exception:
                rules.propose(None, now_ns=now_ns, active=active)  # counted, nothing held
                raise
            decision = rules.propose(sample, now_ns=now_ns, active=active)
            assert decision is not None  # a sample read is always answered
            header = sample.header
        except Exception as exc:  # a defect, not an input (docs/SAFETY_FILTER.md)
            decision = logic.fail_safe_decision(
                safety_filter=active.safety_filter, reason=f'internal error: {_one_line(exc)}')
        self._publish_answer(decision, header, now_ns, active)

    def _refilter(self, now_ns: int) -> None:
        """A new state or source message (at ``now_ns``): the proposal in force filtered again
        and answered as a proposal is (``refilter_on_state``, :meth:`AnswerRules.refilter`); a
        TwistStamped answer has the proposal's frame_id, stamped now. Never raises."""
        rules, active = self._rules, self._active
        header = None
        try:
            decision = rules.refilter(now_ns=now_ns, active=active)
            if decision is None:
                return
            held = rules.held
            header = self._edge.restamped(None if held is None else held.sample.header,
                                          clock=self._clock)
        except Exception as exc:  # a defect, not an input: the fail-safe, stamped now
            decision = logic.fail_safe_decision(
                safety_filter=active.safety_filter, reason=f'internal error: {_one_line(exc)}')
            header = None
        self._publish_answer(decision, header, now_ns, active)

    def _arm_hold_timer(self) -> None:
        """The hold timer at the period of the active filter's ``control_period_s``
        (:func:`logic.hold_timer_period_s`; none for 0), created again when it changes. It
        runs on the steady clock: with ``use_sim_time`` a node's timers follow ``/clock``, and
        the answer within ``control_period_s`` (the fail-safe of a quiet loop) must not wait
        for a clock publisher that stopped or never started."""
        period = logic.hold_timer_period_s(self.config.control_period_s)
        if period == self._hold_period_s:
            return
        if self._hold_timer is not None:
            self.destroy_timer(self._hold_timer)
        self._hold_timer = None if period is None else self.create_timer(
            period, self._on_hold, clock=Clock(clock_type=ClockType.STEADY_TIME))
        self._hold_period_s = period

    def _on_hold(self) -> None:
        """The hold timer: with ``control_period_s`` > 0, when no answer would go out within
        it of the latest (:func:`logic.hold_due`), the proposal in force answered again at the
        newest state, or the fail-safe (:func:`logic.decide_hold`); stamped as a re-filter's.
        Never raises."""
        now_ns = time.monotonic_ns()
        rules, active = self._rules, self._active
        header = None
        try:
            decision = rules.hold(now_ns=now_ns, timer_period_s=self._hold_period_s,
                                  active=active)
            if decision is None:
                return
            held = rules.held
            header = self._edge.restamped(None if held is None else held.sample.header,
                                          clock=self._clock)
        except Exception as exc:  # a defect, not an input: the fail-safe, stamped now
            decision = logic.fail_safe_decision(
                safety_filter=active.safety_filter, reason=f'internal error: {_one_line(exc)}')
            header = None
        self._publish_answer(decision, header, now_ns, active)

    def _publish_answer(self, decision: logic.Decision, header: Any, now_ns: int,
                        active: logic.ActiveFilter) -> None:
        """``cmd_safe``, ``filter_info`` and the diagnostics of one decision, the command
        first; the reason of a WARN or ERROR in the (throttled) log. Never raises."""
        self._rules.answered(now_ns, fail_safe=decision.fail_safe)
        previous_ns, self._last_published_ns = self._last_published_ns, now_ns
        quiet_ns = self._rules.quiet_ns
        if previous_ns is not None and quiet_ns is not None and quiet_ns > previous_ns:
            previous_ns = None  # quiet meanwhile (stop_pub_timeout): no period was owed
        self._note_late_answer(previous_ns, now_ns, active)
        try:  # the command is made first: a failure making the details is in answer.error
            answer = self._edge.answer(
                decision, settings=active.settings,
                barrier_names=active.safety_filter.barrier_names, header=header, now_ns=now_ns,
                last_ok_ns=self._last_ok_diagnostics_ns, clock=self._clock,
                counts=self._counts())
            self._cmd_pub.publish(answer.command)
        except Exception as exc:  # a defect in the output: the fail-safe instead, if it can go
            self._publish_fail_safe(active, f'internal error: {_one_line(exc)}', header, now_ns)
            return
        try:  # the command is out: a failure below costs the details, never a second command
            error = self._publish_details(answer, decision.level, now_ns)
            if not error and decision.level != logic.OK:
                self._log(decision.level, decision.reason, now_ns)
        except Exception as exc:
            error = _one_line(exc)
        if error:
            self._log_safely(f'answer details not published: internal error: {error}', now_ns)

    def _note_late_answer(self, previous_ns: int | None, now_ns: int,
                          active: logic.ActiveFilter) -> None:
        """An answer more than ``control_period_s`` after the previous one (the hold was not
        kept: a callback held the executor, or the machine is overloaded): counted
        (``late_answers`` in the diagnostics), and a WARN (throttled) saying by how much.
        Never raises."""
        try:
            period_s = active.config.control_period_s
            over_s = logic.answer_overrun_s(control_period_s=period_s,
                                            previous_ns=previous_ns, now_ns=now_ns)
            if over_s is None:
                return
            self.late_answers += 1
            self._log(logic.WARN, f'late answer: {over_s + period_s:.3f} s after the previous '
                                  f'one, {over_s:.3f} s over control_period_s = {period_s:g} '
                                  f'(the node could not answer meanwhile)', now_ns)
        except Exception as exc:  # a defect, not an input
            self._log_safely(f'late answer: internal error: {_one_line(exc)}', now_ns)

    def _publish_fail_safe(self, active: logic.ActiveFilter, reason: str, header: Any,
                           now_ns: int) -> None:
        """The fail-safe command alone, and the reason in the (throttled) log: the last resort
        of an answer whose command could not be published. Never raises."""
        try:
            self._publish_command(active.safety_filter.fail_safe_action, header)
        except Exception as exc:
            reason = f'no command published: {reason}; then {_one_line(exc)}'
        self._log_safely(reason, now_ns)

    def _log_safely(self, reason: str, now_ns: int) -> None:
        """An ERROR through the log throttle; a failure of the log itself goes to stderr."""
        try:
            self._log(logic.ERROR, reason, now_ns)
        except Exception as exc:
            console_line(f'{NODE_NAME}: {reason} (log failed: {_one_line(exc)})')

    def _read_proposal(self, data: bytes, active: logic.ActiveFilter) -> logic.ProposalSample:
        """The sample of one ``cmd_proposed`` message, counted when dropped or refused."""
        sample = self._edge.read_proposal(data, twist_fields=active.settings.twist_fields)
        if sample.count:
            self.input_counts[sample.count] += 1
        return sample

    # output ------------------------------------------------------------------------------------
    def _publish_command(self, u_safe: np.ndarray, header: Any = None) -> None:
        """``cmd_safe``: the command alone, in the proposal's type (``header``: the proposal's,
        TwistStamped; None: one stamped now). The message type and twist_fields are
        read-only, so any filter's settings will do."""
        self._cmd_pub.publish(self._edge.command(
            u_safe, twist_fields=self.settings.twist_fields, header=header, clock=self._clock))

    def _publish_details(self, answer: Answer, level: int, now_ns: int) -> str:
        """``filter_info`` and the diagnostics (if due) of an answer whose command is out, as
        far as they were made; why one was not (``answer.error``, '' when none)."""
        if answer.info is None:
            return answer.error
        self._info_pub.publish(answer.info)
        if answer.diagnostics_due and level == logic.OK:
            self._last_ok_diagnostics_ns = now_ns
        if answer.diagnostics is not None:
            self._diag_pub.publish(answer.diagnostics)
        return answer.error

    def _info_cdr(self, decision: logic.Decision) -> bytes:
        """The serialized ``filter_info`` of a decision (:meth:`FilterEdge.info_cdr`)."""
        return self._edge.info_cdr(decision)

    # The Float64MultiArray layouts the edge reads at fixed offsets (() reads every sample the
    # general way).
    @property
    def _state_layouts(self) -> tuple[Any, ...]:
        return self._edge.state_layouts

    @_state_layouts.setter
    def _state_layouts(self, layouts: tuple[Any, ...]) -> None:
        self._edge.state_layouts = layouts

    @property
    def _proposal_layouts(self) -> tuple[Any, ...]:
        return self._edge.proposal_layouts

    @_proposal_layouts.setter
    def _proposal_layouts(self, layouts: tuple[Any, ...]) -> None:
        self._edge.proposal_layouts = layouts

    def _log(self, level: int, reason: str, now_ns: int) -> None:
        key = logic.reason_key(reason)
        if not self._throttle.should_log(key=key, now_ns=now_ns):
            return
        suppressed = self._throttle.pop_suppressed(key)
        text = reason + (f' ({suppressed} more since the last report)' if suppressed else '')
        if level == logic.ERROR:
            self.get_logger().error(f'fail-safe: {text}')
        else:
            self.get_logger().warning(text)

    @property
    def fail_safe_action(self) -> np.ndarray:
        """(n_u,) what the node publishes when it cannot filter."""
        return self.filter.fail_safe_action


OBSTACLES_REST_RATIO = 1.0
"""After building an obstacles message's filter for t seconds, the worker starts the next build
no sooner than this times t later: a stream of large messages takes at most half of the time,
the executor's answers the rest."""
GIL_SWITCH_INTERVAL_S = 0.001
"""Python's thread switch interval in the node (default 5 ms): while the worker builds, the
executor waits at most about this long for the GIL each time it needs it back (an answer
needs it several times). Without a build there is no other thread to switch to."""
BUILD_TIME_SHARE = 0.25
"""The part of the executor's time the filters built for parameter sets may take: each set of
a filter key builds a whole filter on the executor (5 ms, 175 ms with 20,000 obstacles), and a
set_parameters request of 100 entries, each one set, held the answers back for half a
second (10,000 entries, some 300 kB: a minute). A set that comes while this is spent is
refused, saying so."""
BUILD_TIME_BURST_S = 0.2
"""The most executor time (s) the builds may take at once, after a quiet while (plus one
build): a few sets in a row, or one of a large obstacle set, go through."""
TF_TIME_SHARE = 0.25
"""The part of the executor's time ``/tf`` may take (:meth:`SafetyFilterNode._on_tf`): a robot's
own tf (odometry at 50 Hz, a robot_state_publisher's dozens of links at 30 Hz) takes well under
a hundredth of it."""
TF_TIME_BURST_S = 0.02
"""The most executor time (s) ``/tf`` may take at once, after a quiet while (plus one message:
some 15-30 ms for one of 1,024 transforms): less than a ``control_period_s`` of 0.05 s."""
LATE_ANSWERS = 'late_answers'
"""The diagnostics' count of answers more than ``control_period_s`` after the previous one."""


class _OverBudget(ValueError):
    """A parameter set refused because the builds took their share of the executor."""


class _ObstaclesJob(NamedTuple):
    """An ``obstacles`` sample and what its build needs of the node, read on the executor."""

    data: bytes
    base: logic.ActiveFilter
    """The filter in force when the sample arrived: the new one is built from its parameters
    (a snapshot, read without copying them) with the sample's obstacles."""
    probes: tuple[Any, ...]
    """The states the new filter must filter at (:meth:`SafetyFilterNode._probe_states`)."""


class _ObstaclesBuild(NamedTuple):
    """What the worker made of an ``obstacles`` sample."""

    changes: dict[str, list[float]]
    """``obstacles.x`` / ``.y`` / ``.radius`` ({} when the sample was refused)."""
    candidate: logic.ActiveFilter | None
    """The filter of the new set (None: refused, or the same as the job's base)."""
    error: str = ''
    """Why the sample is refused, one line ('' when it is not)."""


def _same_but(a: Mapping[str, Any], b: Mapping[str, Any], keys: Any) -> bool:
    """Whether two flat parameter dicts agree on every key but ``keys``."""
    return logic.same_parameters({k: v for k, v in a.items() if k not in keys},
                                 {k: v for k, v in b.items() if k not in keys})


def _other_description(name: str) -> str | None:
    """The description of an override no spec names: a key of the filter's families
    (:func:`logic.feeds_the_filter`) is described as read-only text; others are left as
    given (None)."""
    return logic.READ_ONLY_DESCRIPTION if logic.feeds_the_filter(name) else None


def _range_refusal(name: str, value: Any) -> str:
    """``<name>: <value> is outside its declared range <low> to <high>`` when the range the
    parameter is declared with refuses ``value`` (:meth:`ParameterSpec.range_refuses`), else
    ''."""
    spec = INTERFACE.spec(name)
    if spec is None or not spec.range_refuses(value):
        return ''
    low, high = spec.range  # type: ignore[misc]
    return (f'{name}: {value!r} is outside its declared range {bound_text(low)} to '
            f'{bound_text(high)}')


def _names(parameters: Sequence[Any], most: int = 4) -> str:
    """The names of a set's parameters, ``, ``-separated (the first ``most``, then how many
    more)."""
    names = [p.name for p in parameters]
    more = f' and {len(names) - most} more' if len(names) > most else ''
    return ', '.join(names[:most]) + more


def _cut(text: str, width: int = 400) -> str:
    """``text`` cut to ``width`` characters (a reason stays one readable line)."""
    return text if len(text) <= width else text[:width - 3] + '...'


def spin_frozen(node: SafetyFilterNode) -> None:
    """Spin ``node`` with everything built before (modules, the filter: ~200 000
    objects) frozen out of the garbage collector's generations (``gc.freeze``): a full
    collection then walks only what the callbacks allocated since, instead of taking ~45 ms
    (long enough to overflow keep-last 10 queues at 1 kHz). Reference counting still frees
    frozen objects; only cycles among them are no longer collected. Python's thread switch
    interval is :data:`GIL_SWITCH_INTERVAL_S`."""
    gc.collect()
    gc.freeze()
    sys.setswitchinterval(GIL_SWITCH_INTERVAL_S)
    spin(node)


def main(args: Sequence[str] | None = None) -> int:
    """Run the node until Ctrl-C / SIGTERM. Returns 2 on invalid parameters."""
    # A batch of one (the autograd assembly, the fallback): threads would only add contention.
    # torch is imported only by a system or barrier that needs it (rcbf_ros.core.torch_import).
    os.environ.setdefault('OMP_NUM_THREADS', '1')
    # Parameter errors are already logged with the node's name by the constructor.
    return run_node(NODE_NAME, SafetyFilterNode, args, run=spin_frozen,
                    setup_errors=(ValueError,), interface=INTERFACE)


if __name__ == '__main__':
    sys.exit(main())
