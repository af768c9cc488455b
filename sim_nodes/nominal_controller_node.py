"""The ``nominal_controller`` node: the deliberately unsafe controllers of rcbf_ros.envs.nominal.

Subscribes ``state`` and publishes ``cmd_proposed`` once per state: Unicycle and PVTOL drive
straight at ``goal``, the car accelerates into car 3 at ``acceleration``. Put a safety_filter
between it and the simulator (``cmd_proposed`` -> filter -> ``cmd_safe``), or remap
``cmd_proposed:=cmd_safe`` to watch it crash.

Message types follow the parameters, as the safety filter's do: ``state_type`` ``array``
(Float64MultiArray, section ``state``, or the whole data when unlabelled) or ``odometry``
(nav_msgs/Odometry, unicycle); ``command_type`` ``array`` (sections ``u`` and ``state``: the
command and the state it answers, so that a lock-step simulator can drop a late answer),
``twist`` or ``twist_stamped`` (u in ``twist_fields``; a TwistStamped carries the header of the
Odometry it answers, else the node's clock and an empty frame_id).

Parameters: :func:`nominal_controller_interface` (``nominal_controller --help``): the node's
own, ``system`` and the ``/nominal_controller`` section of ``config/<system>.yaml`` (``goal``
for unicycle / pvtol, ``acceleration`` for car_following).
"""
from __future__ import annotations

import sys
from typing import Any, Callable, Sequence

import numpy as np

from rcbf_ros.core.config import build_system
from rcbf_ros.envs import env_class
from rcbf_ros.messages import conversions
from rcbf_ros.messages.conversions import msg_to_sections, sections_to_msg
from rcbf_ros.node_logic.edges import MessageSettings
from rcbf_ros.node_logic.interface import (
    COMMAND_TOPIC_TYPES,
    NodeInterface,
    parameter_specs,
    ParameterSpec,
    STATE_TOPIC_TYPES,
    TopicSpec,
)
from rcbf_ros.ros.node_main import run_node
from rcbf_ros.ros.runtime import get_message, Node, QoSProfile
from sim_nodes.packaged import declare_with_packaged_defaults, packaged_interface
from sim_nodes.simulator_node import message_settings

NODE_PARAMETERS: tuple[ParameterSpec, ...] = parameter_specs(MessageSettings,
                                                             mark_read_only=False)
"""The controller's own parameters."""


TOPICS: tuple[TopicSpec, ...] = (
    TopicSpec('state', 'sub', STATE_TOPIC_TYPES,
              'state_type array: section `state` (else all data); odometry: pose [x, y, yaw]'),
    TopicSpec('cmd_proposed', 'pub', COMMAND_TOPIC_TYPES,
              'array: sections `u` (n_u) and `state` (n_x, the state it answers); '
              "twist(_stamped): u in twist_fields, the Odometry's header"),
)


def nominal_controller_interface(argv: Sequence[str] = ()) -> NodeInterface:
    """Topics and parameters of the nominal controller for the ``system`` of a command line."""
    return packaged_interface(
        argv, node='nominal_controller', section='nominal_controller', topics=TOPICS,
        own=NODE_PARAMETERS,
        summary='A deliberately unsafe controller (straight at the goal, or into the car ahead) '
                'to put behind the safety filter.')


def controller_from_params(params: dict[str, Any]) -> Callable[[np.ndarray], np.ndarray]:
    """The nominal controller of ``params['system']`` with its parameters bound (the env's
    :meth:`~rcbf_ros.envs.base.SafetyEnv.nominal_controller`).

    Raises:
        ValueError: naming ``system``, or ``goal`` / ``acceleration`` when malformed.
    """
    return env_class(str(params['system'])).nominal_controller(params)


class NominalControllerNode(Node):
    """state -> cmd_proposed through one nominal controller."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__('nominal_controller',
                         automatically_declare_parameters_from_overrides=True, **kwargs)
        params = declare_with_packaged_defaults(self, 'nominal_controller', own=NODE_PARAMETERS)
        self.system = str(params['system'])
        self.controller = controller_from_params(params)
        messages = message_settings(params, system=self.system, n_u=build_system(params).n_u)
        self.state_type, self.command_type = messages.state_type, messages.command_type
        self.twist_fields = messages.twist_fields
        self.publisher = self.create_publisher(
            get_message(conversions.COMMAND_MESSAGES[self.command_type]), 'cmd_proposed',
            QoSProfile(depth=10))
        self.create_subscription(get_message(conversions.STATE_MESSAGES[self.state_type]),
                                 'state', self.on_state, QoSProfile(depth=10))
        self.done = False
        self.get_logger().info(f'nominal controller for {self.system}, state_type '
                               f'{self.state_type}, command_type {self.command_type}')

    def on_state(self, msg: Any) -> None:
        try:
            if self.state_type == 'odometry':
                state = conversions.odometry_to_state(msg, system=self.system)
            else:
                sections = msg_to_sections(msg, default_label='state')
                if 'state' not in sections:
                    raise ValueError(f'state: no section labelled state in {list(sections)}')
                state = sections['state']
            u = np.asarray(self.controller(state), dtype=np.float64)
        except (ValueError, IndexError) as exc:
            self.get_logger().error(f'{exc}; no command')
            return
        self.publisher.publish(self.command(u, state, msg))

    def command(self, u: np.ndarray, state: np.ndarray, state_msg: Any) -> Any:
        """The ``cmd_proposed`` message answering ``state`` (received as ``state_msg``)."""
        if self.command_type == 'twist':
            return conversions.array_to_twist(u, self.twist_fields)
        if self.command_type == 'twist_stamped':
            if self.state_type == 'odometry':
                header = state_msg.header
            else:
                header = get_message('std_msgs/msg/Header')()
                header.stamp = self.get_clock().now().to_msg()
            return conversions.array_to_twist_stamped(u, self.twist_fields, header)
        # The answered state rides along so that a lock-step simulator can drop stale answers.
        return sections_to_msg({'u': u, 'state': state})


def main(args: Sequence[str] | None = None) -> int:
    """Console script ``nominal_controller``. Returns 2 on invalid parameters."""
    return run_node('nominal_controller', NominalControllerNode, args,
                    setup_errors=(ValueError,), interface=nominal_controller_interface)


if __name__ == '__main__':
    sys.exit(main())
