"""tf2_msgs/TFMessage test messages encoded by rosbags' Jazzy type store (an encoder that is
not the reader under test)."""
from __future__ import annotations

import math

from rcbf_ros.messages.tf import TF_MESSAGE
from rcbf_ros.messages.typestore import jazzy_typestore

STORE = jazzy_typestore()
T = STORE.types


def yaw_quaternion(yaw: float) -> tuple[float, float, float, float]:
    """x, y, z, w of a rotation by ``yaw`` about z."""
    return (0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2))


def transform_stamped(parent: str, child: str, *, stamp_ns: int = 0,
                      translation=(0.0, 0.0, 0.0), rotation=(0.0, 0.0, 0.0, 1.0)):
    """A geometry_msgs/TransformStamped of rosbags'."""
    sec, nanosec = divmod(stamp_ns, 1_000_000_000)
    header = T['std_msgs/msg/Header'](
        stamp=T['builtin_interfaces/msg/Time'](sec=sec, nanosec=nanosec), frame_id=parent)
    return T['geometry_msgs/msg/TransformStamped'](
        header=header, child_frame_id=child,
        transform=T['geometry_msgs/msg/Transform'](
            translation=T['geometry_msgs/msg/Vector3'](*map(float, translation)),
            rotation=T['geometry_msgs/msg/Quaternion'](*map(float, rotation))))


def tf_bytes(*transforms, little_endian: bool = True) -> bytes:
    """The CDR bytes of a TFMessage holding ``transforms`` (:func:`transform_stamped`)."""
    msg = T[TF_MESSAGE](transforms=list(transforms))
    return bytes(STORE.serialize_cdr(msg, TF_MESSAGE, little_endian=little_endian))
