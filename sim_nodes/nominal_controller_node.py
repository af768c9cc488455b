"""The ``nominal_controller`` node: the deliberately unsafe controllers of rcbf_ros.envs.nominal.

Subscribes ``state`` (Float64MultiArray, section ``state``, or the whole data when unlabelled)
and publishes ``cmd_proposed`` (Float64MultiArray, sections ``u`` and ``state``: the command
and the state it answers) once per state: Unicycle and
PVTOL drive straight at ``goal``, the car accelerates into car 3 at ``acceleration``. Put a
safety_filter between it and the simulator (``cmd_proposed`` -> filter -> ``cmd_safe``), or remap
``cmd_proposed:=cmd_safe`` to watch it crash.

Parameters: ``system`` and the ``/nominal_controller`` section of ``config/<system>.yaml``
(``goal`` for unicycle / pvtol, ``acceleration`` for car_following).
"""
from __future__ import annotations

import sys
from typing import Any, Callable, Sequence

import numpy as np

from rcbf_ros.envs.nominal import cars_accelerate, pvtol_go_to_goal, unicycle_go_to_goal
from rcbf_ros.ros.conversions import msg_to_sections, sections_to_msg
from rcbf_ros.ros.node_main import run_node
from rcbf_ros.ros.runtime import get_message, Node, QoSProfile
from sim_nodes.simulator_node import declare_with_packaged_defaults


def controller_from_params(params: dict[str, Any]) -> Callable[[np.ndarray], np.ndarray]:
    """The nominal controller of ``params['system']`` with its parameters bound.

    Raises:
        ValueError: naming ``goal`` or ``acceleration`` when malformed.
    """
    system = params['system']
    if system == 'car_following':
        try:
            acceleration = float(params.get('acceleration', 5.0))
        except (TypeError, ValueError) as exc:
            raise ValueError(f'acceleration: expected a number, got '
                             f'{params.get("acceleration")!r}') from exc
        return lambda x: cars_accelerate(x, acceleration=acceleration)
    default_goal = (2.5, 2.5) if system == 'unicycle' else (5.0, -1.5)
    goal = [float(v) for v in params.get('goal', default_goal)]
    if len(goal) != 2:
        raise ValueError(f'goal: expected 2 values, got {len(goal)}')
    if system == 'unicycle':
        return lambda x: unicycle_go_to_goal(x, goal)
    return lambda x: pvtol_go_to_goal(x, goal)


class NominalControllerNode(Node):
    """state -> cmd_proposed through one nominal controller."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__('nominal_controller',
                         automatically_declare_parameters_from_overrides=True, **kwargs)
        params = declare_with_packaged_defaults(self, 'nominal_controller')
        self.controller = controller_from_params(params)
        array = get_message('std_msgs/msg/Float64MultiArray')
        self.publisher = self.create_publisher(array, 'cmd_proposed', QoSProfile(depth=10))
        self.create_subscription(array, 'state', self.on_state, QoSProfile(depth=10))
        self.done = False
        self.get_logger().info(f'nominal controller for {params["system"]}')

    def on_state(self, msg: Any) -> None:
        try:
            sections = msg_to_sections(msg, default_label='state')
            if 'state' not in sections:
                raise ValueError(f'state: no section labelled state in {list(sections)}')
            u = self.controller(sections['state'])
        except (ValueError, IndexError) as exc:
            self.get_logger().error(f'{exc}; no command')
            return
        # The answered state rides along so that a lock-step simulator can drop stale answers.
        self.publisher.publish(sections_to_msg({'u': u, 'state': sections['state']}))


def main(args: Sequence[str] | None = None) -> int:
    """Console script ``nominal_controller``."""
    return run_node('nominal_controller', NominalControllerNode, args)


if __name__ == '__main__':
    sys.exit(main())
