"""Offered QoS profiles as rosbag2 stores them (``offered_qos_profiles``, bag version 9).

rosbag2 keeps, for every topic, the QoS profiles its publishers offered: a YAML sequence of
profile mappings. In the bag information (``metadata.yaml`` and the MCAP ``rosbag2`` record's
``serialized_metadata``) version 9 (Jazzy) writes the sequence itself; versions 4 to 8 wrote it
dumped to a string, and the MCAP channel metadata (a string-to-string map) still holds that
string. From version 9 the policies are lower-case names (``keep_last``, ``reliable``,
``volatile``, ``automatic``) instead of the integer enum values of version 8; durations are
``{sec, nsec}`` maps with RMW's "infinite" ``{9223372036, 854775807}``.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Sequence

import yaml

from rcbf_ros.parameters import bounded_yaml

#: RMW_DURATION_INFINITE as rosbag2 dumps it: (sec, nsec) = (2**63 - 1) ns split at 1e9.
INFINITE_DURATION_NS = 9223372036 * 1_000_000_000 + 854775807

_HISTORY = ('system_default', 'keep_last', 'keep_all', 'unknown')
_RELIABILITY = ('system_default', 'reliable', 'best_effort', 'unknown', 'best_available')
_DURABILITY = ('system_default', 'transient_local', 'volatile', 'unknown', 'best_available')
_LIVELINESS = ('system_default', 'automatic', 'manual_by_node', 'manual_by_topic', 'unknown',
               'best_available')


@dataclass(frozen=True)
class RecordedQos:
    """One QoS profile offered by a publisher, as rosbag2 records it.

    The defaults are what rclpy's default publisher (``QoSProfile(depth=10)``) offers as seen
    through discovery: keep-last 10, reliable, volatile, infinite deadline/lifespan/lease.
    """

    history: str = 'keep_last'
    """``keep_last``, ``keep_all``, ``system_default`` or ``unknown``."""
    depth: int = 10
    """History depth (meaningful for ``keep_last``; rosbag2 writes 0 for ``keep_all``)."""
    reliability: str = 'reliable'
    """``reliable``, ``best_effort``, ``system_default``, ``best_available`` or ``unknown``."""
    durability: str = 'volatile'
    """``volatile``, ``transient_local``, ``system_default``, ``best_available`` or ``unknown``."""
    deadline_ns: int = INFINITE_DURATION_NS
    """Deadline period in nanoseconds (``INFINITE_DURATION_NS``: none)."""
    lifespan_ns: int = INFINITE_DURATION_NS
    """Lifespan in nanoseconds (``INFINITE_DURATION_NS``: none)."""
    liveliness: str = 'automatic'
    """``automatic``, ``manual_by_topic``, ``system_default``, ... or ``unknown``."""
    liveliness_lease_duration_ns: int = INFINITE_DURATION_NS
    """Liveliness lease duration in nanoseconds."""
    avoid_ros_namespace_conventions: bool = False
    """Whether the topic name bypasses the ``rt/`` prefix conventions."""

    def __post_init__(self) -> None:
        for field_name, allowed in (('history', _HISTORY), ('reliability', _RELIABILITY),
                                    ('durability', _DURABILITY), ('liveliness', _LIVELINESS)):
            if getattr(self, field_name) not in allowed:
                raise ValueError(f'RecordedQos.{field_name} must be one of {allowed}, '
                                 f'got {getattr(self, field_name)!r}')
        if self.depth < 0:
            raise ValueError(f'RecordedQos.depth must be >= 0, got {self.depth}')
        for field_name in ('deadline_ns', 'lifespan_ns', 'liveliness_lease_duration_ns'):
            if getattr(self, field_name) < 0:
                raise ValueError(f'RecordedQos.{field_name} must be >= 0')

    @classmethod
    def sensor_data(cls) -> RecordedQos:
        """rclpy's ``qos_profile_sensor_data``: best effort, keep-last 5."""
        return cls(depth=5, reliability='best_effort')

    @classmethod
    def from_profile(cls, profile: Any) -> RecordedQos:
        """Convert an rclpy-like ``QoSProfile`` (policies as enums, ints or names).

        Reads ``history``, ``depth``, ``reliability``, ``durability`` (enum members are mapped
        by their ``name``, e.g. ``ReliabilityPolicy.BEST_EFFORT`` -> ``best_effort``). Missing
        attributes keep the defaults.
        """
        def policy_name(value: Any, names: tuple[str, ...], default: str) -> str:
            if value is None:
                return default
            name = getattr(value, 'name', None)
            if isinstance(name, str):
                return name.lower()
            if isinstance(value, int) and 0 <= value < len(names):
                return names[value]
            return str(value).lower()

        history = policy_name(getattr(profile, 'history', None), _HISTORY, 'keep_last')
        depth = int(getattr(profile, 'depth', 10) or 0)
        return cls(
            history=history,
            depth=0 if history == 'keep_all' else depth,
            reliability=policy_name(getattr(profile, 'reliability', None), _RELIABILITY,
                                    'reliable'),
            durability=policy_name(getattr(profile, 'durability', None), _DURABILITY,
                                   'volatile'),
        )

    def to_yaml_dict(self) -> dict[str, Any]:
        """The profile as the mapping rosbag2 (version 9) dumps, keys in its order."""
        return {
            'history': self.history,
            'depth': self.depth,
            'reliability': self.reliability,
            'durability': self.durability,
            'deadline': _duration(self.deadline_ns),
            'lifespan': _duration(self.lifespan_ns),
            'liveliness': self.liveliness,
            'liveliness_lease_duration': _duration(self.liveliness_lease_duration_ns),
            'avoid_ros_namespace_conventions': self.avoid_ros_namespace_conventions,
        }


def _duration(nanoseconds: int) -> dict[str, int]:
    return {'sec': nanoseconds // 1_000_000_000, 'nsec': nanoseconds % 1_000_000_000}


def offered_qos_sequence(profiles: Sequence[RecordedQos]) -> list[dict[str, Any]]:
    """``profiles`` as the YAML sequence of the bag information (version 9)."""
    return [p.to_yaml_dict() for p in profiles]


def dump_offered_qos_profiles(profiles: Sequence[RecordedQos]) -> str:
    """YAML text of ``profiles`` in rosbag2's block style (no trailing newline; ``[]`` if empty).

    Example (one default profile)::

        - history: keep_last
          depth: 10
          reliability: reliable
          ...
          avoid_ros_namespace_conventions: false
    """
    if not profiles:
        return '[]'
    text = yaml.safe_dump(offered_qos_sequence(profiles), sort_keys=False,
                          default_flow_style=False, indent=2)
    return text.rstrip('\n')


def parse_offered_qos_profiles(value: str | Sequence[Any] | None) -> list[RecordedQos]:
    """Profiles from either form: the sequence (bag information, version 9) or the YAML string
    (channel metadata; bag information before version 9). Version-8 integer policies too.

    The string is read within the limits of :mod:`rcbf_ros.parameters.bounded_yaml`, without
    aliases (rosbag2 writes none).

    Raises:
        ValueError: the string is not YAML or past a limit, or the value is not a sequence of
            profile mappings (the message names ``offered_qos_profiles``).
    """
    if value is None or (isinstance(value, str) and not value.strip()):
        return []
    if isinstance(value, str):
        try:
            value = bounded_yaml.safe_load(value, source='offered_qos_profiles',
                                           allow_aliases=False) or []
        except bounded_yaml.YAMLLimitError:
            raise
        except yaml.YAMLError as exc:
            raise ValueError(f'offered_qos_profiles: not YAML ({exc})') from exc
    if not isinstance(value, (list, tuple)):
        raise ValueError(f'offered_qos_profiles: expected a sequence of profiles, got '
                         f'{type(value).__name__}')
    try:
        return [_profile_from_yaml(item) for item in value]
    except (KeyError, TypeError, IndexError) as exc:
        raise ValueError(f'offered_qos_profiles: not a QoS profile ({exc!r})') from exc


def _profile_from_yaml(item: dict[str, Any]) -> RecordedQos:
    def name(key: str, names: tuple[str, ...]) -> str:
        value = item[key]
        return names[value] if isinstance(value, int) else str(value)

    def nanos(key: str) -> int:
        return int(item[key]['sec']) * 1_000_000_000 + int(item[key]['nsec'])

    return RecordedQos(
        history=name('history', _HISTORY), depth=int(item['depth']),
        reliability=name('reliability', _RELIABILITY),
        durability=name('durability', _DURABILITY),
        deadline_ns=nanos('deadline'), lifespan_ns=nanos('lifespan'),
        liveliness=name('liveliness', _LIVELINESS),
        liveliness_lease_duration_ns=nanos('liveliness_lease_duration'),
        avoid_ros_namespace_conventions=bool(item['avoid_ros_namespace_conventions']))
