"""``policy`` node: a trained policy alone, proposing actions to the safety filter.

Deployment without the learner: loads ``policy.pt`` (written by the learner node or
``rcbf_ros train``), takes the mean action of the actor for every observation and publishes it
on ``cmd_proposed`` for the safety_filter node, which keeps it safe (its disturbance box comes
from its own parameters). Input: ``sim/step`` (sections ``observation`` and ``state``; the state
rides along in the proposal so the filter answers exactly the state the action was made for),
remappable to any Float64MultiArray stream with an ``observation`` section.

Parameters: ``policy_path`` (required), ``input_topic`` (default ``sim/step``).
"""
from __future__ import annotations

from dataclasses import dataclass
import sys
from typing import Any, Sequence

import numpy as np
import torch

from rcbf_ros.messages.conversions import msg_to_sections, sections_to_msg
from rcbf_ros.node_logic.interface import (
    declarations,
    FLOAT64_MULTIARRAY,
    NodeInterface,
    parameter_specs,
    ParameterSpec,
    TopicSpec,
)
from rcbf_ros.parameters.reader import read_parameters, setting
from rcbf_ros.ros.node_main import declare_specs, run_node
from rcbf_ros.ros.runtime import get_message, Node, QoSProfile
from rcbf_ros.training.policy_io import load_policy


@dataclass(frozen=True)
class PolicySettings:
    """The policy node's parameters."""

    policy_path: str = setting('', description='the policy.pt to run (from the learner or '
                                                'rcbf_ros train; required)')
    """The policy.pt to run (required)."""
    input_topic: str = setting('sim/step', description='Float64MultiArray topic with an '
                                                       '`observation` section (and `state`)')
    """Where the observations come from."""


PARAMETERS: tuple[ParameterSpec, ...] = parameter_specs(PolicySettings)
"""The policy node's parameters, in declaration order."""

INTERFACE = NodeInterface(
    node='policy',
    summary='A trained policy alone, proposing actions to the safety filter (deployment).',
    topics=(
        TopicSpec('sim/step', 'sub', FLOAT64_MULTIARRAY,
                  'input_topic: sections observation (the policy input) and optional state, '
                  'episode, step, terminated, truncated'),
        TopicSpec('cmd_proposed', 'pub', FLOAT64_MULTIARRAY,
                  "sections u (n_u: the actor's mean action) and state (n_x, when the input "
                  'has it)'),
    ),
    parameters=PARAMETERS,
)
"""Topics and parameters (``policy --help``, README)."""


class PolicyNode(Node):
    """See module docstring."""

    def __init__(self) -> None:
        super().__init__('policy')
        declare_specs(self, PARAMETERS)
        values = {name: self.get_parameter(name).value for name, _ in declarations(PARAMETERS)}
        settings = read_parameters(PolicySettings, values)
        path, topic = settings.policy_path, settings.input_topic
        if not path:
            raise ValueError('policy_path: required (a policy.pt from the learner)')
        self.policy = load_policy(path)
        self.last_index: tuple[float, float] | None = None
        self.last_msg: Any = None
        array = get_message('std_msgs/msg/Float64MultiArray')
        qos = QoSProfile(depth=10)
        self.publisher = self.create_publisher(array, 'cmd_proposed', qos)
        self.create_subscription(array, topic, self.on_input, qos)
        self.get_logger().info(f'policy {path} ({self.policy.system}, obs {self.policy.obs_dim}, '
                               f'u {self.policy.n_u}) on {topic}')

    def on_input(self, msg: Any) -> None:
        try:
            sections = msg_to_sections(msg, default_label='observation')
            done = any(sections.get(k, np.zeros(1))[0] > 0.5 for k in ('terminated', 'truncated'))
            if done:
                return  # the episode is over: the simulator resets and sends step 0
            index = (float(sections.get('episode', [-1])[0]), float(sections.get('step', [-1])[0]))
            if index == self.last_index and self.last_msg is not None:
                self.publisher.publish(self.last_msg)  # re-published step: answer it again
                return
            u = self.policy(sections['observation'])
        except (KeyError, ValueError) as exc:
            self.get_logger().error(f'input: {exc}')
            return
        out = {'u': u}
        if 'state' in sections:
            out['state'] = sections['state']
        self.last_index, self.last_msg = index, sections_to_msg(out)
        self.publisher.publish(self.last_msg)


def main(args: Sequence[str] | None = None) -> int:
    torch.set_num_threads(1)
    return run_node('policy', PolicyNode, args, setup_errors=(ValueError, FileNotFoundError),
                    setup_message='', interface=INTERFACE)


if __name__ == '__main__':
    sys.exit(main())
