"""Transforms from tf: tf2_msgs/TFMessage CDR bytes -> checked, stamped rigid transforms.

The filter takes sensor points to the state's frame through the transforms of ``/tf`` and
``/tf_static`` (:mod:`rcbf_ros.node_logic.tf_buffer` keeps them); this module reads them
straight from the CDR bytes a subscription receives, with the cursor of
:mod:`rcbf_ros.messages.sensor` (its 4-byte encapsulation header, either byte order), without
building a message. The layout is Jazzy's (:func:`rcbf_ros.messages.typestore.jazzy_typestore`;
the tests encode with rosbags).

Every size is bounded before it is used (:data:`MAX_TRANSFORMS` per message, frame ids of at
most :data:`MAX_FRAME_ID` characters). A message that does not fit its layout is
:class:`~rcbf_ros.messages.sensor.Refused` whole, in one line; a transform that tf2's
``BufferCore::setTransform`` would ignore (the same frame as parent and child, an empty frame
id, a NaN, and here also an infinite value or a translation beyond :data:`MAX_TRANSLATION`, a
quaternion whose squared length is off 1 by :data:`QUATERNION_TOLERANCE` or more) is refused
alone, one line naming its frames, and the others are kept. A leading ``/`` of a frame id is
dropped, as tf2 drops it. Pure library: never raises.
"""
from __future__ import annotations

import math
from typing import NamedTuple

from rcbf_ros.messages import sensor
from rcbf_ros.messages.sensor import _Bad, _Cursor, Refused  # the readers' one CDR cursor

TF_MESSAGE = 'tf2_msgs/msg/TFMessage'

MAX_TRANSFORMS = 1024
"""The most transforms read from one message; a message with more is refused (a robot's
whole tree is tens of frames)."""
MAX_FRAME_ID = sensor.MAX_FRAME_ID
"""The most characters of a frame id (``header.frame_id``, ``child_frame_id``)."""
MAX_TRANSLATION = 1.0e6
"""The largest |translation| (m) on any axis; a transform farther is refused (sensor points
lie within :data:`rcbf_ros.messages.sensor.MAX_COORDINATE` of their frame, and the barrier's
squares must stay finite)."""
QUATERNION_TOLERANCE = 0.01
"""A rotation is refused when | x^2 + y^2 + z^2 + w^2 - 1 | >= this (tf2's
``QUATERNION_NORMALIZATION_TOLERANCE``); a kept one is normalised."""


class StampedTransform(NamedTuple):
    """One transform of a TFMessage: where ``child`` is in ``parent`` at ``stamp_ns``.

    A point p in ``child`` is ``R(rotation) p + translation`` in ``parent``."""

    parent: str
    """header.frame_id (no leading ``/``)."""
    child: str
    """child_frame_id (no leading ``/``)."""
    stamp_ns: int
    """header.stamp in nanoseconds."""
    translation: tuple[float, float, float]
    """x, y, z (m), finite, each within :data:`MAX_TRANSLATION`."""
    rotation: tuple[float, float, float, float]
    """x, y, z, w: a unit quaternion."""


class Transforms(NamedTuple):
    """A read TFMessage: the transforms kept and why the others were refused."""

    transforms: tuple[StampedTransform, ...]
    """The valid transforms, in message order."""
    refused: tuple[str, ...]
    """One line per refused transform, naming its index and frames."""


def quoted(frame: str, width: int = 80) -> str:
    """``frame`` as a reason names it: quoted and escaped (one line whatever it holds), cut
    to about ``width`` characters."""
    text = repr(frame)
    return text if len(text) <= width else text[:width - 4] + "...'"


def transform_refusal(parent: str, child: str, translation: tuple[float, ...],
                      rotation: tuple[float, ...]) -> str:
    """Why a transform ``parent`` -> ``child`` cannot be used ('' when it can): tf2's
    checks (same or empty frames, NaN, a quaternion off unit length) and the bounds here
    (infinite values, |translation| > :data:`MAX_TRANSLATION`)."""
    names = f'{quoted(parent)} -> {quoted(child)}'
    if not parent or not child:
        return f'{names}: empty frame id'
    if parent == child:
        return f'{names}: a frame cannot be its own parent'
    for name, values in (('translation', translation), ('rotation', rotation)):
        if not all(math.isfinite(v) for v in values):
            return (f'{names}: {name} '
                    f"({', '.join(f'{v:g}' for v in values)}) is not finite")
    if not all(abs(v) <= MAX_TRANSLATION for v in translation):
        return (f'{names}: translation '
                f"({', '.join(f'{v:g}' for v in translation)}) beyond +-{MAX_TRANSLATION:g} m")
    norm2 = math.fsum(v * v for v in rotation)
    if not abs(norm2 - 1.0) < QUATERNION_TOLERANCE:
        return (f'{names}: rotation '
                f"({', '.join(f'{v:g}' for v in rotation)}) is not a unit quaternion "
                f'(squared length {norm2:.3g})')
    return ''


def refusals_line(refused: list[str]) -> str:
    """The refusals of one message's transforms as one line: '' for none, else the first
    (its whitespace folded) and how many more."""
    if not refused:
        return ''
    more = f' (and {len(refused) - 1} more)' if len(refused) > 1 else ''
    return ' '.join(refused[0].split()) + more


def frame_name_refusal(frame: str) -> str:
    """Why ``frame`` cannot name a frame a node publishes ('' when it can): empty, longer than
    the readers' :data:`MAX_FRAME_ID`, with white space or a control character, or with a
    leading ``/`` (tf2 refuses or strips it, so that the id published is not the one looked
    up)."""
    if not frame:
        return 'empty frame id'
    if len(frame) > MAX_FRAME_ID:
        return f'{len(frame)} characters, more than the bound {MAX_FRAME_ID}: {quoted(frame, 40)}'
    if any(c.isspace() or not c.isprintable() for c in frame):
        return f'{quoted(frame)} holds white space or a control character'
    if frame.startswith('/'):
        return f'{quoted(frame)} starts with / (tf2 frame ids do not)'
    return ''


def _frame(text: str) -> str:
    """A frame id as tf2 keeps it: without a leading ``/``."""
    return text[1:] if text.startswith('/') else text


def tf_transforms(data: bytes | memoryview, *, max_transforms: int = MAX_TRANSFORMS
                  ) -> Transforms | Refused:
    """The transforms of a TFMessage sample (module docstring): :class:`Transforms`, or
    :class:`Refused` naming the field when the bytes do not fit the layout. Never raises."""
    try:
        cursor = _Cursor(data)
        count = cursor.uint32('transforms')
        if count > max_transforms:
            return Refused(f'{TF_MESSAGE}: transforms has {count} entries, more than the bound '
                           f'{max_transforms}')
        kept: list[StampedTransform] = []
        refused: list[str] = []
        for k in range(count):
            sec = cursor.int32(f'transforms[{k}].header.stamp.sec')
            nanosec = cursor.uint32(f'transforms[{k}].header.stamp.nanosec')
            parent = _frame(cursor.string(f'transforms[{k}].header.frame_id', MAX_FRAME_ID))
            child = _frame(cursor.string(f'transforms[{k}].child_frame_id', MAX_FRAME_ID))
            translation = cursor.float64s(3, f'transforms[{k}].transform.translation')
            rotation = cursor.float64s(4, f'transforms[{k}].transform.rotation')
            why = transform_refusal(parent, child, translation, rotation)
            if why:
                refused.append(f'transforms[{k}] {why}')
                continue
            norm = math.sqrt(math.fsum(v * v for v in rotation))
            x, y, z, w = (v / norm for v in rotation)
            kept.append(StampedTransform(parent, child, sec * 1_000_000_000 + nanosec,
                                         (translation[0], translation[1], translation[2]),
                                         (x, y, z, w)))
        return Transforms(tuple(kept), tuple(refused))
    except _Bad as exc:
        return Refused(f'{TF_MESSAGE}: {exc}')
    except Exception as exc:  # bytes are untrusted: any other failure is a refusal too
        return Refused(f'{TF_MESSAGE}: {type(exc).__name__}: {" ".join(str(exc).split())}'[:200])
