"""The safety filter's message edge: CDR bytes in, checked samples; a decision in, bytes out.

One room for what the filter node and ``rcbf_ros refilter`` read and write: a proposal or a
state by its message type (Float64MultiArray sections, a Twist's or TwistStamped's
``twist_fields``, an Odometry's pose), checked into a :class:`Proposal` or :class:`StateSample`;
an ``obstacles`` sample into parameters; and a :class:`Decision` back into the bytes of
``cmd_safe``, ``filter_info`` and diagnostics (:meth:`FilterEdge.answer`, one pass, the command
first). The node's own layouts are read and written at fixed offsets
(:class:`Float64ArrayLayout`: the bytes the one codec, :mod:`rcbf_ros.messages.cdr`, writes
for a layout, made once); any other sample goes through that codec. What to answer is
:func:`rcbf_ros.node_logic.safety_filter.decide`'s job.
No middleware: the node hands in its runtime's decoder, message classes and clock.
"""
from __future__ import annotations

from dataclasses import dataclass
import math
import struct
from typing import Any, Callable, Mapping, NamedTuple, Sequence

import numpy as np

from rcbf_ros.core import filter_info
from rcbf_ros.core.config import OBSTACLE_LIMIT
from rcbf_ros.core.filter import FilterResult
from rcbf_ros.messages import conversions
from rcbf_ros.messages.cdr import (
    CDR_LE_HEADER,
    deserialize_message,
    float64_multiarray_head,
    serialize_message,
)
from rcbf_ros.messages.classes import get_message as classes_get_message
from rcbf_ros.messages.conversions import FLOAT64_MULTIARRAY, ODOMETRY, TWIST, TWIST_STAMPED

# diagnostic_msgs/DiagnosticStatus levels.
OK = 0
WARN = 1
ERROR = 2

DROPPED = 'dropped_samples'
"""Count key of a sample that does not decode as its topic's type (either topic)."""
REFUSED_PROPOSAL = 'refused_proposals'
"""Count key of a proposal that decodes but cannot be used (layout, length, NaN, ...)."""
REFUSED_STATE = 'refused_states'
"""Count key of a state that decodes but cannot be used."""
INPUT_COUNT_KEYS = (DROPPED, REFUSED_PROPOSAL, REFUSED_STATE)
"""The node's cumulative input counts, as its diagnostics name them."""

Deserialize = Callable[[bytes, Any], Any]
"""(CDR bytes, message class or type name) -> message: a runtime's ``deserialize_message``."""


class Float64ArrayLayout:
    """The serialized ``std_msgs/Float64MultiArray`` samples of one layout: labelled sections
    of fixed sizes (stride = size, data_offset 0) holding ``size`` values in all.

    Everything before the values is then fixed: the codec's own bytes for the layout
    (:func:`rcbf_ros.messages.cdr.float64_multiarray_head`, written once here), so
    :meth:`encode` is those bytes and the values, and :meth:`decode` recognises a sample of
    the layout by comparing them and reads its values at a fixed offset: what the decoder would
    read from it. Every other sample (another layout, big endian, padding that is not zero,
    one that ends early) is left to the general readers (:meth:`decode` returns None).
    """

    def __init__(self, sections: Sequence[tuple[str, int]]) -> None:
        """Args: sections: (label, size) of each section, in order ('' labels one unlabelled
        section: an empty ``layout.dim``, as a bare Float64MultiArray has)."""
        sections = tuple((str(label), int(size)) for label, size in sections)
        if len(sections) == 1 and sections[0][0] == '':
            dims: tuple[tuple[str, int, int], ...] = ()
        else:
            dims = tuple((label, size, size) for label, size in sections)
        self.sections = sections
        self.size = sum(size for _, size in sections)
        """How many values a sample holds."""
        self.head = float64_multiarray_head(dims, 0, self.size)
        """The bytes before the values (encapsulation header and all)."""
        self._body = self.head[4:]
        self._length = len(self.head) + 8 * self.size
        self._values = struct.Struct(f'<{self.size}d')

    def decode(self, data: bytes) -> tuple[float, ...] | None:
        """The values of a little-endian sample of this layout (any encapsulation options,
        bytes after the values ignored, as the decoder ignores them), else None."""
        if (type(data) is not bytes or len(data) < self._length
                or not data.startswith(CDR_LE_HEADER[:2]) or not data.startswith(self._body, 4)):
            return None
        return self._values.unpack_from(data, len(self.head))

    def encode(self, values: Any) -> bytes:
        """The serialized message of ``values`` (``size`` numbers, section after section).

        Raises:
            ValueError: not ``size`` values.
        """
        array = np.asarray(values, dtype='<f8').reshape(-1)
        if array.size != self.size:
            raise ValueError(f'expected {self.size} values, got {array.size}')
        return self.head + array.tobytes()


# bytes in ----------------------------------------------------------------------------------------
def checked_vector(name: str, values: Any, size: int) -> np.ndarray:
    """A finite float64 vector (a writable copy) of exactly ``size`` values.

    Raises:
        ValueError: naming ``name`` (wrong length, NaN/inf, not numeric).
    """
    try:
        array = np.array(values, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError) as exc:
        raise ValueError(f'{name}: not a numeric vector ({exc})') from exc
    if array.size != size:
        raise ValueError(f'{name}: expected {size} values, got {array.size}')
    # A state or command has a few values: checked as Python floats, a longer one by numpy.
    if not (all(map(math.isfinite, array.tolist())) if size <= _FEW_VALUES
            else np.isfinite(array).all()):
        raise ValueError(f'{name}: contains NaN or inf')
    return array


_FEW_VALUES = 32
"""Up to this many values, :func:`checked_vector` checks them one by one as Python floats."""


def state_from_sections(*, sections: Mapping[str, np.ndarray], n_x: int) -> np.ndarray:
    """The ``state`` section of a state message, else its first section, validated.

    Raises:
        ValueError: naming ``state`` (empty message, wrong length, NaN/inf).
    """
    if not sections:
        raise ValueError('state: empty message')
    values = sections['state'] if 'state' in sections else next(iter(sections.values()))
    return checked_vector('state', values, n_x)


@dataclass(frozen=True)
class Proposal:
    """A validated proposed command and what rides on it (float64 arrays)."""

    u: np.ndarray
    """(n_u,) proposed command u_RL."""
    disturbance_mean: np.ndarray | None = None
    """(n_x,) learned disturbance mean for the proposal's state, or None."""
    disturbance_std: np.ndarray | None = None
    """(n_x,) learned disturbance std (>= 0), or None."""
    state: np.ndarray | None = None
    """(n_x,) the state the proposal was made for, or None (use the state topic)."""


PROPOSAL_SECTIONS = ('u', 'disturbance_mean', 'disturbance_std', 'state')
_PROPOSAL_SECTION_SET = frozenset(PROPOSAL_SECTIONS)


def proposal_from_sections(*, sections: Mapping[str, np.ndarray], n_u: int,
                           n_x: int) -> Proposal:
    """Validate the sections of a proposal message (``u`` required; unlabelled data is ``u``).

    Raises:
        ValueError: naming the section (missing ``u``, unknown label, wrong length, NaN/inf,
            negative std).
    """
    if not _PROPOSAL_SECTION_SET.issuperset(sections):
        unknown = sorted(set(sections) - _PROPOSAL_SECTION_SET)
        raise ValueError(f'{unknown[0]}: unknown proposal section (expected '
                         f'{list(PROPOSAL_SECTIONS)})')
    if 'u' not in sections:
        raise ValueError('u: proposal has no u section')
    u = checked_vector('u', sections['u'], n_u)
    if len(sections) == 1:
        return Proposal(u=u)
    extra = {key: checked_vector(key, sections[key], n_x)
             for key in PROPOSAL_SECTIONS[1:] if key in sections}
    std = extra.get('disturbance_std')
    if std is not None and (std < 0).any():
        raise ValueError('disturbance_std: must be >= 0')
    return Proposal(u=u, disturbance_mean=extra.get('disturbance_mean'),
                    disturbance_std=std, state=extra.get('state'))


@dataclass(frozen=True)
class StateSample:
    """The latest state message as the node saw it."""

    received_ns: int
    """Monotonic arrival time in nanoseconds."""
    state: np.ndarray | None
    """(n_x,) validated state, or None when the message was bad."""
    error: str = ''
    """Why the message was rejected (empty when ``state`` is set)."""
    stamp_ns: int | None = None
    """An Odometry's header stamp (ns, on the publisher's ROS clock); None for an array."""


OBSTACLE_COLUMNS = ('x', 'y', 'radius')
"""One row of an ``obstacles`` message: centre x, centre y (m), radius (m)."""


def obstacle_parameters(*, data: Sequence[float], dims: Sequence[tuple[str, int, int]] = (),
                        data_offset: int = 0) -> dict[str, list[float]]:
    """The ``obstacles.x`` / ``.y`` / ``.radius`` parameters of an ``obstacles`` message.

    The message is a std_msgs/Float64MultiArray of k rows [x, y, radius] in row-major order
    (:data:`OBSTACLE_COLUMNS`): ``data`` holds 3 k values. Its layout may be empty, or two
    dimensions, the second of size 3 (e.g. ``obstacles`` k 3k, ``xyr`` 3 3). The values
    themselves (finite, radius >= 0, ...) are checked by the same function as a params file's
    ``obstacles`` section, when the filter is built from them.

    Args:
        dims: (label, size, stride) of every ``layout.dim``.
        data_offset: ``layout.data_offset`` (must be 0).

    Raises:
        ValueError: naming the message field (``data``, ``layout.dim``, ``layout.data_offset``).
    """
    if data_offset != 0:
        raise ValueError(f'obstacles: layout.data_offset: expected 0, got {data_offset}')
    values = data
    if len(values) % len(OBSTACLE_COLUMNS):
        raise ValueError(f'obstacles: data: expected rows of [x, y, radius] (a multiple of 3 '
                         f'values), got {len(values)} values')
    rows = len(values) // len(OBSTACLE_COLUMNS)
    if rows > OBSTACLE_LIMIT:
        raise ValueError(f'obstacles: data: at most {OBSTACLE_LIMIT} rows of [x, y, radius], '
                         f'got {rows}')
    if dims and (len(dims) != 2 or dims[1][1] != len(OBSTACLE_COLUMNS)
                 or dims[0][1] != rows):
        sizes = [size for _, size, _ in dims]
        raise ValueError(f'obstacles: layout.dim: expected sizes [{rows}, 3] (rows of '
                         f'[x, y, radius]) or none, got {sizes}')
    try:
        floats = [float(v) for v in values]
    except (TypeError, ValueError, OverflowError) as exc:
        raise ValueError(f'obstacles: data: not numbers ({exc})') from exc
    return {f'obstacles.{column}': floats[index::len(OBSTACLE_COLUMNS)]
            for index, column in enumerate(OBSTACLE_COLUMNS)}


class Undecodable(ValueError):
    """CDR bytes that are not a sample of their topic's type (the text: ``Type: why``)."""


REASON_LIMIT = 400
"""Most characters of a decision's reason (:func:`shown_reason`): what a log line and the
diagnostics' message and ``reason`` value say of it."""


def shown_reason(text: str, limit: int = REASON_LIMIT) -> str:
    """``text`` on one line (runs of white space as one space), cut to ``limit`` characters
    with the number cut off said, so that a 1 MB frame id in a refusal stays a short line."""
    line = ' '.join(str(text).split())
    if len(line) <= limit:
        return line
    tail = f'... ({len(line) - limit} characters more)'
    return line[:max(0, limit - len(tail))] + tail


def one_line(exc: BaseException) -> str:
    """``Type: text`` of an exception on one line, at most 200 characters."""
    text = ' '.join(f'{type(exc).__name__}: {exc}'.split())
    return text if len(text) <= 200 else text[:197] + '...'


def decoded(data: bytes, message_type: Any, deserialize: Deserialize = deserialize_message
            ) -> Any:
    """The message of an untrusted sample.

    Any exception of the decoder means "not a sample of this type": the decoder is rclpy's or
    ours and neither promises a closed set of exceptions.

    Raises:
        Undecodable: the decoder's error, on one line.
    """
    try:
        return deserialize(data, message_type)
    except Exception as exc:
        raise Undecodable(one_line(exc)) from None


def array_sections(data: bytes, layouts: Sequence[Float64ArrayLayout],
                   default_label: str) -> dict[str, Any] | None:
    """The sections of a Float64MultiArray sample (CDR bytes), as
    :func:`rcbf_ros.messages.conversions.sections_from_cdr` reads them: at once for a sample of
    one of ``layouts`` (one section: its label, or ``default_label`` when unlabelled; the
    values as a tuple of floats), else through that function (None: leave it to the decoder).

    Raises:
        ValueError: as sections_from_cdr, for a layout that does not fit.
    """
    for layout in layouts:
        values = layout.decode(data)
        if values is not None:
            return {layout.sections[0][0] or default_label: values}
    return conversions.sections_from_cdr(data, default_label=default_label)


def float64_sections(data: bytes, *, default_label: str,
                     layouts: Sequence[Float64ArrayLayout] = (), message_type: Any = None,
                     deserialize: Deserialize = deserialize_message) -> dict[str, Any]:
    """The sections of a Float64MultiArray sample (unlabelled data as ``default_label``): at
    once where :func:`array_sections` reads it, else through the decoder.

    Raises:
        Undecodable: the bytes are not a Float64MultiArray sample.
        ValueError: a layout that does not fit (naming the dimension).
    """
    sections = array_sections(data, layouts, default_label)
    if sections is not None:
        return sections
    msg = decoded(data, message_type or FLOAT64_MULTIARRAY, deserialize)
    return conversions.msg_to_sections(msg, default_label=default_label)


def proposal_sections(data: bytes, *, type_name: str, twist_fields: Sequence[str],
                      layouts: Sequence[Float64ArrayLayout] = (), message_type: Any = None,
                      deserialize: Deserialize = deserialize_message
                      ) -> tuple[dict[str, Any], Any]:
    """The sections of a proposal sample of ``type_name`` (a Float64MultiArray's, unlabelled
    data as ``u``; ``u`` of a Twist or TwistStamped in ``twist_fields``), and the
    TwistStamped's header (else None).

    Args:
        layouts: Float64MultiArray layouts read at fixed offsets (see :func:`array_sections`).
        message_type: what ``deserialize`` takes for the type (default: ``type_name``).

    Raises:
        Undecodable: the bytes are not a sample of the type.
        ValueError: a layout that does not fit, or a type that holds no proposal.
    """
    if type_name == FLOAT64_MULTIARRAY:
        return float64_sections(data, default_label='u', layouts=layouts,
                                message_type=message_type, deserialize=deserialize), None
    if type_name not in (TWIST, TWIST_STAMPED):
        raise ValueError(f'type {type_name!r} holds no proposal (expected one of '
                         f'{sorted(conversions.COMMAND_MESSAGES.values())})')
    msg = decoded(data, message_type or type_name, deserialize)
    if type_name == TWIST:
        return {'u': conversions.twist_to_array(msg, twist_fields)}, None
    return {'u': conversions.twist_stamped_to_array(msg, twist_fields)}, msg.header


def state_sections(data: bytes, *, type_name: str, system: str, frame_id: str = '',
                   layouts: Sequence[Float64ArrayLayout] = (), message_type: Any = None,
                   deserialize: Deserialize = deserialize_message) -> dict[str, Any]:
    """The sections of a state sample of ``type_name``: a Float64MultiArray's (unlabelled data
    as ``state``), or ``state`` of ``system`` read from an Odometry in frame ``frame_id`` (''
    takes any).

    Raises:
        Undecodable: the bytes are not a sample of the type.
        ValueError: a layout that does not fit, an Odometry the state cannot be read from
            (naming the field, or ``state_type`` for a system it does not hold), or a type
            that holds no state.
    """
    if type_name == FLOAT64_MULTIARRAY:
        return float64_sections(data, default_label='state', layouts=layouts,
                                message_type=message_type, deserialize=deserialize)
    if type_name != ODOMETRY:
        raise ValueError(f'type {type_name!r} holds no state (expected one of '
                         f'{sorted(conversions.STATE_MESSAGES.values())})')
    return stamped_state_sections(
        data, type_name=type_name, system=system, frame_id=frame_id, message_type=message_type,
        deserialize=deserialize)[0]


def stamped_state_sections(data: bytes, *, type_name: str, system: str, frame_id: str = '',
                           child_frame_id: str = '',
                           layouts: Sequence[Float64ArrayLayout] = (), message_type: Any = None,
                           deserialize: Deserialize = deserialize_message
                           ) -> tuple[dict[str, Any], int | None]:
    """:func:`state_sections` and an Odometry's header stamp in nanoseconds (None for an
    array, which has no stamp); an Odometry's child frame must be ``child_frame_id`` where
    both are given (:func:`~rcbf_ros.messages.conversions.odometry_to_state`)."""
    if type_name != ODOMETRY:
        return state_sections(data, type_name=type_name, system=system, layouts=layouts,
                              message_type=message_type, deserialize=deserialize), None
    msg = decoded(data, message_type or type_name, deserialize)
    state = conversions.odometry_to_state(msg, system=system, frame_id=frame_id,
                                          child_frame_id=child_frame_id)
    stamp = msg.header.stamp
    return {'state': state}, int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


# bytes out ---------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Decision:
    """What the node publishes for one proposal."""

    u_safe: np.ndarray
    """(n_u,) the command to publish: the filtered proposal or the fail-safe action."""
    u_rl: np.ndarray | None
    """(n_u,) the proposal as received, or None when it was unusable (undecodable, wrong
    length, NaN or inf)."""
    level: int
    """OK, WARN or ERROR."""
    reason: str
    """Human-readable reason for the level ('' when OK), on one line of at most
    :data:`REASON_LIMIT` characters (cut when longer)."""
    fail_safe: bool
    """True when u_safe is the fail-safe action."""
    result: FilterResult | None = None
    """The filter's result when the QP was solved (even if it failed), else None."""
    state_source: str = ''
    """'proposal', 'topic' or '' (no usable state)."""
    state: np.ndarray | None = None
    """(n_x,) the state the command answers (the proposal's own, or the latest ``state``
    sample), or None when there was no usable one."""

    def __post_init__(self) -> None:
        # The one place every reason passes: each log line and diagnostics message of it
        # is bounded here (:func:`shown_reason`).
        object.__setattr__(self, 'reason', shown_reason(self.reason))

    @property
    def u_s(self) -> np.ndarray:
        """(n_u,) the correction u_safe - u_rl; zeros when there was no usable proposal."""
        if self.u_rl is None:
            return np.zeros_like(self.u_safe)
        return self.u_safe - self.u_rl

    @property
    def active(self) -> bool:
        """Whether the published command differs from the proposal (the fail-safe counts)."""
        return bool(self.fail_safe or np.any(self.u_safe != self.u_rl))


def status_code(decision: Decision) -> int:
    """The ``status`` number of a decision (:data:`rcbf_ros.core.filter_info.STATUS_CODES`)."""
    return int(info_sections(decision)['status'][0])


def status_name(decision: Decision) -> str:
    """The solver status of a filtered command, else the key of the fail-safe's reason (an
    observation source's, ``source <name>``, as the one status of every source)."""
    if not decision.fail_safe and decision.result is not None:
        return decision.result.status
    key = reason_key(decision.reason)
    return filter_info.SOURCE_UNUSABLE if key.startswith('source ') else key


def info_sections(decision: Decision) -> dict[str, np.ndarray]:
    """The labelled sections of ``filter_info`` for one decision
    (:data:`rcbf_ros.core.filter_info.INFO_SECTIONS`): never NaN, a value that was not
    evaluated is left out with its section."""
    return filter_info.info_sections(
        u=decision.u_safe, u_rl=decision.u_rl, fail_safe=decision.fail_safe,
        status=status_name(decision), result=decision.result, state=decision.state)


def full_info_values(decision: Decision) -> np.ndarray | None:
    """The values of :func:`info_sections` of ``decision``, section after section, when it
    has every section (:data:`rcbf_ros.core.filter_info.INFO_SECTIONS`: a solved answer with its
    state, a usable proposal and every number finite), else None.

    The answers of a running filter are nearly all of this kind, and their ``filter_info`` is
    then one fixed layout (sizes n_u, 1, K, n_x, 4 m) whose values these are, made in one step;
    any other answer is left to :func:`info_sections`, which decides what to leave out.
    """
    result, u_rl, state = decision.result, decision.u_rl, decision.state
    if result is None or u_rl is None or state is None:
        return None
    u = decision.u_safe
    if u_rl.shape != u.shape or not len(result.h) or not len(result.constraint_values):
        return None
    code = filter_info.STATUS_CODES.get(status_name(decision), filter_info.UNKNOWN_STATUS)
    values = np.concatenate((
        u, u_rl, u - u_rl, (1.0 if decision.fail_safe else 0.0, float(code)), result.h,
        result.constraint_values, (result.slack, result.needed_slack, result.solve_time_s),
        state, filter_info.binding_points(getattr(result, 'points', None)).reshape(-1)),
        dtype=np.float64)
    return values if np.isfinite(values).all() else None


def full_info_layout(decision: Decision, values: np.ndarray) -> tuple[tuple[str, int], ...]:
    """The (label, size) of every ``filter_info`` section of a decision that has them all,
    given its :func:`full_info_values` (``binding_points`` only when it holds a point)."""
    n_u, n_barriers = decision.u_safe.size, len(decision.result.h)
    sizes = {'u': n_u, 'u_rl': n_u, 'u_s': n_u, 'h': n_barriers,
             'constraint': len(decision.result.constraint_values), 'state': decision.state.size}
    sizes['binding_points'] = values.size - (3 * n_u + 5 + n_barriers + sizes['constraint']
                                             + sizes['state'])
    return tuple((label, sizes.get(label, 1)) for label, _, _ in filter_info.INFO_SECTIONS
                 if sizes.get(label, 1))


def reason_key(reason: str) -> str:
    """The throttling key of a reason: its text up to the first ':'."""
    return reason.split(':', 1)[0]


DIAGNOSTIC_BARRIERS = 32
"""At most this many barriers have ``h.<barrier>`` and ``constraint.<barrier>`` keys in a
diagnostic (those of least h): a status of 20,000 obstacles took 170 ms to encode, and the
node answers in between. ``filter_info`` carries every barrier."""


def shown_barriers(h: np.ndarray, limit: int = DIAGNOSTIC_BARRIERS) -> np.ndarray:
    """Indices, ascending, of the barriers a diagnostic names: all of them up to ``limit``,
    else the ``limit`` of least h (a NaN counts as the largest)."""
    h = np.asarray(h, dtype=float)
    if len(h) <= limit:
        return np.arange(len(h))
    key = np.where(np.isnan(h), np.inf, h)
    return np.sort(np.argpartition(key, limit - 1)[:limit])


def diagnostic_values(*, decision: Decision,
                      barrier_names: Sequence[str]) -> tuple[int, str, dict[str, Any]]:
    """(level, message, key/values) of the DiagnosticStatus for one decision.

    Keys: ``status`` (solver status or 'not solved'), ``slack``, ``h.<barrier>`` and
    ``constraint.<barrier>`` for every barrier up to :data:`DIAGNOSTIC_BARRIERS` (beyond it, for
    those of least h, and ``barriers_shown`` says so), ``min_h``, ``solve_time_s``,
    ``total_time_s``, ``needed_slack`` (what the rows need at the published command),
    ``proposal_clipped``, ``fail_safe``, ``active``, ``reason``, ``state_source``, ``u_rl``,
    ``u_safe``. A value that was not evaluated (no QP solved, a refused input, no usable
    proposal) is ``''``, never NaN.
    """
    result = decision.result
    nan = float('nan')
    values: dict[str, Any] = {
        'status': result.status if result is not None else 'not solved',
        'slack': result.slack if result is not None else nan,
    }
    h = result.h if result is not None else np.full(len(barrier_names), np.nan)
    residual = (result.constraint_values if result is not None
                else np.full(len(barrier_names), np.nan))
    shown = shown_barriers(h)
    for index in shown:
        values[f'h.{barrier_names[index]}'] = float(h[index])
    for index in shown:
        values[f'constraint.{barrier_names[index]}'] = float(residual[index])
    if len(shown) < len(h):
        values['barriers_shown'] = (f'{len(shown)} of {len(h)}: the least h (filter_info '
                                    'holds every one)')
    values['min_h'] = float(np.min(h)) if len(h) else nan
    values['solve_time_s'] = result.solve_time_s if result is not None else nan
    values['total_time_s'] = result.total_time_s if result is not None else nan
    values['needed_slack'] = result.needed_slack if result is not None else nan
    values['proposal_clipped'] = bool(result is not None and result.proposal_clipped)
    values['fail_safe'] = decision.fail_safe
    values['active'] = decision.active
    values['reason'] = decision.reason
    values['state_source'] = decision.state_source
    values['u_rl'] = ('' if decision.u_rl is None
                      else ' '.join(repr(float(v)) for v in decision.u_rl))
    values['u_safe'] = ' '.join(repr(float(v)) for v in decision.u_safe)
    for key, value in values.items():
        if isinstance(value, float) and not math.isfinite(value):
            values[key] = ''
    if decision.level == OK:
        message = 'filtering' if values['active'] else 'pass-through'
    else:
        message = decision.reason
    return decision.level, message, values


def diagnostics_due(*, level: int, now_ns: int, last_ok_ns: int | None,
                    min_period_s: float) -> bool:
    """Whether to publish the diagnostics of a decision now.

    WARN and ERROR always; OK at most once per ``min_period_s`` (0: always), so that a 1 kHz
    loop need not pay for a DiagnosticArray per command.

    Args:
        last_ok_ns: when OK diagnostics were last published (None: never).
    """
    if level != OK or min_period_s <= 0 or last_ok_ns is None:
        return True
    return now_ns - last_ok_ns >= int(min_period_s * 1e9)


def command_cdr(u_safe: np.ndarray, *, type_name: str, twist_fields: Sequence[str],
                header: Any = None) -> bytes:
    """The serialized ``cmd_safe`` of a command in ``type_name``: a Float64MultiArray with one
    section ``u``, or a Twist or TwistStamped (with ``header``'s stamp and frame_id) with u in
    ``twist_fields`` (others 0).

    Raises:
        ValueError: ``type_name`` is not a command type.
    """
    if type_name == FLOAT64_MULTIARRAY:
        return conversions.sections_to_cdr({'u': u_safe})
    return serialize_message(conversions.command_to_msg(
        u_safe, type_name=type_name, twist_fields=twist_fields, header=header,
        message_class=classes_get_message))


def info_cdr(decision: Decision,
             layouts: dict[tuple[tuple[str, int], ...], Float64ArrayLayout] | None = None
             ) -> bytes:
    """The serialized ``filter_info`` of a decision: the values of an answer with every
    section in the bytes of its layout (kept in ``layouts``, one per set of sizes), any other
    answer through its sections (the same bytes either way)."""
    values = full_info_values(decision)
    if values is None:
        return conversions.sections_to_cdr(info_sections(decision))
    sizes = full_info_layout(decision, values)
    layout = None if layouts is None else layouts.get(sizes)
    if layout is None:
        layout = Float64ArrayLayout(sizes)
        if layouts is not None:
            layouts[sizes] = layout
    return layout.encode(values)


def diagnostics_cdr(decision: Decision, *, barrier_names: Sequence[str], stamp_ns: int,
                    name: str, hardware_id: str = '',
                    counts: Mapping[str, int] | None = None) -> bytes:
    """The serialized DiagnosticArray of a decision (one status: its level, message and
    key/values, :func:`diagnostic_values`, then ``counts``),
    stamped ``stamp_ns``."""
    level, message, values = diagnostic_values(decision=decision, barrier_names=barrier_names)
    values.update(counts or {})
    return conversions.diagnostics_to_cdr(stamp_ns=stamp_ns, name=name, level=level,
                                          message=message, values=values,
                                          hardware_id=hardware_id)


class ProposalSample(NamedTuple):
    """One ``cmd_proposed`` sample as read: a checked proposal, or why there is none (a tuple:
    one per proposal, made in a fraction of a frozen dataclass's time)."""

    proposal: Proposal | None
    """The checked proposal, or None."""
    error: str = ''
    """Why there is no proposal ('' when there is one)."""
    header: Any = None
    """The TwistStamped's header (its answer carries it), else None."""
    count: str = ''
    """The input count it adds to: '', :data:`DROPPED` or :data:`REFUSED_PROPOSAL`."""
    undecodable: bool = False
    """The bytes were no sample of the topic's type (answered with the fail-safe)."""


class Answer(NamedTuple):
    """The messages of one answer, in publishing order (:meth:`FilterEdge.answer`; a tuple,
    as :class:`ProposalSample`)."""

    command: Any
    """``cmd_safe``: bytes (Float64MultiArray), else the Twist or TwistStamped message."""
    info: bytes | None
    """``filter_info``'s bytes, or None when making them failed (see ``error``)."""
    diagnostics: bytes | None
    """The DiagnosticArray's bytes when due and made, else None."""
    diagnostics_due: bool
    """Whether diagnostics were due (:func:`diagnostics_due`)."""
    error: str = ''
    """Why a detail is missing (``Type: text``; '' when none is)."""


class FilterEdge:
    """The filter node's edge for its message types and sizes (fixed at start).

    Every ``read_*`` method returns what it read or why not, never raises for any bytes; every
    ``*_cdr`` method gives the bytes of the message the same values would serialize to;
    :meth:`answer` makes all of one answer's messages.
    """

    def __init__(self, *, state_type: str, command_type: str, system: str, n_x: int, n_u: int,
                 deserialize: Deserialize = deserialize_message,
                 get_message: Callable[[str], Any] = classes_get_message) -> None:
        """Args:
            state_type, command_type: the node's ``state_type`` and ``command_type``
                (:data:`rcbf_ros.messages.conversions.STATE_MESSAGES`, ``COMMAND_MESSAGES``).
            system: the filter's system (an Odometry state is read for it).
            n_x, n_u: its state and command sizes.
            deserialize, get_message: the runtime's decoder and message classes.
        """
        self.state_type_name = conversions.STATE_MESSAGES[state_type]
        self.command_type_name = conversions.COMMAND_MESSAGES[command_type]
        self.system, self.n_x, self.n_u = system, n_x, n_u
        self._deserialize = deserialize
        self._state_message = get_message(self.state_type_name)
        self._command_message = get_message(self.command_type_name)
        self._array_message = get_message(FLOAT64_MULTIARRAY)
        self._header_message = get_message('std_msgs/msg/Header')
        arrays = (state_type == 'array', command_type == 'array')
        self.state_layouts: tuple[Float64ArrayLayout, ...] = (
            Float64ArrayLayout([('state', n_x)]), Float64ArrayLayout([('', n_x)])
        ) if arrays[0] else ()
        """State layouts read at fixed offsets ('' is an unlabelled section)."""
        self.proposal_layouts: tuple[Float64ArrayLayout, ...] = (
            Float64ArrayLayout([('u', n_u)]), Float64ArrayLayout([('', n_u)])
        ) if arrays[1] else ()
        """Proposal layouts read at fixed offsets."""
        self._command_layout = Float64ArrayLayout([('u', n_u)])
        self._info_layouts: dict[tuple[tuple[str, int], ...], Float64ArrayLayout] = {}

    # bytes in ----------------------------------------------------------------------------------
    def read_state(self, data: bytes, *, received_ns: int, frame_id: str = '',
                   child_frame_id: str = '') -> tuple[StateSample, str]:
        """The state sample of one ``state`` sample and the input count it adds to ('' for a
        good one): an undecodable or unusable one is a bad sample saying why.

        ``frame_id``: the Odometry frame a state must be in ('' takes any);
        ``child_frame_id``: the robot's frame, its child frame ('' takes any).
        """
        try:
            sections, stamp_ns = stamped_state_sections(
                data, type_name=self.state_type_name, system=self.system, frame_id=frame_id,
                child_frame_id=child_frame_id,
                layouts=self.state_layouts, message_type=self._state_message,
                deserialize=self._deserialize)
            state = state_from_sections(sections=sections, n_x=self.n_x)
        except Undecodable as exc:
            return StateSample(received_ns=received_ns, state=None,
                               error=f'undecodable sample: {exc}'), DROPPED
        except ValueError as exc:
            return StateSample(received_ns=received_ns, state=None,
                               error=str(exc)), REFUSED_STATE
        return StateSample(received_ns=received_ns, state=state, stamp_ns=stamp_ns), ''

    def read_proposal(self, data: bytes, *, twist_fields: Sequence[str]) -> ProposalSample:
        """The checked proposal of one ``cmd_proposed`` sample, or why there is none."""
        for layout in self.proposal_layouts:  # the node's own layouts: ``u`` alone, at once
            values = layout.decode(data)
            if values is not None:
                try:
                    return ProposalSample(Proposal(u=checked_vector('u', values, self.n_u)))
                except ValueError as exc:
                    return ProposalSample(None, str(exc), None, REFUSED_PROPOSAL)
        header = None
        try:
            sections, header = proposal_sections(
                data, type_name=self.command_type_name, twist_fields=twist_fields,
                layouts=self.proposal_layouts, message_type=self._command_message,
                deserialize=self._deserialize)
            proposal = proposal_from_sections(sections=sections, n_u=self.n_u, n_x=self.n_x)
        except Undecodable as exc:
            return ProposalSample(None, str(exc), count=DROPPED, undecodable=True)
        except (ValueError, TypeError) as exc:
            return ProposalSample(None, str(exc), header, REFUSED_PROPOSAL)
        return ProposalSample(proposal, header=header)

    def read_obstacles(self, data: bytes) -> dict[str, list[float]]:
        """The ``obstacles.x`` / ``.y`` / ``.radius`` parameters of an ``obstacles`` sample
        (:func:`obstacle_parameters`).

        Raises:
            ValueError: the sample does not decode, or what that function refuses.
        """
        try:
            msg = decoded(data, self._array_message, self._deserialize)
        except Undecodable as exc:
            raise ValueError(f'undecodable sample: {exc}') from None
        return obstacle_parameters(
            data=msg.data, data_offset=int(msg.layout.data_offset),
            dims=[(d.label, int(d.size), int(d.stride)) for d in msg.layout.dim])

    # bytes out ---------------------------------------------------------------------------------
    def command(self, u_safe: np.ndarray, *, twist_fields: Sequence[str], header: Any = None,
                clock: Any = None) -> Any:
        """``cmd_safe`` of a command, in the proposal's type: a Float64MultiArray's bytes (one
        section ``u``), else the Twist or TwistStamped message (with ``header``; without one,
        a header stamped ``clock.now()``, as for an undecodable proposal)."""
        if self.command_type_name == FLOAT64_MULTIARRAY:
            layout = self._command_layout
            return (layout.encode(u_safe) if u_safe.size == layout.size
                    else conversions.sections_to_cdr({'u': u_safe}))
        if self.command_type_name == TWIST_STAMPED and header is None:
            header = self._header_message()
            header.stamp = clock.now().to_msg()
        return conversions.command_to_msg(u_safe, type_name=self.command_type_name,
                                          twist_fields=twist_fields, header=header)

    def restamped(self, header: Any, *, clock: Any) -> Any:
        """A copy of a proposal's ``header`` (None: None) stamped ``clock.now()``: the header
        of a re-filtered answer, which keeps the proposal's frame_id and is as new as the
        answer (as Nav2's collision_monitor stamps what it publishes)."""
        if header is None:
            return None
        fresh = self._header_message()
        fresh.frame_id = header.frame_id
        fresh.stamp = clock.now().to_msg()
        return fresh

    def info_cdr(self, decision: Decision) -> bytes:
        """The serialized ``filter_info`` of a decision (:func:`info_cdr`; the layouts of the
        answers with every section kept)."""
        return info_cdr(decision, self._info_layouts)

    diagnostics_cdr = staticmethod(diagnostics_cdr)

    def answer(self, decision: Decision, *, settings: Any, barrier_names: Sequence[str],
               header: Any, now_ns: int, last_ok_ns: int | None, clock: Any,
               counts: Mapping[str, int]) -> Answer:
        """Everything the node publishes for a decision, in one pass: ``cmd_safe``, then
        ``filter_info``, then the diagnostics when they are due (:func:`diagnostics_due`,
        stamped ``clock.now()``).

        The command is made first and alone may raise: an answer whose command cannot be made
        has nothing to publish (the node sends the fail-safe instead). A failure making the
        details after it is caught: the answer keeps the command (and ``filter_info`` if it
        was made) and says why in :attr:`Answer.error`.

        Args:
            settings: the node's settings (``twist_fields``, ``diagnostics.*``:
                :class:`rcbf_ros.node_logic.safety_filter.NodeSettings`).
            header: the proposal's (TwistStamped), else None.
            now_ns: the proposal's arrival (monotonic ns); ``last_ok_ns``: when OK diagnostics
                last went out (None: never).
            clock: the node's clock (``now()``), for stamps.
            counts: the node's input counts (:data:`INPUT_COUNT_KEYS`), into the diagnostics.
        """
        command = self.command(decision.u_safe, twist_fields=settings.twist_fields,
                               header=header, clock=clock)
        due = diagnostics_due(level=decision.level, now_ns=now_ns, last_ok_ns=last_ok_ns,
                              min_period_s=settings.diagnostics_min_period_s)
        info = None
        try:
            info = info_cdr(decision, self._info_layouts)
            diagnostics = diagnostics_cdr(
                decision, barrier_names=barrier_names, stamp_ns=clock.now().nanoseconds,
                name=settings.diagnostics_name, hardware_id=settings.diagnostics_hardware_id,
                counts=counts) if due else None
        except Exception as exc:  # a defect in the details: the command goes out regardless
            return Answer(command, info, None, due, one_line(exc))
        return Answer(command, info, diagnostics, due)
