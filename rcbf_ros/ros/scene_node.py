"""scene_markers: the safety problem as a MarkerArray for RViz and Foxglove.

    ros2 run rcbf_ros scene_markers --ros-args --params-file config/unicycle.yaml

Topics (relative, so remappable):

- ``state`` (sub): as the safety_filter reads it: std_msgs/Float64MultiArray, its ``state``
  section, else its first section; or nav_msgs/Odometry with ``state_type: odometry``;
- ``diagnostics`` (sub, diagnostic_msgs/DiagnosticArray): the filter's; the ``h.<barrier>``
  values and the message of the status that carries them (or ``min_h``: a filter whose only
  rows are sensor points');
- ``obstacles`` (sub, std_msgs/Float64MultiArray, reliable, keep-last 1, transient-local): the
  safety filter's obstacle set, rows [x, y, radius] (:data:`rcbf_ros.node_logic.interface.
  OBSTACLES_QOS`); the scene draws the new set. A set the filter would refuse is refused here
  too (checked by the same functions), with an ERROR, and the old set stays drawn;
- ``filter_info`` (sub, std_msgs/Float64MultiArray): the filter's answers; their
  ``binding_points`` (the sensor points closest to binding), read at most ``rate_hz`` times a
  second (the latest sample; :func:`rcbf_ros.node_logic.scene.info_binding_points`);
- ``scene_markers`` (pub, visualization_msgs/MarkerArray): obstacles, margins, the robot, its
  footprint, the guarded look-ahead point, every barrier's value, the binding points and the
  active rows (:mod:`rcbf_ros.node_logic.scene`), at most ``rate_hz`` times a second and only
  after a new state, diagnostics or filter_info.

Parameters: the filter keys of the params file (``system``, ``obstacles.*``, ``bands.*``,
``gaps.*``, ...), read and checked as the filter reads them
(:func:`rcbf_ros.core.scene.scene_geometry`; the shipped configs keep them under ``/**``), and
the node's own (:data:`PARAMETERS`): ``frame_id`` ('': the filter's state frame, its
``odom_frame_id`` with observation sources, else ``map``; with sources no other frame is taken),
``rate_hz`` (10.0), ``caution_h`` (0.1: barrier values in [0, caution_h) are amber),
``max_obstacles`` (200: the most obstacles drawn, the nearest to the robot), ``state_type``
(``array``; an Odometry not in ``odom_frame_id`` is skipped with sources).

A state sample that does not decode, or has the wrong length or a NaN, is skipped with a
warning (at most one a second per kind); the scene keeps the last good state. So is a
diagnostics sample that does not decode, and a filter_info sample that does not decode or
whose ``binding_points`` do not fit (the last good points stay drawn).
"""
from __future__ import annotations

import sys
import time
from typing import Any, Mapping, Sequence

import numpy as np

from rcbf_ros.core.scene import scene_geometry
from rcbf_ros.messages import conversions
from rcbf_ros.node_logic import scene as logic
from rcbf_ros.node_logic.edges import MessageSettings
from rcbf_ros.node_logic.filter_edge import shown_reason
from rcbf_ros.node_logic.interface import (
    DIAGNOSTIC_ARRAY,
    FLOAT64_MULTIARRAY,
    NodeInterface,
    OBSTACLES_QOS,
    parameter_specs,
    ParameterSpec,
    STATE_TOPIC_TYPES,
    TopicSpec,
)
from rcbf_ros.node_logic.safety_filter import (
    collect_parameters,
    FILTER_PARAMETERS,
    LogThrottle,
    merged_parameters,
    obstacle_parameters,
    state_from_sections,
)
from rcbf_ros.parameters.reader import read_parameters
from rcbf_ros.ros.node_main import declare_specs, run_node
from rcbf_ros.ros.runtime import (
    deserialize_message,
    DurabilityPolicy,
    get_message,
    HistoryPolicy,
    Node,
    QoSProfile,
    ReliabilityPolicy,
)

NODE_NAME = 'scene_markers'
MARKER_ARRAY = 'visualization_msgs/msg/MarkerArray'

SCENE_PARAMETERS: tuple[ParameterSpec, ...] = parameter_specs(logic.SceneSettings)
"""The scene's settings (:class:`rcbf_ros.node_logic.scene.SceneSettings`)."""
STATE_TYPE_PARAMETERS: tuple[ParameterSpec, ...] = parameter_specs(
    MessageSettings, mark_read_only=False)[:1]
"""``state_type``."""
PARAMETERS: tuple[ParameterSpec, ...] = SCENE_PARAMETERS + STATE_TYPE_PARAMETERS + \
    FILTER_PARAMETERS
"""Every parameter the node declares: its own, then the filter keys of the params file
(declared when given, as the filter reads them)."""

INTERFACE = NodeInterface(
    node=NODE_NAME,
    summary='The safety problem as a MarkerArray for RViz and Foxglove: obstacles, margins, the '
            'robot, every barrier value and the sensor points that bind.',
    topics=(
        TopicSpec('state', 'sub', STATE_TOPIC_TYPES,
                  'as the safety filter reads it (state_type)'),
        TopicSpec('diagnostics', 'sub', DIAGNOSTIC_ARRAY,
                  "the filter's: h.<barrier> values and the status message"),
        TopicSpec('obstacles', 'sub', FLOAT64_MULTIARRAY,
                  "the safety filter's obstacle set, rows [x, y, radius]: drawn instead of "
                  'obstacles.x/y/radius', OBSTACLES_QOS),
        TopicSpec('filter_info', 'sub', FLOAT64_MULTIARRAY,
                  "the filter's answers: their binding_points (sensor points closest to "
                  'binding), the latest read at most rate_hz times a second'),
        TopicSpec('scene_markers', 'pub', 'visualization_msgs/msg/MarkerArray',
                  'obstacles, margins, robot, footprint, guarded point, barrier values, '
                  'binding points and active rows, in frame_id'),
    ),
    parameters=PARAMETERS,
)
"""Topics and parameters (``scene_markers --help``, README)."""


MARKER_DELETEALL = 3
"""visualization_msgs/Marker DELETEALL: the viewer forgets every marker it has from us."""


def marker_array(markers: Sequence[Mapping[str, Any]], *, stamp: Any = None,
                 clear: bool = False) -> Any:
    """Marker dicts (:func:`rcbf_ros.node_logic.scene.scene_markers`) -> a MarkerArray.

    Args:
        clear: begin with a DELETEALL marker (the scene changed: fewer obstacles must not leave
            old discs behind in the viewer).
    """
    marker_cls = get_message('visualization_msgs/msg/Marker')
    point_cls = get_message('geometry_msgs/msg/Point')
    color_cls = get_message('std_msgs/msg/ColorRGBA')
    out = get_message(MARKER_ARRAY)()
    messages = []
    if clear:
        messages.append(marker_cls(action=MARKER_DELETEALL))
    for item in markers:
        msg = marker_cls()
        msg.header.frame_id = item['frame_id']
        if stamp is not None:
            msg.header.stamp = stamp
        msg.ns, msg.id, msg.type, msg.action = item['ns'], item['id'], item['type'], 0
        position, orientation = msg.pose.position, msg.pose.orientation
        position.x, position.y, position.z = item['position']
        orientation.x, orientation.y, orientation.z, orientation.w = item['orientation']
        msg.scale.x, msg.scale.y, msg.scale.z = item['scale']
        msg.color.r, msg.color.g, msg.color.b, msg.color.a = item['color']
        if 'points' in item:
            msg.points = [point_cls(x=p[0], y=p[1], z=p[2]) for p in item['points']]
        if 'colors' in item:
            msg.colors = [color_cls(r=c[0], g=c[1], b=c[2], a=c[3]) for c in item['colors']]
        msg.text = item.get('text', '')
        messages.append(msg)
    out.markers = messages
    return out


def _level(status: Any) -> int:
    level = status.level
    return level[0] if isinstance(level, (bytes, bytearray)) else int(level)


class SceneNode(Node):
    """Parameters -> scene geometry; state and diagnostics in, MarkerArray out."""

    def __init__(self, node_name: str = NODE_NAME) -> None:
        """Declare and check every parameter, then create the endpoints.

        Raises:
            ValueError: a parameter is invalid (the message names the key).
        """
        super().__init__(node_name, automatically_declare_parameters_from_overrides=True)
        # The settings dynamically typed, so that rate_hz:=10 is taken as well as 10.0; the
        # filter keys are declared when given (by the overrides), described as the filter's.
        declare_specs(self, SCENE_PARAMETERS, dynamic_typing=True, others=None)
        declare_specs(self, STATE_TYPE_PARAMETERS, given=FILTER_PARAMETERS)
        params = collect_parameters({name: parameter.value for name, parameter
                                     in self.get_parameters_by_prefix('').items()})
        self._params = params
        self.settings = logic.scene_settings(params)
        self.geometry = scene_geometry(params)
        self.frame_id = logic.marker_frame(self.settings.frame_id, self.geometry)
        self.state_type = self._state_type_parameter()
        self.state: np.ndarray | None = None
        self.h: dict[str, float] = {}
        self.status: tuple[int, str] | None = None
        self.points: np.ndarray | None = None
        """(m, 4) the latest good filter_info's binding_points, or None before one."""
        self._info: bytes | None = None
        self.published = 0
        self._changed = False
        self._clear = False
        self._throttle = LogThrottle(1.0)
        qos = QoSProfile(depth=10)
        self._state_type = get_message(conversions.STATE_MESSAGES[self.state_type])
        self._publisher = self.create_publisher(get_message(MARKER_ARRAY), 'scene_markers', qos)
        self.create_subscription(self._state_type, 'state', self._on_state, qos, raw=True)
        self._diagnostics_type = get_message(DIAGNOSTIC_ARRAY)
        self.create_subscription(self._diagnostics_type, 'diagnostics', self._on_diagnostics,
                                 qos, raw=True)
        self.create_subscription(get_message(FLOAT64_MULTIARRAY), 'filter_info',
                                 self._on_filter_info, qos, raw=True)
        self._obstacles_type = get_message(FLOAT64_MULTIARRAY)
        self.create_subscription(
            self._obstacles_type, 'obstacles', self._on_obstacles,
            QoSProfile(depth=1, history=HistoryPolicy.KEEP_LAST,
                       reliability=ReliabilityPolicy.RELIABLE,
                       durability=DurabilityPolicy.TRANSIENT_LOCAL), raw=True)
        self.create_timer(1.0 / self.settings.rate_hz, self._on_timer)
        self.get_logger().info(
            f'{self.geometry.system}: {len(self.geometry.obstacles)} obstacles, '
            f'{len(self.geometry.barrier_names)} barriers, frame {self.frame_id!r}')
        self._say_left_out()

    @property
    def _left_out(self) -> int:
        """How many obstacles of the scene are not drawn (``max_obstacles``)."""
        return max(0, len(self.geometry.obstacles) - self.settings.max_obstacles)

    def _say_left_out(self) -> None:
        """Once per obstacle set: how many of its obstacles are not drawn."""
        if self._left_out:
            count = len(self.geometry.obstacles)
            self.get_logger().info(logic.omitted_text(count - self._left_out, count))

    def _state_type_parameter(self) -> str:
        """The declared ``state_type``, checked against the system (ValueError naming it)."""
        state_type = read_parameters(
            MessageSettings, {'state_type': self.get_parameter('state_type').value}
        ).state_type
        if state_type == 'odometry':
            conversions.check_odometry_support(self.geometry.system)
        return str(state_type)

    def _on_state(self, data: bytes) -> None:
        try:
            msg = deserialize_message(data, self._state_type)
        except Exception as exc:  # any decoder error means "not a state sample"
            self._warn('state', f'undecodable state sample skipped: {type(exc).__name__}')
            return
        try:
            if self.state_type == 'odometry':
                # with sources, as the filter: a state in another frame than the points' is
                # not theirs to be drawn with
                sections = {'state': conversions.odometry_to_state(
                    msg, system=self.geometry.system,
                    frame_id=self.geometry.odom_frame_id or '')}
            else:
                sections = conversions.msg_to_sections(msg, default_label='state')
            self.state = state_from_sections(sections=sections, n_x=self.geometry.n_x)
        except ValueError as exc:
            self._warn('state', f'state skipped: {exc}')
            return
        self._changed = True

    def _on_diagnostics(self, data: bytes) -> None:
        try:
            msg = deserialize_message(data, self._diagnostics_type)
        except Exception as exc:  # any decoder error means "not a diagnostics sample"
            self._warn('diagnostics', f'undecodable diagnostics sample skipped: '
                       f'{type(exc).__name__}')
            return
        for status in msg.status:
            values = {kv.key: kv.value for kv in status.values}
            h = logic.barrier_values(values)
            if h or 'min_h' in values:  # the filter's status, with barriers or sensor rows only
                self.h, self.status = h, (_level(status), str(status.message))
                self._changed = True

    def _on_filter_info(self, data: bytes) -> None:
        """Keep the latest sample: it is read when the next array is made (at most rate_hz a
        second, however fast the filter answers)."""
        self._info = data
        self._changed = True

    def _read_info(self) -> None:
        """The latest filter_info's binding points, or a warning (the last good ones kept)."""
        data, self._info = self._info, None
        if data is None:
            return
        try:
            self.points = logic.info_binding_points(data)
        except Exception as exc:  # any failure means "not a filter_info sample we can draw"
            text = (str(exc) if isinstance(exc, ValueError)
                    else f'filter_info: {type(exc).__name__}')
            self._warn('filter_info', f'{" ".join(text.split())}; sample skipped, the last '
                                      'points stay drawn')

    def _on_obstacles(self, data: bytes) -> None:
        """A new obstacle set: the scene of the parameters with it, or an ERROR (old kept)."""
        try:
            msg = deserialize_message(data, self._obstacles_type)
            changes = obstacle_parameters(
                data=msg.data, data_offset=int(msg.layout.data_offset),
                dims=[(d.label, int(d.size), int(d.stride)) for d in msg.layout.dim])
            params = merged_parameters(current=self._params, changes=changes)
            geometry = scene_geometry(params)
        except Exception as exc:  # a bad message (or one that does not decode): keep the old
            text = str(exc) if isinstance(exc, ValueError) else type(exc).__name__
            self.get_logger().error(shown_reason(f'obstacles message refused, the obstacles '
                                                 f'drawn are unchanged: {text}'))
            return
        self._params, self.geometry = params, geometry
        self._changed = self._clear = True
        self._say_left_out()

    def _on_timer(self) -> None:
        if not self._changed:
            return
        self._changed = False
        self._read_info()
        markers = logic.scene_markers(
            geometry=self.geometry, state=self.state, h=self.h,
            frame_id=self.frame_id, caution=self.settings.caution_h,
            status=self.status, points=self.points,
            max_obstacles=self.settings.max_obstacles)
        # With obstacles left out, the ones drawn change as the robot moves: each array then
        # replaces the whole scene, so that none drawn before stays behind in the viewer.
        self._publisher.publish(marker_array(markers, stamp=self.get_clock().now().to_msg(),
                                             clear=self._clear or self._left_out > 0))
        self._clear = False
        self.published += 1

    def _warn(self, key: str, text: str) -> None:
        """Log ``text`` (one bounded line, :func:`shown_reason`), at most once a second per
        ``key``."""
        if self._throttle.should_log(key=key, now_ns=time.monotonic_ns()):
            self.get_logger().warning(shown_reason(text))


def main(args: Sequence[str] | None = None) -> int:
    """Run the node until Ctrl-C / SIGTERM. Returns 2 on invalid parameters."""
    return run_node(NODE_NAME, SceneNode, args, setup_errors=(ValueError,),
                    interface=INTERFACE)


if __name__ == '__main__':
    sys.exit(main())
