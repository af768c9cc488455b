"""The safety filter node's topics and parameters, without the node and without the middleware.

``safety_filter --help`` prints :data:`INTERFACE` from here
(:func:`rcbf_ros.ros.node_main.main_of`) before anything of the DDS runtime loads; the node
(:mod:`rcbf_ros.ros.safety_filter_node`), docs/INTERFACE.md and the README read the same
object.
"""
from __future__ import annotations

from rcbf_ros.node_logic.interface import (
    COMMAND_TOPIC_TYPES,
    DIAGNOSTIC_ARRAY,
    FLOAT64_MULTIARRAY,
    NodeInterface,
    OBSTACLES_QOS,
    STATE_TOPIC_TYPES,
    TopicSpec,
)
from rcbf_ros.node_logic.safety_filter import PARAMETERS

NODE_NAME = 'safety_filter'
_QOS = 'reliable, keep-last 10 (qos.reliable, qos.depth)'
TF_MESSAGE = 'tf2_msgs/msg/TFMessage'
TF_QOS = 'reliable, keep-last 100 (tf2_ros listener)'
"""QoS of the ``/tf`` subscription (tf2_ros's listener's)."""
TF_STATIC_QOS = 'reliable, keep-last 1, transient-local (tf2_ros static listener)'
"""QoS of the ``/tf_static`` subscription (tf2_ros's static listener's)."""


def _topic(name: str, direction: str, kind: str, layout: str) -> TopicSpec:
    """A topic of the filter's own (QoS from qos.reliable and qos.depth)."""
    return TopicSpec(name, direction, kind, layout, _QOS)


INTERFACE = NodeInterface(
    node=NODE_NAME,
    summary='The RCBF safety filter in front of any controller: a proposed command in, the '
            'safe command out (every parameter also from --params-file config/<system>.yaml).',
    topics=(
        _topic('state', 'sub', STATE_TOPIC_TYPES,
               'state_type array: section `state` (else the first), n_x values in the '
               "system's state layout; odometry: [x, y, yaw] of the pose (unicycle)"),
        _topic('cmd_proposed', 'sub', COMMAND_TOPIC_TYPES,
               'command_type array: section `u` (n_u; unlabelled data is u) and optional '
               '`disturbance_mean`, `disturbance_std`, `state` (n_x each); twist(_stamped): '
               'u in twist_fields'),
        _topic('cmd_safe', 'pub', 'the type of cmd_proposed (command_type)',
               'the safe command only: array: exactly u (n_u values, section `u`); '
               "twist(_stamped): u in twist_fields, others 0; TwistStamped: the proposal's "
               'header (stamp, frame_id)'),
        _topic('filter_info', 'pub', FLOAT64_MULTIARRAY,
               'one per command: sections u, u_rl, u_s (n_u each), fail_safe, status (1 each),'
               ' then when known h, constraint (K each), slack, needed_slack, solve_time_s '
               '(1 each), state (n_x), binding_points (4 per point, at most 16 sensor points: '
               'x, y, row value, h); never NaN'),
        _topic('diagnostics', 'pub', DIAGNOSTIC_ARRAY,
               'a status per WARN / ERROR answer, OK ones at most every '
               'diagnostics.min_period_s (0: every one): h.<barrier>, constraint.<barrier>, '
               'slack, status, reason, times, counts'),
        TopicSpec('obstacles', 'sub', FLOAT64_MULTIARRAY,
                  'the whole obstacle set, rows [x, y, radius] (3 k values, layout.dim none or '
                  '[k, 3]); replaces obstacles.x/y/radius as a parameter change would',
                  OBSTACLES_QOS),
        TopicSpec('/tf', 'sub', TF_MESSAGE,
                  'with observation_sources: transforms that place sensor points in '
                  'odom_frame_id at their stamps (docs/SAFETY_FILTER.md "Perception sources")',
                  TF_QOS),
        TopicSpec('/tf_static', 'sub', TF_MESSAGE,
                  'with observation_sources: the static transforms (sensor mounts)',
                  TF_STATIC_QOS),
    ),
    parameters=PARAMETERS,
    notes=('Parameters marked <name> are families whose names you choose (bands.operator.index, '
           'system_params.with_operator, front.topic of a source front listed in '
           'observation_sources): declared when given.',),
)
"""Topics and parameters (``safety_filter --help``, README)."""
