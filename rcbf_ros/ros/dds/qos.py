"""rclpy-compatible QoS profiles and their Cyclone DDS equivalents (as rmw_cyclonedds does)."""
from __future__ import annotations

from dataclasses import dataclass
import enum

from cyclonedds.core import Policy, Qos
from cyclonedds.util import duration

from rcbf_ros.ros.dds import messages

# A reliable writer whose KEEP_ALL history is full blocks at most this long in write().
_RELIABLE_MAX_BLOCKING_S = 1


class ReliabilityPolicy(enum.IntEnum):
    """rclpy.qos.ReliabilityPolicy."""

    SYSTEM_DEFAULT = 0
    RELIABLE = 1
    BEST_EFFORT = 2


class DurabilityPolicy(enum.IntEnum):
    """rclpy.qos.DurabilityPolicy."""

    SYSTEM_DEFAULT = 0
    TRANSIENT_LOCAL = 1
    VOLATILE = 2


class HistoryPolicy(enum.IntEnum):
    """rclpy.qos.HistoryPolicy."""

    SYSTEM_DEFAULT = 0
    KEEP_LAST = 1
    KEEP_ALL = 2


@dataclass
class QoSProfile:
    """The QoS subset our runtime honours (rclpy.qos.QoSProfile's keywords).

    ROS 2 defaults: reliable, volatile, keep-last 10.
    """

    history: HistoryPolicy = HistoryPolicy.KEEP_LAST
    """Keep the last ``depth`` samples or all of them."""
    depth: int = 10
    """History depth for KEEP_LAST (ignored for KEEP_ALL)."""
    reliability: ReliabilityPolicy = ReliabilityPolicy.RELIABLE
    """Retransmit lost samples (RELIABLE) or not (BEST_EFFORT)."""
    durability: DurabilityPolicy = DurabilityPolicy.VOLATILE
    """Late joiners get old samples (TRANSIENT_LOCAL) or not (VOLATILE)."""

    def __post_init__(self) -> None:
        self.history = HistoryPolicy(self.history)
        self.reliability = ReliabilityPolicy(self.reliability)
        self.durability = DurabilityPolicy(self.durability)
        if not isinstance(self.depth, int) or self.depth < 0:
            raise ValueError(f'QoSProfile.depth must be a non-negative int, got {self.depth!r}')
        if self.history == HistoryPolicy.KEEP_LAST and self.depth == 0:
            raise ValueError('QoSProfile.depth must be >= 1 with HistoryPolicy.KEEP_LAST')


qos_profile_sensor_data = QoSProfile(depth=5, reliability=ReliabilityPolicy.BEST_EFFORT)
"""rclpy's sensor-data profile: best effort, volatile, keep-last 5."""


def as_profile(qos: QoSProfile | int) -> QoSProfile:
    """``create_publisher(..., 10)`` means keep-last 10 with the other defaults, as in rclpy."""
    if isinstance(qos, QoSProfile):
        return qos
    if isinstance(qos, int) and not isinstance(qos, bool):
        return QoSProfile(depth=qos)
    if hasattr(qos, 'reliability') and hasattr(qos, 'depth'):
        return QoSProfile(history=int(qos.history), depth=int(qos.depth),
                          reliability=int(qos.reliability), durability=int(qos.durability))
    raise TypeError(f'qos_profile must be a QoSProfile or a history depth, got {qos!r}')


def type_user_data(type_name: str) -> bytes:
    """The USER_DATA rmw gives an endpoint of ``type_name``: ``typehash=RIHS01_<hex>;``."""
    return f'typehash={messages.type_hash(type_name)};'.encode()


def to_cyclone_qos(profile: QoSProfile, user_data: bytes) -> Qos:
    """The Cyclone QoS of an endpoint with this profile and USER_DATA (:func:`type_user_data`)."""
    if profile.reliability == ReliabilityPolicy.BEST_EFFORT:
        reliability = Policy.Reliability.BestEffort
    else:
        reliability = Policy.Reliability.Reliable(duration(seconds=_RELIABLE_MAX_BLOCKING_S))
    durability = (Policy.Durability.TransientLocal
                  if profile.durability == DurabilityPolicy.TRANSIENT_LOCAL
                  else Policy.Durability.Volatile)
    history = (Policy.History.KeepAll if profile.history == HistoryPolicy.KEEP_ALL
               else Policy.History.KeepLast(profile.depth))
    policies = [reliability, durability, history, Policy.Userdata(user_data)]
    if profile.durability == DurabilityPolicy.TRANSIENT_LOCAL:
        # What a writer keeps for late joiners is Cyclone's durability-service history (default
        # keep-last 1), not its history; rmw_cyclonedds sets the one to the other.
        policies.append(Policy.DurabilityService(
            cleanup_delay=0, history=history, max_samples=-1, max_instances=-1,
            max_samples_per_instance=-1))
    return Qos(*policies)


def from_cyclone_qos(qos: Qos | None) -> QoSProfile:
    """The profile a discovered endpoint's Cyclone QoS stands for (inverse of
    :func:`to_cyclone_qos` as far as discovery tells: history, reliability, durability).

    Policies discovery did not carry keep the ROS 2 defaults; durabilities beyond transient
    local, which no ROS 2 profile offers, read as system default.
    """
    profile = QoSProfile()
    if qos is None:
        return profile
    reliability, durability, history = (qos[Policy.Reliability], qos[Policy.Durability],
                                        qos[Policy.History])
    if reliability is not None:
        profile.reliability = (ReliabilityPolicy.BEST_EFFORT
                               if reliability == Policy.Reliability.BestEffort
                               else ReliabilityPolicy.RELIABLE)
    if durability is not None:
        profile.durability = {Policy.Durability.Volatile: DurabilityPolicy.VOLATILE,
                              Policy.Durability.TransientLocal: DurabilityPolicy.TRANSIENT_LOCAL,
                              }.get(durability, DurabilityPolicy.SYSTEM_DEFAULT)
    if isinstance(history, Policy.History.KeepLast) and history.depth >= 1:
        profile.history, profile.depth = HistoryPolicy.KEEP_LAST, int(history.depth)
    elif history == Policy.History.KeepAll:
        profile.history, profile.depth = HistoryPolicy.KEEP_ALL, 0
    return profile
