"""The message types of a node's edges: ``state_type``, ``command_type``, ``twist_fields``.

One dataclass (:class:`MessageSettings`) read by the typed reader, shared by the safety filter,
the simulator and the nominal controller, so that the three accept the same values, say the
same thing in ``--help`` and default alike. Pure: no middleware, no messages.
"""
from __future__ import annotations

from dataclasses import dataclass

from rcbf_ros.parameters.reader import ParameterError, setting

STATE_TYPES = ('array', 'odometry')
"""``state_type``: std_msgs/Float64MultiArray or nav_msgs/Odometry."""
COMMAND_TYPES = ('array', 'twist', 'twist_stamped')
"""``command_type``: std_msgs/Float64MultiArray, geometry_msgs/Twist or TwistStamped."""
SIM_STEP_SECTIONS = ('state', 'observation', 'reward', 'action', 'terminated', 'truncated',
                     'violation', 'goal_reached', 'episode', 'step')
"""The sections of the simulator's ``sim/step`` message, in order."""
TWIST_FIELDS = tuple(f'{group}.{axis}' for group in ('linear', 'angular') for axis in 'xyz')
"""The Twist fields u may sit in."""


@dataclass(frozen=True)
class MessageSettings:
    """The message types of a node's state and command topics."""

    state_type: str = setting(
        'array', choices=STATE_TYPES, read_only=True,
        description='type of `state`: array (std_msgs/Float64MultiArray) or odometry '
                    '(nav_msgs/Odometry; unicycle only)')
    """'array' (Float64MultiArray, its ``state`` section) or 'odometry' (nav_msgs/Odometry)."""
    command_type: str = setting(
        'array', choices=COMMAND_TYPES, read_only=True,
        description='type of the command topics: array (std_msgs/Float64MultiArray), twist or '
                    'twist_stamped (geometry_msgs)')
    """'array' (Float64MultiArray with labelled sections), 'twist' (geometry_msgs/Twist) or
    'twist_stamped' (geometry_msgs/TwistStamped)."""
    twist_fields: tuple[str, ...] = setting(
        ('linear.x', 'angular.z'), choices=TWIST_FIELDS, nonempty=True, distinct=True,
        read_only=True, description='for twist and twist_stamped: the n_u Twist fields holding '
                                    'u, in order (the others are 0)')
    """For 'twist' / 'twist_stamped': the Twist fields holding u in order, e.g.
    (linear.x, angular.z)."""

    def check_inputs(self, *, n_u: int, system: str) -> None:
        """Refuse twist fields that are not one per input of ``system``.

        Raises:
            ParameterError: naming ``twist_fields``.
        """
        if self.command_type != 'array' and len(self.twist_fields) != n_u:
            raise ParameterError(f'twist_fields: expected {n_u} fields (n_u of {system}), '
                                 f'got {list(self.twist_fields)}')
