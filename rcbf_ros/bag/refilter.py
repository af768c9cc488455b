"""Offline re-filtering of a recorded run: the safety filter with another YAML, no DDS.

    rcbf_ros refilter SOURCE_BAG OUTPUT_BAG --params-file F [--node N] [cmd_in:=/topic ...]

Replays a recorded run through the safety_filter node's answering rules
(:class:`rcbf_ros.node_logic.answer_rules.AnswerRules`) with a ``SafetyFilter`` built from the
new parameters, in log time: every proposal answered, the proposal in force filtered again at
states and source messages (``refilter_on_state``) and at the hold timer's calls
(``control_period_s``), every state older than ``latency_s`` refused; writes a new bag: the
source topics unchanged plus ``/refilter/cmd_safe``, ``/refilter/filter_info`` and
``/refilter/diagnostics`` as the node would publish them; then compares the new answers to
proposals with the recorded ones. A pure library and command line, so that a parameter change
can be tried on a run without a robot or middleware.

What it reads, writes, skips and compares: docs/BAGS.md#re-filtering-a-run
"""
from __future__ import annotations

import argparse
from collections import defaultdict, deque
from dataclasses import asdict, dataclass, field
import json
import math
import os
from pathlib import Path
import sys
from types import SimpleNamespace
from typing import Any, Callable, Iterator, Mapping, Sequence

import numpy as np

from rcbf_ros.bag import bag_info, BagError, BagWriter, mcap_files, read_bag
from rcbf_ros.bag.playback import several_types
from rcbf_ros.core.config import filter_config_from_params, FilterConfig, flatten
from rcbf_ros.core.filter import ACTIVE_TOLERANCE, SafetyFilter
from rcbf_ros.core.lie_closed_form import state_barrier_values
from rcbf_ros.core.lie_closed_form_rows import VectorAssembly
from rcbf_ros.core.rcbf import RCBFProblem
from rcbf_ros.core.sampled_data import TIMING_LIMIT_S
from rcbf_ros.messages.conversions import (
    DIAGNOSTIC_ARRAY,
    FLOAT64_MULTIARRAY,
    ODOMETRY,
    TWIST,
    TWIST_STAMPED,
)
from rcbf_ros.messages.typestore import jazzy_typestore
from rcbf_ros.node_logic import filter_edge
from rcbf_ros.node_logic import safety_filter as logic
from rcbf_ros.node_logic.answer_rules import AnswerRules
from rcbf_ros.node_logic.safety_filter_interface import INTERFACE, NODE_NAME
from rcbf_ros.node_logic.sources import (
    MIDDLEWARE_TOPICS,
    ObservationSources,
    SENSOR_MESSAGES,
    topic_refusal,
)
from rcbf_ros.parameters.arguments import (
    check_node_name,
    expand_topic_name,
    RosArgumentError,
)
from rcbf_ros.parameters.rules import (
    find_config,
    key_matches,
    load_params,
    ParamRules,
    WILDCARD_KEY,
)

PROPOSAL_TOPIC = '/cmd_proposed'
STATE_TOPIC = '/state'
RECORDED_COMMAND_TOPIC = '/cmd_safe'
RECORDED_INFO_TOPIC = '/filter_info'
NODE_TOPICS = {'cmd_proposed': PROPOSAL_TOPIC, 'state': STATE_TOPIC,
               'cmd_safe': RECORDED_COMMAND_TOPIC, 'filter_info': RECORDED_INFO_TOPIC}
"""The node's topics a bag is read by, under their names in the closed loops (no remaps)."""
LAUNCH_ARGUMENTS = {'cmd_in': 'cmd_proposed', 'odom': 'state', 'cmd_out': 'cmd_safe'}
"""The drop-in launch's arguments (``safety_filter.launch.py``) and the node topics they
remap: ``cmd_in:=/x`` here reads what the launch with ``cmd_in:=/x`` filtered."""
DROP_IN_TOPICS = {'cmd_proposed': '/cmd_vel_nav', 'state': '/odom', 'cmd_safe': '/cmd_vel',
                  'filter_info': RECORDED_INFO_TOPIC}
"""The topics of the drop-in launch at its defaults (``rcbf_ros.launch.table.ROBOT_ARGUMENTS``),
read when a bag has no ``/cmd_proposed`` and no remap is given."""
TOPIC_NAME_LIMIT = 256
TF_TOPICS = ('/tf', '/tf_static')
"""What the node's sources place points through (tf2_msgs/TFMessage), read from a bag that
has them, as the node's subscriptions read them."""
OUTPUT_COMMAND_TOPIC = '/refilter/cmd_safe'
OUTPUT_INFO_TOPIC = '/refilter/filter_info'
OUTPUT_DIAGNOSTICS_TOPIC = '/refilter/diagnostics'
OUTPUT_TOPICS = (OUTPUT_COMMAND_TOPIC, OUTPUT_INFO_TOPIC, OUTPUT_DIAGNOSTICS_TOPIC)
DEFAULT_TOLERANCE = 1e-6
ANSWER_KINDS = ('proposal', 'refilter', 'hold')
"""The events the node answers at (:class:`rcbf_ros.node_logic.answer_rules.AnswerRules`)."""
HOLD_STRETCH_LIMIT = 2 * round(TIMING_LIMIT_S / logic.HOLD_TIMER_MIN_PERIOD_S)
"""The most hold-timer answers made in a stretch of log time without a message before one
is the fail-safe (:class:`_HoldTimer`). Within the parameters' limits it is never reached:
with control_period_s > 0 a state older than latency_s (at most TIMING_LIMIT_S, 1 s) is
the fail-safe, and the timer answers at most once a HOLD_TIMER_MIN_PERIOD_S (1 ms), so at
most 1001 answers of a stretch come before its first fail-safe. A guard, should those limits
change: the run is refused rather than simulated without bound."""
LATEST_LOG_TIME_NS = 2**31 * 10**9 - 1
"""The latest log time (ns) a run may hold: each answer is stamped with a log time, and
builtin_interfaces/msg/Time counts its seconds in an int32 (up to 2038-01-19). An MCAP log time
may be any uint64."""


class RefilterError(ValueError):
    """The source bag, the parameters or their combination cannot be re-filtered."""


@dataclass
class RefilterSummary:
    """What re-filtering a bag with new parameters changed (see module docstring)."""

    source: str
    """The source bag."""
    output: str
    """The bag written."""
    system: str
    """The new parameters' ``system``."""
    barrier_names: list[str]
    """The new barriers, in row order."""
    topics: dict[str, str] = field(default_factory=dict)
    """The node's topics (``cmd_proposed``, ``state``, ``cmd_safe``, ``filter_info``, and each
    observation source by name) -> the bag's topic read for it."""
    proposals: int = 0
    """Proposals (``cmd_proposed``) read, each answered (one ``/refilter/cmd_safe`` each)."""
    processed: int = 0
    """Proposals filtered (answered by a solve of the new filter)."""
    skipped: dict[str, int] = field(default_factory=dict)
    """Proposals not filtered, by reason ('no state received yet', 'stale state', 'late
    state', ...): answered with the fail-safe, as the node answers them."""
    refilters: int = 0
    """Answers at a new state or source message (``refilter_on_state``): the proposal in force
    filtered again."""
    holds: int = 0
    """Answers of the hold timer (``control_period_s`` > 0) written."""
    hold_repeats: int = 0
    """Answers of the hold timer not written: in a stretch of log time without a message,
    those after its first fail-safe, which repeat the fail-safe action (see
    :func:`refilter_bag`)."""
    fail_safe_answers: dict[str, int] = field(default_factory=dict)
    """Answers written that are the fail-safe action, by kind: ``proposal``, ``refilter``,
    ``hold``."""
    state_from_proposal: int = 0
    """Processed proposals filtered at their own ``state`` section."""
    state_from_topic: int = 0
    """Processed proposals filtered at the latest ``/state``."""
    recorded_commands: int = 0
    """Recorded answers the comparison reads: ``/filter_info`` messages, or ``/cmd_safe`` ones
    in a bag without ``/filter_info``."""
    recorded_topic: str = ''
    """Where the recorded answers came from: ``/filter_info``, ``/cmd_safe`` or '' (none)."""
    compared: int = 0
    """Processed proposals paired with a recorded answer."""
    tolerance: float = DEFAULT_TOLERANCE
    """|Δu| above this counts as changed."""
    changed: int = 0
    """Compared commands with |Δu| = ||u_new - u_recorded||_2 > tolerance."""
    max_abs_du: float = 0.0
    """max |Δu| over compared commands (0 when none)."""
    mean_abs_du: float = 0.0
    """mean |Δu| over compared commands (0 when none)."""
    recorded_active: int = 0
    """Compared commands where the recorded filter acted (|u_s| > 1e-7 in some component)."""
    active: int = 0
    """Processed proposals where the new filter acted (|u_S| > 1e-7, or fail-safe)."""
    max_slack: float = 0.0
    """Largest QP slack of the new filter (solved steps; 0 when none)."""
    slack_exceeded: int = 0
    """Steps whose rows needed more slack than ``slack_tolerance`` (infeasible within the
    limits): the fail-safe action was written."""
    fail_safe: int = 0
    """Processed proposals where the new filter wrote the fail-safe action (refused input,
    failed or unverified solve, slack exceeded); every fail-safe answer: ``fail_safe_answers``."""
    min_h: dict[str, float] = field(default_factory=dict)
    """Smallest new h_i per barrier over the evaluated recorded states."""
    barrier_states: str = ''
    """Which recorded states the barrier statistics cover: '/state' messages, or the
    proposals' state sections when the bag has no usable /state."""
    states_evaluated: int = 0
    """Recorded states evaluated against the new barriers."""
    states_violating: int = 0
    """Evaluated states with some new h_i < 0."""
    violations_per_barrier: dict[str, int] = field(default_factory=dict)
    """Evaluated states with h_i < 0, per barrier."""
    not_copied: dict[str, str] = field(default_factory=dict)
    """Source topics (or some of their messages) the output bag could not hold, and why (a
    type name that is not ``pkg/msg/Type``, a message that is not CDR, ...): left out of the
    copy; a topic the filter reads is still read."""
    not_copied_messages: int = 0
    """Source messages left out of the copy (:attr:`not_copied`)."""

    @property
    def skipped_total(self) -> int:
        """All skipped proposals."""
        return sum(self.skipped.values())

    def to_json(self) -> str:
        """The summary as JSON (NaN/inf written as null)."""
        def clean(value: Any) -> Any:
            if isinstance(value, float) and not math.isfinite(value):
                return None
            if isinstance(value, dict):
                return {k: clean(v) for k, v in value.items()}
            return value
        data = {k: clean(v) for k, v in asdict(self).items()}
        data['skipped_total'] = self.skipped_total
        return json.dumps(data, indent=2, sort_keys=False)

    def format(self) -> str:
        """Human-readable report."""
        skipped = ', '.join(f'{n} {reason}' for reason, n in sorted(self.skipped.items()))
        lines = [
            f're-filtered {self.source} -> {self.output}',
            'topics: ' + ', '.join(f'{name} {topic}' for name, topic in self.topics.items()),
            f'new filter: {self.system}, {len(self.barrier_names)} barriers',
            f'proposals: {self.proposals}   processed: {self.processed} '
            f'(own state {self.state_from_proposal}, /state {self.state_from_topic})   '
            f'skipped: {self.skipped_total}' + (f' ({skipped})' if skipped else ''),
            f'answers: proposal {self.proposals}   re-filter {self.refilters}   hold '
            f'{self.holds}' + (f' (+{self.hold_repeats} repeats not written)'
                               if self.hold_repeats else '')
            + '   fail-safe: ' + ', '.join(f'{kind} {self.fail_safe_answers.get(kind, 0)}'
                                          for kind in ANSWER_KINDS),
            f'recorded {self.recorded_topic or "/cmd_safe"}: {self.recorded_commands}   '
            f'compared: {self.compared}   '
            f'changed (|du| > {self.tolerance:g}): {self.changed}',
            f'|du| max {self.max_abs_du:.6g}   mean {self.mean_abs_du:.6g}',
            f'filter active: new {self.active} of {self.processed}, recorded '
            f'{self.recorded_active} of {self.compared} compared',
            f'max slack {self.max_slack:.3g}   slack exceeded {self.slack_exceeded}   '
            f'fail-safe {self.fail_safe}',
            f'states ({self.barrier_states}): {self.states_evaluated} evaluated, '
            f'{self.states_violating} violate the new barriers (h_i < 0)',
        ]
        for name in self.barrier_names:
            lines.append(f'  {name:24s} min h {self.min_h.get(name, math.nan):10.4f}   '
                         f'violating states {self.violations_per_barrier.get(name, 0)}')
        if self.not_copied:
            lines.append(f'not copied: {self.not_copied_messages} messages of '
                         f'{len(self.not_copied)} topics: ' + '; '.join(
                             f'{topic}: {why}' for topic, why in list(
                                 self.not_copied.items())[:MAX_NOT_COPIED_SHOWN]))
        return '\n'.join(lines)


# -- parameters ------------------------------------------------------------------------------

def resolve_params(params: str | os.PathLike[str] | Mapping[str, Any], *,
                   node: str = 'safety_filter') -> dict[str, Any]:
    """Flat parameters from a params file (path, or a packaged name like ``unicycle``) and its
    ``node`` section (``/**`` merged in), or from a flat / nested dict.

    Raises:
        RefilterError: the file does not exist or is not a ROS 2 params file.
    """
    if isinstance(params, Mapping):
        return flatten(params)
    path = Path(params)
    try:
        if not path.is_file():
            path = find_config(str(params))
        flat = load_params(path, node)
    except FileNotFoundError as exc:
        raise RefilterError(f'params file: {exc}') from exc
    except OSError as exc:  # unreadable, or not a regular file (a FIFO, a device)
        raise RefilterError(f'params file {str(path)!r}: {exc.strerror or exc}') from exc
    except ValueError as exc:
        raise RefilterError(f'params file: {exc}') from exc
    if not flat:
        raise RefilterError(f'params file {str(path)!r}: no ros__parameters for node {node!r} '
                            'or /**')
    _check_node_section(path, node)
    return flat


ROS_NODE_PARAMETERS = ('use_sim_time', 'start_type_description_service')
"""Parameters every ROS 2 node declares: a safety filter's section may set them."""


def _check_node_section(path: Path, node: str) -> None:
    """Refuse a ``node`` that the params file's sections do not name, or name as another
    node's: in a file with sections besides ``/**``, one of them must match ``/<node>`` (a
    typo would build the filter from ``/**`` alone), and every key of those must be a safety
    filter's (``--node unicycle_lidar`` would build one from the simulator's obstacles).

    Raises:
        RefilterError: naming the sections there are, or the keys no filter takes.
    """
    rules = ParamRules()
    rules.add_file(path)
    fully_qualified = f'/{node}'
    named = {key: values for key, values in rules.sections().items() if key != WILDCARD_KEY}
    mine = {key: values for key, values in named.items()
            if key_matches(key, fully_qualified)}
    if named and not mine:
        raise RefilterError(f'--node {node[:80]!r}: no section of {str(path)!r} names it '
                            f'(sections: {", ".join(list(rules.sections())[:20])})')
    foreign = [name for values in mine.values() for name in values
               if not (logic.feeds_the_filter(name) or name in ROS_NODE_PARAMETERS
                       or name.startswith('qos_overrides.'))]
    if foreign:
        raise RefilterError(
            f'--node {node[:80]!r}: section {", ".join(mine)} of {str(path)!r} is not a safety '
            f"filter's: {', '.join(sorted(set(foreign))[:8])} "
            f'{"is not a" if len(set(foreign)) == 1 else "are not"} safety_filter parameter'
            f'{"" if len(set(foreign)) == 1 else "s"}')


def build_filter(flat: Mapping[str, Any]) -> tuple[FilterConfig, logic.NodeSettings,
                                                   SafetyFilter]:
    """The filter exactly as the safety_filter node builds it from the same parameters.

    Raises:
        RefilterError: ``params: <key>: <problem>``.
    """
    try:
        settings = logic.node_settings_from_params(flat)
        config = filter_config_from_params(flat)
        settings = logic.state_frame_settings(settings, config)  # the node's state frame
        safety_filter = logic.build_safety_filter(config=config, settings=settings)
    except (ValueError, TypeError, ImportError, AttributeError) as exc:
        raise RefilterError(f'params: {exc}') from exc
    return config, settings, safety_filter


# -- source bag ------------------------------------------------------------------------------

@dataclass(frozen=True)
class _SourceTopic:
    name: str
    type_name: str
    definition: str | None
    type_hash: str | None
    qos: tuple[Any, ...]
    several_types: str = ''
    """Why the topic cannot be read as one type (:func:`several_types`), else ''."""


def _source_topics(path: str | os.PathLike[str]) -> dict[str, _SourceTopic]:
    """Topics of the source bag with their schema text and hash (copied as recorded).

    Every file of the bag is checked in full first (:func:`rcbf_ros.bag.bag_info`): a damaged,
    empty, foreign or cut-short file raises :class:`rcbf_ros.bag.BagError`.
    """
    info = bag_info(path, allow_cut_short=False)
    store = jazzy_typestore()
    topics = {}
    for name, topic in info.topics.items():
        definition, type_hash = None, None
        if topic.schema_encoding == 'ros2msg':
            definition, type_hash = topic.message_definition, topic.type_hash
        if definition is None and topic.type_name not in store.fielddefs:
            raise RefilterError(f'{name}: type {topic.type_name!r} has no stored schema and is '
                                'not in the ROS 2 Jazzy type store')
        topics[name] = _SourceTopic(name, topic.type_name, definition, type_hash,
                                    topic.offered_qos, several_types(topic))
    return topics


def _array_sections(topic: str, log_time_ns: int, data: bytes, type_name: str,
                    default_label: str) -> dict[str, np.ndarray]:
    if type_name != FLOAT64_MULTIARRAY:
        raise RefilterError(f'{topic}: type {type_name!r} is not supported (re-filtering reads '
                            f'{FLOAT64_MULTIARRAY} sections)')
    try:
        return filter_edge.float64_sections(data, default_label=default_label)
    except ValueError as exc:  # undecodable bytes, or a layout that does not fit
        raise _BadMessage(topic, log_time_ns, _decoding_error(exc)) from exc


class _BadMessage(RefilterError):
    """One recorded proposal or state the node would refuse (undecodable, a layout that does
    not fit): the run stops on a topic's first message (the bag of another system, or not
    one the filter reads); a later one is refused alone, as the node refuses it."""

    def __init__(self, topic: str, log_time_ns: int, reason: str) -> None:
        super().__init__(f'{topic} at log time {log_time_ns}: {reason}')
        self.reason = reason


def _decoding_error(exc: ValueError) -> str:
    """What the edge refused, as the safety_filter node says it."""
    return (f'undecodable sample: {exc}' if isinstance(exc, filter_edge.Undecodable)
            else str(exc))


def _proposal_sections(item: Any, settings: logic.NodeSettings
                       ) -> tuple[dict[str, np.ndarray], Any]:
    """The sections of a recorded proposal, read as the node reads them
    (:func:`rcbf_ros.node_logic.filter_edge.proposal_sections`: a Float64MultiArray's, or ``u``
    of a Twist or TwistStamped in the new parameters' ``twist_fields``); and the
    TwistStamped's header (else None)."""
    if item.type_name in (TWIST, TWIST_STAMPED):
        try:
            return filter_edge.proposal_sections(item.data, type_name=item.type_name,
                                                 twist_fields=settings.twist_fields)
        except ValueError as exc:
            raise _BadMessage(item.topic, item.log_time_ns, _decoding_error(exc)) from exc
    return _array_sections(item.topic, item.log_time_ns, item.data, item.type_name, 'u'), None


def _state_sections(item: Any, settings: logic.NodeSettings, system: str,
                    child_frame_id: str = '') -> tuple[dict[str, np.ndarray], int | None] | str:
    """The sections of a recorded state (an Odometry's as the node reads it) and an
    Odometry's header stamp (ns; None for an array), or why an Odometry is refused
    (undecodable, a wrong frame or child frame, an orientation without heading)."""
    if item.type_name == ODOMETRY:
        try:
            return filter_edge.stamped_state_sections(item.data, type_name=ODOMETRY,
                                                      system=system,
                                                      frame_id=settings.state_frame_id,
                                                      child_frame_id=child_frame_id)
        except ValueError as exc:
            if str(exc).startswith('state_type:'):
                raise RefilterError(f'{item.topic}: {exc}') from exc
            return _decoding_error(exc)
    return _array_sections(item.topic, item.log_time_ns, item.data, item.type_name,
                           'state'), None


def _state_sample(item: Any, settings: logic.NodeSettings, system: str,
                  n_x: int, first: bool = True, child_frame_id: str = '') -> logic.StateSample:
    """The state sample of a recorded state message, received at its log time, as the node's
    edge reads it: a bad one says why (an Odometry the node would refuse, an empty message, a
    NaN); an Odometry's header stamp kept for the ``latency_s`` check.

    Raises:
        RefilterError: the topic's ``first`` state of another length than the new system's
            ``n_x`` (a later one is a bad state, as the node reads it).
    """
    received_ns = item.log_time_ns
    try:
        read = _state_sections(item, settings, system, child_frame_id)
    except _BadMessage as exc:
        if first:
            raise
        return logic.StateSample(received_ns, None, exc.reason)
    if isinstance(read, str):  # an Odometry the node would refuse
        return logic.StateSample(received_ns, None, read)
    sections, stamp_ns = read
    values = sections.get('state', next(iter(sections.values()), None))
    if values is None:
        return logic.StateSample(received_ns, None, 'state: empty message')
    if first:
        _check_length(item.topic, received_ns, 'state', values, n_x, 'n_x', system)
    try:
        state = logic.state_from_sections(sections=sections, n_x=n_x)
    except ValueError as exc:
        return logic.StateSample(received_ns, None, str(exc))
    return logic.StateSample(received_ns, state, stamp_ns=stamp_ns)


def _stamped(header: Any, stamp_ns: int) -> Any:
    """A re-filtered answer's header: the proposal's frame_id (none: ''), stamped
    ``stamp_ns``, as the node stamps one with its clock at the answer."""
    stamp = SimpleNamespace(sec=stamp_ns // 1_000_000_000, nanosec=stamp_ns % 1_000_000_000)
    return SimpleNamespace(stamp=stamp, frame_id='' if header is None else header.frame_id)


MAX_NOT_COPIED_SHOWN = 5
"""Topics left out of the copy named in :meth:`RefilterSummary.format` (all are in the JSON)."""


def _copy(writer: BagWriter, item: Any, summary: RefilterSummary) -> None:
    """Copy one source message into the output, or leave it out and count it when the output
    cannot hold it (its topic refused at registration, or the message itself: not CDR)."""
    if item.topic in summary.not_copied:
        summary.not_copied_messages += 1
        return
    try:
        writer.write(item.topic, item.data, item.log_time_ns, item.publish_time_ns)
    except ValueError as exc:
        summary.not_copied.setdefault(item.topic, filter_edge.one_line(exc))
        summary.not_copied_messages += 1


def _check_length(topic: str, log_time_ns: int, label: str, values: np.ndarray, size: int,
                  what: str, system: str) -> None:
    """Refuse the run when a topic's first message has another length than the new system's:
    the bag of another system (a later message of a wrong length is refused alone, answered
    with the fail-safe, as the node answers it)."""
    if values.size != size:
        raise RefilterError(
            f'{topic} at log time {log_time_ns}: {label} has {values.size} values but the new '
            f'system {system!r} has {what} = {size} (parameters for another system?)')


def resolve_topic(name: str, key: str) -> str:
    """``name`` as the node resolves it in the root namespace (``odom`` -> ``/odom``), checked
    against rcl's rules for a topic name (letters, digits, ``_`` and ``/`` separated tokens not
    starting with a digit; ``~`` and substitutions are not taken here).

    Raises:
        RefilterError: naming ``key`` and the name.
    """
    text = name if isinstance(name, str) else ''
    try:
        if text.startswith('~') or '{' in text:
            raise RosArgumentError('no node here to expand it')
        full = expand_topic_name(text, 'refilter', '/')  # rcl's token rules, one place
        if len(full) > TOPIC_NAME_LIMIT:
            raise RosArgumentError(f'longer than {TOPIC_NAME_LIMIT} characters')
    except RosArgumentError:
        raise RefilterError(f'{key}: {str(name)[:80]!r} is not a topic name (letters, digits, '
                            f'_ and / separated tokens, at most {TOPIC_NAME_LIMIT} characters)'
                            ) from None
    return full


def topic_names(remaps: Mapping[str, str], bag_topics: Sequence[str]) -> dict[str, str]:
    """The bag's topic for each of the node's (:data:`NODE_TOPICS`), from ``remaps`` (the
    node's names or the drop-in launch's arguments, :data:`LAUNCH_ARGUMENTS`, -> topic names).

    The names not given are the launch's defaults (:data:`DROP_IN_TOPICS`) when some launch
    argument is given, as the launch fills them; the node's own names when only node names
    are given. Without remaps: the node's own names when the bag has ``/cmd_proposed``, else
    the drop-in launch's defaults when it has their ``cmd_in``.

    Raises:
        RefilterError: an unknown name, a name given twice, a topic that is not a name, or two
            of the node's topics on one bag topic.
    """
    names = dict(NODE_TOPICS)
    if any(key in LAUNCH_ARGUMENTS for key in remaps) or (
            not remaps and PROPOSAL_TOPIC not in bag_topics
            and DROP_IN_TOPICS['cmd_proposed'] in bag_topics):
        names = dict(DROP_IN_TOPICS)
    given: dict[str, str] = {}
    for key, topic in remaps.items():
        node_name = LAUNCH_ARGUMENTS.get(key, key)
        if node_name not in NODE_TOPICS:
            raise RefilterError(
                f'{key}:={topic}: unknown topic name; known: '
                f'{", ".join([*LAUNCH_ARGUMENTS, *NODE_TOPICS])}')
        if node_name in given:
            raise RefilterError(f'{key}:={topic}: {node_name} is remapped twice '
                                f'({given[node_name]}:=...)')
        given[node_name] = key
        names[node_name] = resolve_topic(topic, key)
    refusal = topic_refusal(None, [topic.name for topic in INTERFACE.topics],
                            node_resolver(names))
    if refusal:
        raise RefilterError(refusal)
    return names


def node_resolver(names: Mapping[str, str], node: str = NODE_NAME) -> Callable[[str], str]:
    """A name as the node ``node`` in the root namespace resolves it under the remaps
    ``names`` (its topic names -> the bag's, :func:`topic_names`): for the node's topic clash
    rule (:func:`rcbf_ros.node_logic.sources.topic_refusal`), the same here as in the node.
    A name with ``~`` or a substitution is expanded for the middleware's own services only."""
    node = node.rsplit('/', 1)[-1]
    try:
        check_node_name(node)
    except RosArgumentError:
        node = NODE_NAME
    remapped = {'/' + name: topic for name, topic in names.items()}  # as rcl matches a rule

    def resolve(name: str) -> str:
        text = name if isinstance(name, str) else ''
        if name not in MIDDLEWARE_TOPICS and (text.startswith('~') or '{' in text):
            raise RosArgumentError('no node here to expand it')
        full = expand_topic_name(text, node, '/')
        if len(full) > TOPIC_NAME_LIMIT:
            raise RosArgumentError(f'longer than {TOPIC_NAME_LIMIT} characters')
        return remapped.get(full, full)
    return resolve


RecordedAnswers = dict[bytes, deque[tuple[bytes | None, np.ndarray]]]
"""Recorded answers: u_rl bytes -> FIFO of (answered state bytes or None, u)."""


def _bytes(values: np.ndarray | None) -> bytes | None:
    return None if values is None else np.ascontiguousarray(values, np.float64).tobytes()


def _recorded_commands(path: str | os.PathLike[str], topics: Mapping[str, Any],
                       names: Mapping[str, str]) -> tuple[str, int, RecordedAnswers]:
    """(topic, count, answers): the recorded answers, from ``filter_info`` when the bag has
    it, else from a ``cmd_safe`` of the earlier form (``u``, ``u_rl``, ``u_s`` sections);
    ``names``: the bag's topic of each (:func:`topic_names`)."""
    info, command = names['filter_info'], names['cmd_safe']
    topic = info if info in topics else command
    if topic not in topics:
        return '', 0, {}
    answers: RecordedAnswers = defaultdict(deque)
    count = 0
    for item in read_bag(path, topics=[topic]):
        count += 1
        if item.type_name != FLOAT64_MULTIARRAY:
            continue
        sections = _array_sections(item.topic, item.log_time_ns, item.data, item.type_name, 'u')
        if 'u' not in sections or 'u_rl' not in sections:
            continue
        answers[_bytes(sections['u_rl'])].append((_bytes(sections.get('state')),
                                                  sections['u']))
    return topic, count, answers


def _pop_recorded(answers: RecordedAnswers, u_rl: np.ndarray,
                  state: np.ndarray | None) -> np.ndarray | None:
    """The first recorded answer to ``u_rl`` that does not name another state than ``state``
    (None: no state to compare), removed from ``answers``."""
    queue = answers.get(_bytes(u_rl))
    if not queue:
        return None
    wanted = _bytes(state)
    for index, (answered, u) in enumerate(queue):
        if wanted is None or answered is None or answered == wanted:
            del queue[index]
            return u
    return None


# -- barrier statistics ----------------------------------------------------------------------

BARRIER_CHUNK = 256
"""States evaluated together for the barrier statistics: with their K values, all that the
statistics hold in memory, whatever the number of states."""


class _BarrierTally:
    """min h_i and violation counts of the new barriers over states, reduced as they come.

    States are evaluated :data:`BARRIER_CHUNK` at a time and folded into K minima and K counts,
    so the memory is one chunk's (states and K values each), not N x K. Each value is
    :func:`~rcbf_ros.core.lie_closed_form.state_barrier_values`' (the larger of the point
    ahead's and the point behind's where a look-ahead follows the direction of travel): from
    the filter's array rows (:class:`~rcbf_ros.core.lie_closed_form_rows.VectorAssembly`) where
    the problem has a circle family large enough for them, else from that function itself.
    """

    def __init__(self, problem: RCBFProblem) -> None:
        self.problem = problem
        n = problem.n_barriers
        self.count = 0
        """States evaluated."""
        self.violating = 0
        """States with some h_i < 0."""
        self.min_h = np.full(n, np.inf)
        """(K,) smallest h_i so far (NaN once a value was NaN)."""
        self.violations = np.zeros(n, dtype=np.int64)
        """(K,) states with h_i < 0."""
        self._pending: list[np.ndarray] = []
        self._rows = VectorAssembly.from_problem(problem)
        system = problem.system
        self._zeros_x = [0.0] * system.n_x
        self._ahead = [0.0] * system.n_u
        speeds = sorted({s for s in (getattr(f, 'speed_input', None) for f in problem.families)
                         if s is not None})
        self._behind = [-1.0 if j in speeds else 0.0 for j in range(system.n_u)] if speeds \
            else None

    def add(self, state: np.ndarray) -> None:
        """One state (n_x,)."""
        self._pending.append(state)
        if len(self._pending) >= BARRIER_CHUNK:
            self.flush()

    def _values(self, states: np.ndarray) -> np.ndarray:
        """(n, K) barrier values of (n, n_x) states; (n, 0) for a filter whose only obstacles
        are its sources' points (no static barrier to evaluate)."""
        if self.problem.n_barriers == 0:
            return np.empty((len(states), 0))
        if self._rows is None:
            return state_barrier_values(self.problem, states)
        values = np.empty((len(states), self.problem.n_barriers))
        for row, x in zip(values, states.tolist()):
            row[:] = self._rows.evaluate(x, self._ahead, self._zeros_x, self._zeros_x).h
            if self._behind is not None:
                np.maximum(row, self._rows.evaluate(x, self._behind, self._zeros_x,
                                                    self._zeros_x).h, out=row)
        return values

    def flush(self) -> None:
        """Fold the pending states into the statistics."""
        if not self._pending:
            return
        h = self._values(np.stack(self._pending))
        self._pending.clear()
        self.count += len(h)
        self.min_h = np.minimum(self.min_h, h.min(axis=0))
        violated = h < 0
        self.violations += violated.sum(axis=0)
        self.violating += int(violated.any(axis=1).sum())


def _barrier_statistics(summary: RefilterSummary, tally: _BarrierTally) -> None:
    """The summary's min h_i and violation counts of the new barriers, from ``tally``."""
    tally.flush()
    names = summary.barrier_names
    summary.states_evaluated = tally.count
    summary.violations_per_barrier = {name: int(tally.violations[i])
                                      for i, name in enumerate(names)}
    summary.states_violating = tally.violating
    summary.min_h = {name: float(tally.min_h[i]) if tally.count else math.nan
                     for i, name in enumerate(names)}


# -- the job ---------------------------------------------------------------------------------

def refilter_bag(source: str | os.PathLike[str], output: str | os.PathLike[str],
                 params: str | os.PathLike[str] | Mapping[str, Any], *,
                 node: str = 'safety_filter',
                 tolerance: float = DEFAULT_TOLERANCE,
                 remaps: Mapping[str, str] | None = None) -> RefilterSummary:
    """Answer the messages recorded in ``source`` as the node with new parameters would;
    write ``output``.

    The node's rules (:class:`~rcbf_ros.node_logic.answer_rules.AnswerRules`), with the log
    time as the clock: a message is received at its log time; a proposal is answered then; a
    state or source message answers the proposal in force again when ``refilter_on_state``
    says so; ``/tf`` and ``/tf_static`` feed the sources' transforms. The hold timer
    (``control_period_s`` > 0) calls every :func:`logic.hold_timer_period_s` from the first
    message's log time; the calls at or before a message's log time come before it, none
    after the last message, and only those that answer are made (:class:`_HoldTimer`: in a
    stretch without messages, the answers after its first fail-safe repeat it and are counted
    as ``hold_repeats``, not written). An Odometry's header stamp is aged against the log time
    of the decision too (the node ages it against its ROS clock), and a source message's
    stamp likewise: stamps on another clock than the log times (simulation time recorded on
    the wall clock) make every such state late once ``latency_s`` applies. What differs from
    a run of the node: its timer's jitter and phase, the time its callbacks take (an answer
    here takes none), and its clocks (monotonic and ROS) where the bag has the recorder's.

    Each answer is written at its log time; a re-filter's or a hold's TwistStamped carries
    the proposal's frame_id, stamped then. The answers to proposals are paired with the
    recorded answers (:func:`_pop_recorded`: first come first served by ``u_rl``, and by the
    state where both name one); those to states, sources and the timer are not paired.

    Args:
        source: bag directory or ``.mcap`` file with the proposals (``/cmd_proposed``, or the
            drop-in launch's ``cmd_in``), the states, and each observation source's topic.
        output: new bag directory (must not hold a bag yet).
        params: a ROS 2 params file (or packaged config name, e.g. ``unicycle``) read for
            ``node``, or a flat / nested parameter dict.
        node: the params file section to read (``/**`` merged in).
        tolerance: |Δu| above this counts as a changed command.
        remaps: the node's topic names or the drop-in launch's arguments -> the bag's topics
            (:func:`topic_names`), as the launch was given them.

    Returns:
        The summary of what changed.

    Raises:
        RefilterError: missing source bag, no ``/cmd_proposed``, bad parameters (the message
            names the key), a first state or proposal of the wrong length for the new
            system (a later one is answered with the fail-safe, as the node does), a
            source that already holds ``/refilter/*`` topics, an existing output bag, or
            parameters under which the hold timer would answer a quiet controller without
            end (:data:`HOLD_STRETCH_LIMIT`).
    """
    if not tolerance >= 0:
        raise RefilterError(f'tolerance: must be >= 0, got {tolerance}')
    if not os.fspath(output):
        raise RefilterError('output: must not be empty (a new bag directory)')
    try:
        files = mcap_files(source)
    except BagError as exc:
        raise RefilterError(f'source bag: {exc}') from exc
    inside = Path(output).resolve()
    if os.path.abspath(output) == os.path.abspath(source) or any(
            inside == f.resolve().parent for f in files):
        raise RefilterError('output: must not be the source bag')
    if Path(source).is_dir() and Path(source).resolve() in inside.parents:
        raise RefilterError(f'output: {str(output)!r} is inside the source bag {str(source)!r}; '
                            'write the new bag beside it')
    topics = _source_topics(source)
    names = topic_names(dict(remaps or {}), list(topics))
    proposal_topic, state_topic = names['cmd_proposed'], names['state']
    if proposal_topic not in topics:
        hint = ('' if remaps else f"; a bag of the drop-in launch has its cmd_in "
                f"({DROP_IN_TOPICS['cmd_proposed']} unless given): name it, cmd_in:=/topic")
        raise RefilterError(f'source bag {str(source)!r} has no {proposal_topic} topic '
                            f'(topics: {sorted(topics)}){hint}')
    if state_topic not in topics and topics[proposal_topic].type_name in (TWIST, TWIST_STAMPED):
        raise RefilterError(
            f'source bag {str(source)!r} has no {state_topic} topic, and its proposals '
            f'({proposal_topic}, {topics[proposal_topic].type_name}) carry no state: name the '
            'state topic, odom:=/topic')
    clashing = sorted(t for t in topics if t in OUTPUT_TOPICS)
    if clashing:
        raise RefilterError(f'source bag already holds {clashing} (re-filter the original run)')
    flat = resolve_params(params, node=node)
    config, settings, safety_filter = build_filter(flat)
    sources, source_topics = _sources(config, topics, names, node)
    read = [proposal_topic, state_topic, *source_topics, *(TF_TOPICS if sources else ())]
    for topic in (t for t in read if t in topics and topics[t].several_types):
        raise RefilterError(f'{topic}: {topics[topic].several_types}; the node subscribes to '
                            f'it as {topics[topic].type_name} and would not receive the others')
    system_name = str(flat.get('system'))
    n_x, n_u = safety_filter.n_x, safety_filter.n_u
    summary = RefilterSummary(source=str(source), output=str(output), system=system_name,
                              barrier_names=list(safety_filter.problem.barrier_names),
                              tolerance=float(tolerance), topics=dict(names))
    summary.topics.update({name: topic for topic, name in source_topics.items()})
    summary.recorded_topic, summary.recorded_commands, recorded = _recorded_commands(
        source, topics, names)
    active = logic.ActiveFilter(params=flat, settings=settings, config=config,
                                safety_filter=safety_filter)
    rules = AnswerRules(sources)  # no stamp clock: a stamp is aged against the log time
    timer = _HoldTimer(logic.hold_timer_period_s(config.control_period_s))

    absent = [d for d in (Path(output), *Path(output).parents) if not os.path.lexists(d)]
    try:
        writer = BagWriter(output)
    except (FileExistsError, ValueError) as exc:
        raise RefilterError(f'output: {exc}') from exc
    deltas: list[float] = []
    # The statistics cover the /state messages, or the proposals' states in a bag without a
    # usable /state: the proposals' tally is dropped at the first state message.
    topic_states = _BarrierTally(safety_filter.problem)
    proposal_states: _BarrierTally | None = _BarrierTally(safety_filter.problem)
    skipped: dict[str, int] = defaultdict(int)
    fail_safes: dict[str, int] = dict.fromkeys(ANSWER_KINDS, 0)
    info_layouts: dict[Any, Any] = {}
    command_type = FLOAT64_MULTIARRAY

    def write_answer(kind: str, decision: logic.Decision, log_time_ns: int) -> None:
        """One answer at ``log_time_ns``, as the node publishes it: a proposal's with the
        proposal's header, a re-filter's or a hold's with its frame_id stamped then."""
        held = rules.held
        header = None if held is None else held.sample.header
        if kind != 'proposal' and command_type == TWIST_STAMPED:
            header = _stamped(header, log_time_ns)
        if decision.fail_safe:
            fail_safes[kind] += 1
        writer.write(OUTPUT_COMMAND_TOPIC, filter_edge.command_cdr(
            decision.u_safe, type_name=command_type, twist_fields=settings.twist_fields,
            header=header), log_time_ns)
        writer.write(OUTPUT_INFO_TOPIC, filter_edge.info_cdr(decision, info_layouts),
                     log_time_ns)
        writer.write(OUTPUT_DIAGNOSTICS_TOPIC, filter_edge.diagnostics_cdr(
            decision, barrier_names=safety_filter.barrier_names, stamp_ns=log_time_ns,
            name=settings.diagnostics_name, hardware_id=settings.diagnostics_hardware_id),
            log_time_ns)

    seen_state = False  # a state read: later ones of a wrong length are refused alone

    def refilter(log_time_ns: int) -> None:
        """A new state or source message: the proposal in force again, if due."""
        decision = rules.refilter(now_ns=log_time_ns, active=active)
        if decision is not None:
            write_answer('refilter', decision, log_time_ns)

    try:
        with writer:
            for topic in topics.values():
                if topic.several_types:  # its messages cannot share one output channel
                    summary.not_copied[topic.name] = (f'{topic.several_types}; one output '
                                                      'channel holds one')
                    continue
                try:
                    writer.add_topic(topic.name, topic.type_name, topic.qos or None,
                                     message_definition=topic.definition,
                                     type_hash=topic.type_hash)
                except ValueError as exc:  # a channel the output cannot hold: left out
                    summary.not_copied[topic.name] = filter_edge.one_line(exc)
            command_type = topics[proposal_topic].type_name
            if command_type not in (TWIST, TWIST_STAMPED):
                command_type = FLOAT64_MULTIARRAY
            writer.add_topic(OUTPUT_COMMAND_TOPIC, command_type)
            writer.add_topic(OUTPUT_INFO_TOPIC, FLOAT64_MULTIARRAY)
            writer.add_topic(OUTPUT_DIAGNOSTICS_TOPIC, DIAGNOSTIC_ARRAY)
            for item in read_bag(source):
                if item.log_time_ns > LATEST_LOG_TIME_NS:  # before any answer reaches it
                    raise RefilterError(
                        f'{item.topic} at log time {item.log_time_ns}: later than '
                        f'{LATEST_LOG_TIME_NS} ns, the latest builtin_interfaces/msg/Time '
                        '(2038-01-19) an answer can be stamped with')
                for tick_ns, decision in timer.calls(rules, active, until_ns=item.log_time_ns):
                    write_answer('hold', decision, tick_ns)
                _copy(writer, item, summary)
                if item.topic in source_topics:  # what the node's source callback reads
                    sources.read(source_topics[item.topic], item.data,  # type: ignore[union-attr]
                                 received_ns=item.log_time_ns)
                    refilter(item.log_time_ns)
                elif sources is not None and item.topic in TF_TOPICS:
                    sources.read_tf(item.data, static=item.topic == TF_TOPICS[1],
                                    now_ns=item.log_time_ns)  # the bag's time: the clock
                elif item.topic == state_topic:
                    sample = _state_sample(item, settings, system_name, n_x,
                                           first=not seen_state,
                                           child_frame_id=active.robot_frame_id)
                    seen_state = True
                    rules.latest_state = sample
                    if sample.state is not None:
                        topic_states.add(sample.state)
                        proposal_states = None
                    refilter(item.log_time_ns)
                elif item.topic == proposal_topic:
                    summary.proposals += 1
                    proposal, error = None, ''
                    try:
                        sections, header = _proposal_sections(item, settings)
                    except _BadMessage as exc:  # the first one stops the run; later: refused
                        if summary.proposals == 1:
                            raise
                        sections, header, error = {}, None, exc.reason
                    for label, size, what in (('u', n_u, 'n_u'), ('state', n_x, 'n_x'),
                                              ('disturbance_mean', n_x, 'n_x'),
                                              ('disturbance_std', n_x, 'n_x')):
                        if label in sections and summary.proposals == 1:
                            _check_length(item.topic, item.log_time_ns, label, sections[label],
                                          size, what, system_name)
                    try:
                        if not error:
                            proposal = logic.proposal_from_sections(sections=sections, n_u=n_u,
                                                                    n_x=n_x)
                    except ValueError as exc:
                        error = str(exc)
                    decision = rules.propose(logic.ProposalSample(proposal, error, header),
                                             now_ns=item.log_time_ns, active=active)
                    assert decision is not None  # a sample read is always answered
                    write_answer('proposal', decision, item.log_time_ns)
                    if decision.result is None:
                        skipped[logic.reason_key(decision.reason)] += 1
                        continue
                    assert proposal is not None
                    _account(summary, decision, proposal, recorded, deltas, tolerance)
                    if proposal.state is not None and proposal_states is not None:
                        proposal_states.add(proposal.state)
        summary.refilters = rules.refilters
        summary.holds, summary.hold_repeats = rules.holds - timer.repeats, timer.repeats
        summary.fail_safe_answers = fail_safes
        summary.skipped = dict(skipped)
        if deltas:
            summary.max_abs_du = float(np.max(deltas))
            summary.mean_abs_du = float(np.mean(deltas))
        if proposal_states is None:
            summary.barrier_states = state_topic
            _barrier_statistics(summary, topic_states)
        else:
            summary.barrier_states = f'{proposal_topic} state sections'
            _barrier_statistics(summary, proposal_states)
    except BaseException:  # bad input, a defect or Ctrl-C: no bag of a run that failed is left
        _discard(writer, absent)
        raise
    return summary


class _HoldTimer:
    """The node's hold timer in log time: a call every ``period_s`` from the first message's
    log time on; the calls at or before a message's log time are made, in order, before it,
    and none after the last message.

    Only the calls that answer are made. None answers before the first answer; after an
    answer the next call that does is the first one ``control_period_s - period_s`` or more
    later (:func:`logic.hold_due`), reached by arithmetic and checked by hold_due itself, so
    a long stretch without messages costs nothing when nothing is held. In a stretch without
    messages only time moves, and every age only grows: once an answer of the stretch is the
    fail-safe, each later call of the stretch that answers repeats it; those are counted
    (:attr:`repeats`, and in the rules' holds and latest answer, as the node's would be), not
    made. No call answers past the rules' quiet (:meth:`AnswerRules.quiet_from_ns`: a stale
    proposal's fail-safe gone out for ``stop_pub_timeout``). A stretch with more than
    :data:`HOLD_STRETCH_LIMIT` answers and no fail-safe among them is refused
    (:class:`RefilterError`).
    """

    def __init__(self, period_s: float | None) -> None:
        """Args: period_s: the timer's period (:func:`logic.hold_timer_period_s`; None: no
        timer, ``control_period_s`` 0)."""
        self.period_s = period_s
        self.period_ns = 0 if period_s is None else max(1, round(period_s * 1e9))
        self.origin_ns: int | None = None
        """The log time of the first call (the first message's)."""
        self.next_call = 0
        """The index of the next call not yet made or skipped."""
        self.repeats = 0
        """Answers of the fail-safe counted, not made (see the class docstring)."""

    def calls(self, rules: AnswerRules, active: logic.ActiveFilter, *, until_ns: int
              ) -> Iterator[tuple[int, logic.Decision]]:
        """The answers (log time, decision) of the calls up to ``until_ns`` (a message's log
        time) not made yet, in order.

        Raises:
            RefilterError: more than :data:`HOLD_STRETCH_LIMIT` answers before ``until_ns``
                without a fail-safe.
        """
        if self.period_s is None:
            return
        if self.origin_ns is None:
            self.origin_ns = until_ns
        last_call = (until_ns - self.origin_ns) // self.period_ns
        made = 0
        while rules.last_answer_ns is not None:
            answering = self._answering(rules, active, last_call)
            if self.next_call > answering:
                break
            call = self._first_due(rules.last_answer_ns, active)
            if call > answering:
                break
            now_ns = self.origin_ns + call * self.period_ns
            self.next_call = call + 1
            decision = rules.hold(now_ns=now_ns, timer_period_s=self.period_s, active=active)
            if decision is None:  # not due after all (checked in _first_due): go on
                continue
            yield now_ns, decision
            if decision.fail_safe:  # (the quiet moves with the fail-safe's first answer)
                self._repeat(rules, active, call, self._answering(rules, active, last_call))
                break
            made += 1
            if made >= HOLD_STRETCH_LIMIT:
                config, settings = active.config, active.settings
                raise RefilterError(
                    f'log time {now_ns}: the hold timer answered {made} times since the last '
                    f'message and would go on (control_period_s = {config.control_period_s:g}, '
                    f'latency_s = {config.latency_s:g}, max_proposal_age_s = '
                    f'{settings.max_proposal_age_s:g}): a quiet controller is never stopped '
                    'with these parameters')
        self.next_call = max(self.next_call, last_call + 1)

    def _answering(self, rules: AnswerRules, active: logic.ActiveFilter, last_call: int
                   ) -> int:
        """The last call up to ``last_call`` that may answer: none past the rules' quiet
        (:meth:`AnswerRules.quiet_from_ns`, as the answers so far leave it)."""
        assert self.origin_ns is not None
        quiet_from = rules.quiet_from_ns(active)
        if quiet_from is None:
            return last_call
        return min(last_call, (quiet_from - self.origin_ns) // self.period_ns)

    def _due(self, last_answer_ns: int, call: int, active: logic.ActiveFilter) -> bool:
        assert self.origin_ns is not None and self.period_s is not None
        return logic.hold_due(control_period_s=active.config.control_period_s,
                              timer_period_s=self.period_s, last_answer_ns=last_answer_ns,
                              now_ns=self.origin_ns + call * self.period_ns)

    def _first_due(self, last_answer_ns: int, active: logic.ActiveFilter) -> int:
        """The first call from :attr:`next_call` on that answers after an answer at
        ``last_answer_ns``: hold_due's inequality solved for the call's index, then checked
        by hold_due (a step or two either way for its rounding)."""
        assert self.origin_ns is not None and self.period_s is not None
        wait_ns = (active.config.control_period_s - self.period_s) * 1e9
        call = max(self.next_call, math.ceil(
            (last_answer_ns - self.origin_ns + wait_ns) / self.period_ns))
        while call > self.next_call and self._due(last_answer_ns, call - 1, active):
            call -= 1
        while not self._due(last_answer_ns, call, active):
            call += 1
        return call

    def _repeat(self, rules: AnswerRules, active: logic.ActiveFilter, call: int,
                last_call: int) -> None:
        """After the fail-safe answered at ``call``: the later calls up to ``last_call`` that
        answer (every ``step``-th: the answer moves the next one on) counted as repeats."""
        answer_ns = rules.last_answer_ns
        assert answer_ns is not None and self.origin_ns is not None
        step = 1
        while not self._due(answer_ns, call + step, active):
            step += 1
        count = (last_call - call) // step
        if count:
            self.repeats += count
            rules.holds += count
            rules.answered(self.origin_ns + (call + count * step) * self.period_ns,
                           fail_safe=True)


def _sources(config: FilterConfig, topics: Mapping[str, Any], names: Mapping[str, str],
             node: str = NODE_NAME) -> tuple[ObservationSources | None, dict[str, str]]:
    """The observation sources of the new parameters, read from the bag as the node's
    subscriptions read them, and each source's bag topic -> its name (none: ``None, {}``).

    Raises:
        RefilterError: a source whose topic the bag lacks, holds another type, or clashes
            with another of the node's names (the node's rule, :func:`topic_refusal`).
    """
    if config.sources is None:
        return None, {}
    refusal = topic_refusal(config.sources, [topic.name for topic in INTERFACE.topics],
                            node_resolver(names, node))
    if refusal:
        raise RefilterError(refusal)
    by_topic: dict[str, str] = {}
    for name, source in config.sources.sources:
        key = f'{name}.topic'
        topic = resolve_topic(source.topic, key)
        wanted = SENSOR_MESSAGES[source.type]
        if topic not in topics:
            raise RefilterError(f'{key}: the source bag has no {topic} topic (topics: '
                                f'{sorted(topics)[:20]})')
        if topics[topic].type_name != wanted:
            raise RefilterError(f'{key}: {topic} holds {topics[topic].type_name}, not the '
                                f'{wanted} of {name}.type {source.type}')
        by_topic[topic] = name
    return ObservationSources(config.sources), by_topic


def _account(summary: RefilterSummary, decision: logic.Decision, proposal: logic.Proposal,
             recorded: RecordedAnswers,
             deltas: list[float], tolerance: float) -> None:
    """Add one filtered proposal to the summary (and pair it with its recorded answer)."""
    result = decision.result
    assert result is not None
    summary.processed += 1
    if decision.state_source == 'proposal':
        summary.state_from_proposal += 1
    else:
        summary.state_from_topic += 1
    if result.active:
        summary.active += 1
    if decision.fail_safe:
        summary.fail_safe += 1
    elif math.isfinite(result.slack):
        summary.max_slack = max(summary.max_slack, result.slack)
    if logic.reason_key(decision.reason) == 'slack_exceeded':
        summary.slack_exceeded += 1
    old = _pop_recorded(recorded, proposal.u, proposal.state)
    if old is None or old.shape != decision.u_safe.shape:
        return
    summary.compared += 1
    if np.any(np.abs(old - proposal.u) > ACTIVE_TOLERANCE):
        summary.recorded_active += 1
    delta = float(np.linalg.norm(decision.u_safe - old))
    deltas.append(delta)
    if delta > tolerance:
        summary.changed += 1


def _discard(writer: BagWriter, created: Sequence[Path] = ()) -> None:
    """Remove a half-written output bag after an error, and the directories made for it
    (``created``, deepest first: those that did not exist before; a directory something else
    was written into meanwhile stays)."""
    try:
        writer.close()
    except Exception:  # noqa: BLE001 - best effort; the error being raised matters more
        pass
    for path in (writer.mcap_path, writer.directory / 'metadata.yaml'):
        if path.exists():
            path.unlink()
    for directory in (writer.directory, *created):
        try:
            directory.rmdir()
        except OSError:
            pass


# -- command line ----------------------------------------------------------------------------

def main(argv: Sequence[str] | None = None) -> int:
    """``rcbf_ros refilter`` (also the console script ``rcbf_ros_refilter``). Returns 0, or 2
    on bad input (message on stderr), 1 when the summary's JSON cannot be written after the
    run (the new bag kept)."""
    parser = argparse.ArgumentParser(
        prog='rcbf_ros refilter',
        description='Run the safety filter over the proposals recorded in a bag with other '
                    'parameters; write a new bag with /refilter/cmd_safe and '
                    '/refilter/diagnostics and print what changed.')
    parser.add_argument('source', help='recorded bag directory or .mcap file')
    parser.add_argument('output', help='new bag directory (must not exist yet)')
    parser.add_argument('--params-file', required=True,
                        help='ROS 2 params YAML (or a packaged config name, e.g. unicycle)')
    parser.add_argument('--node', default='safety_filter',
                        help='params file section to read (default: safety_filter)')
    parser.add_argument('--tolerance', type=float, default=DEFAULT_TOLERANCE,
                        help=f'|du| counted as a change (default {DEFAULT_TOLERANCE:g})')
    parser.add_argument('--json', dest='json_path', default=None,
                        help='also write the summary as JSON to this file')
    parser.add_argument('remaps', nargs='*', metavar='NAME:=TOPIC',
                        help="the bag's topic of a node topic (cmd_proposed, state, cmd_safe, "
                             'filter_info) or of a drop-in launch argument (cmd_in, odom, '
                             "cmd_out), as given to the launch; default: the node's names, or "
                             "the drop-in launch's defaults (/cmd_vel_nav, /odom, /cmd_vel) "
                             'in a bag without /cmd_proposed')
    # the remaps may come after the options, as a launch's arguments do
    args = parser.parse_intermixed_args(None if argv is None else list(argv))
    remaps: dict[str, str] = {}
    for text in args.remaps:
        key, sep, topic = text.partition(':=')
        if not sep or not key:
            print(f'rcbf_ros refilter: error: {text[:80]!r}: not NAME:=TOPIC (for example '
                  'cmd_in:=/cmd_vel_nav)', file=sys.stderr)
            return 2
        if key in remaps:
            print(f'rcbf_ros refilter: error: {key}:= given twice', file=sys.stderr)
            return 2
        remaps[key] = topic
    if args.json_path is not None:
        problem = (_json_path_problem(args.json_path)
                   or _json_input_clash(args.json_path, args.source, args.params_file))
        if problem:
            print(f'rcbf_ros refilter: error: --json {args.json_path!r}: {problem}',
                  file=sys.stderr)
            return 2
    try:
        summary = refilter_bag(args.source, args.output, args.params_file, node=args.node,
                               tolerance=args.tolerance, remaps=remaps)
    except (RefilterError, BagError, OSError) as exc:
        # A bag that cannot be read (BagError: the file and what is wrong, e.g. a chunk's CRC
        # mismatch), bad parameters, an output that cannot be written: one line, exit 2.
        print(f'rcbf_ros refilter: error: {exc}', file=sys.stderr)
        return 2
    print(summary.format())
    if args.json_path:
        try:
            Path(args.json_path).write_text(summary.to_json() + '\n')
        except OSError as exc:
            print(f'rcbf_ros refilter: error: --json {args.json_path!r}: cannot write '
                  f'({exc.strerror or exc}); the bag {args.output!r} is kept', file=sys.stderr)
            return 1
    return 0


def _json_path_problem(path: str) -> str:
    """Why the summary could not be written to ``path`` (checked before the run, so a bad
    path does not cost it), or ''."""
    if not path:
        return 'must not be empty'
    target = Path(path)
    if target.is_dir():
        return 'is a directory'
    if os.path.lexists(target) and not target.is_file():  # a FIFO would block the write
        return 'exists and is not a regular file'
    parent = target.parent
    if not parent.is_dir():
        return f'{str(parent)!r} is not a directory'
    if not os.access(parent, os.W_OK):
        return f'{str(parent)!r} is not writable'
    return ''


def _json_input_clash(path: str, source: str, params_file: str) -> str:
    """Why the summary must not be written to ``path`` because it is one of the run's inputs
    (the write would replace it: a recorded bag or the params file lost), or ''. Refused: a
    path inside the source bag directory (its ``.mcap`` files, ``metadata.yaml``, anything
    new there), or any name (a link, a hard link) of a source ``.mcap`` file or of the params
    file."""
    target = Path(path)
    bag = Path(source)
    try:
        if bag.is_dir():
            inside = target.resolve()
            root = bag.resolve()
            if inside == root or root in inside.parents:
                return f'is inside the source bag {source!r}; write the summary beside it'
        if not target.exists():
            return ''
        inputs: list[tuple[Path, str]] = []
        try:
            inputs += [(f, 'a file of the source bag') for f in mcap_files(source)]
        except BagError:  # the run says what is wrong with the bag
            pass
        if bag.is_file():
            inputs.append((bag, 'the source bag'))
        params = Path(params_file)
        if not params.is_file():
            try:
                params = find_config(params_file)
            except (OSError, ValueError):  # the run says what is wrong with it
                params = Path()
        if params.is_file():
            inputs.append((params, 'the params file'))
        for name, what in inputs:
            if _same_file(target, name):
                return f'is {what} ({str(name)!r}); the summary would replace it'
    except OSError as exc:  # a path that cannot be examined: the write would fail as well
        return f'cannot be examined ({exc.strerror or exc})'
    return ''


def _same_file(a: Path, b: Path) -> bool:
    """Whether ``a`` and ``b`` name one file (False when either cannot be examined)."""
    try:
        return os.path.samefile(a, b)
    except OSError:
        return False


if __name__ == '__main__':
    sys.exit(main())
