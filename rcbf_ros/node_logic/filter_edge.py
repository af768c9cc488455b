"""The safety filter's message edge: CDR bytes in, checked samples; a decision in, bytes out.

The filter node and ``rcbf_ros refilter`` read a proposal or a state by its message type here
(Float64MultiArray sections, a Twist's or TwistStamped's ``twist_fields``, an Odometry's pose),
and the node writes ``cmd_safe``, ``filter_info`` and diagnostics here, as the bytes (or, for
twists, the message) a publisher takes. Samples of the node's own layouts are read and written
at fixed offsets (:class:`rcbf_ros.messages.cdr.Float64ArrayLayout`), any other bytes through
the one Float64MultiArray reader of :mod:`rcbf_ros.messages.cdr` or the decoder; the sections
are checked by :mod:`rcbf_ros.node_logic.safety_filter`. No middleware: the node hands in its
runtime's decoder and message classes, the offline tools use :mod:`rcbf_ros.messages`.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from rcbf_ros.messages import conversions
from rcbf_ros.messages.cdr import deserialize_message, Float64ArrayLayout, serialize_message
from rcbf_ros.messages.classes import get_message as classes_get_message
from rcbf_ros.messages.conversions import FLOAT64_MULTIARRAY, ODOMETRY, TWIST, TWIST_STAMPED
from rcbf_ros.node_logic import safety_filter as logic

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


class Undecodable(ValueError):
    """CDR bytes that are not a sample of their topic's type (the text: ``Type: why``)."""


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
    msg = decoded(data, message_type or type_name, deserialize)
    return {'state': conversions.odometry_to_state(msg, system=system, frame_id=frame_id)}


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


def info_cdr(decision: logic.Decision,
             layouts: dict[tuple[tuple[str, int], ...], Float64ArrayLayout] | None = None
             ) -> bytes:
    """The serialized ``filter_info`` of a decision: the values of an answer with every
    section in the bytes of its layout (kept in ``layouts``, one per set of sizes), any other
    answer through its sections (the same bytes either way)."""
    values = logic.full_info_values(decision)
    if values is None:
        return conversions.sections_to_cdr(logic.info_sections(decision))
    sizes = logic.full_info_layout(decision)
    layout = None if layouts is None else layouts.get(sizes)
    if layout is None:
        layout = Float64ArrayLayout(sizes)
        if layouts is not None:
            layouts[sizes] = layout
    return layout.encode(values)


def diagnostics_cdr(decision: logic.Decision, *, barrier_names: Sequence[str], stamp_ns: int,
                    name: str, hardware_id: str = '',
                    counts: Mapping[str, int] | None = None) -> bytes:
    """The serialized DiagnosticArray of a decision (one status: its level, message and
    key/values, :func:`rcbf_ros.node_logic.safety_filter.diagnostic_values`, then ``counts``),
    stamped ``stamp_ns``."""
    level, message, values = logic.diagnostic_values(decision=decision,
                                                     barrier_names=barrier_names)
    values.update(counts or {})
    return conversions.diagnostics_to_cdr(stamp_ns=stamp_ns, name=name, level=level,
                                          message=message, values=values,
                                          hardware_id=hardware_id)


@dataclass(frozen=True)
class ProposalSample:
    """One ``cmd_proposed`` sample as read: a checked proposal, or why there is none."""

    proposal: logic.Proposal | None
    """The checked proposal, or None."""
    error: str = ''
    """Why there is no proposal ('' when there is one)."""
    header: Any = None
    """The TwistStamped's header (its answer carries it), else None."""
    count: str = ''
    """The input count it adds to: '', :data:`DROPPED` or :data:`REFUSED_PROPOSAL`."""
    undecodable: bool = False
    """The bytes were no sample of the topic's type (answered with the fail-safe)."""


class FilterEdge:
    """The filter node's edge for its message types and sizes (fixed at start).

    Every ``read_*`` method returns what it read or why not, never raises for any bytes; every
    ``*_cdr`` method gives the bytes of the message the same values would serialize to.
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
    def read_state(self, data: bytes, *, received_ns: int, frame_id: str = ''
                   ) -> tuple[logic.StateSample, str]:
        """The state sample of one ``state`` sample and the input count it adds to ('' for a
        good one): an undecodable or unusable one is a bad sample saying why.

        ``frame_id``: the Odometry frame a state must be in ('' takes any).
        """
        try:
            sections = state_sections(
                data, type_name=self.state_type_name, system=self.system, frame_id=frame_id,
                layouts=self.state_layouts, message_type=self._state_message,
                deserialize=self._deserialize)
            state = logic.state_from_sections(sections=sections, n_x=self.n_x)
        except Undecodable as exc:
            return logic.StateSample(received_ns=received_ns, state=None,
                                     error=f'undecodable sample: {exc}'), DROPPED
        except ValueError as exc:
            return logic.StateSample(received_ns=received_ns, state=None,
                                     error=str(exc)), REFUSED_STATE
        return logic.StateSample(received_ns=received_ns, state=state), ''

    def read_proposal(self, data: bytes, *, twist_fields: Sequence[str]) -> ProposalSample:
        """The checked proposal of one ``cmd_proposed`` sample, or why there is none."""
        header = None
        try:
            sections, header = proposal_sections(
                data, type_name=self.command_type_name, twist_fields=twist_fields,
                layouts=self.proposal_layouts, message_type=self._command_message,
                deserialize=self._deserialize)
            proposal = logic.proposal_from_sections(sections=sections, n_u=self.n_u,
                                                    n_x=self.n_x)
        except Undecodable as exc:
            return ProposalSample(None, str(exc), count=DROPPED, undecodable=True)
        except (ValueError, TypeError) as exc:
            return ProposalSample(None, str(exc), header, REFUSED_PROPOSAL)
        return ProposalSample(proposal, header=header)

    def read_obstacles(self, data: bytes) -> dict[str, list[float]]:
        """The ``obstacles.x`` / ``.y`` / ``.radius`` parameters of an ``obstacles`` sample
        (:func:`rcbf_ros.node_logic.safety_filter.obstacle_parameters`).

        Raises:
            ValueError: the sample does not decode, or what that function refuses.
        """
        try:
            msg = decoded(data, self._array_message, self._deserialize)
        except Undecodable as exc:
            raise ValueError(f'undecodable sample: {exc}') from None
        return logic.obstacle_parameters(
            data=msg.data, data_offset=int(msg.layout.data_offset),
            dims=[(d.label, int(d.size), int(d.stride)) for d in msg.layout.dim])

    # bytes out ---------------------------------------------------------------------------------
    def command(self, u_safe: np.ndarray, *, twist_fields: Sequence[str], header: Any = None
                ) -> Any:
        """``cmd_safe`` of a command, in the proposal's type: a Float64MultiArray's bytes (one
        section ``u``), else the Twist or TwistStamped (with ``header``) message."""
        if self.command_type_name == FLOAT64_MULTIARRAY:
            layout = self._command_layout
            return (layout.encode(u_safe) if u_safe.size == layout.size
                    else conversions.sections_to_cdr({'u': u_safe}))
        return conversions.command_to_msg(u_safe, type_name=self.command_type_name,
                                          twist_fields=twist_fields, header=header)

    def info_cdr(self, decision: logic.Decision) -> bytes:
        """The serialized ``filter_info`` of a decision (:func:`info_cdr`; the layouts of the
        answers with every section kept)."""
        return info_cdr(decision, self._info_layouts)

    diagnostics_cdr = staticmethod(diagnostics_cdr)
