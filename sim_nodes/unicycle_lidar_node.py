"""The ``unicycle_lidar`` node: a simulated differential-drive robot with a 2-D lidar, on the
topics a real base and its driver publish.

Publishes ``scan`` (sensor_msgs/LaserScan in ``laser``, 360 beams at ``scan_rate_hz``),
``odom`` (nav_msgs/Odometry, odom -> base_link, from the wheel encoders: it drifts from the
true pose), ``/tf`` (odom -> base_link), ``/tf_static`` (base_link -> laser, once, transient
local) and ``world_markers`` (the world's true posts and walls, once, transient local: ground
truth for a viewer, which no node of the robot's would have); takes ``cmd_vel``
(geometry_msgs/Twist: linear.x, angular.z), holding the latest for ``cmd_timeout_s`` and
stopping after. The world and the base are
:mod:`sim_nodes.lidar_world`'s: the packaged ``obstacles.*`` posts in a walled arena (the
filter's layout, so a map and the scan agree), or a seeded random world (``world_seed`` >= 0).
Topics and parameters: :func:`unicycle_lidar_interface` (``unicycle_lidar --help``).
"""
from __future__ import annotations

from dataclasses import dataclass
import itertools
import math
import sys
from typing import Any, Mapping, Sequence

import numpy as np

from rcbf_ros.messages.tf import frame_name_refusal, quoted
from rcbf_ros.node_logic.interface import NodeInterface, parameter_specs, ParameterSpec, TopicSpec
from rcbf_ros.node_logic.scene import CUBE, CYLINDER, TEXT_VIEW_FACING
from rcbf_ros.parameters.reader import (
    PERIOD_LIMITS_S,
    RATE_LIMITS_HZ,
    read_parameters,
    setting,
)
from rcbf_ros.ros.node_main import run_node
from rcbf_ros.ros.runtime import DurabilityPolicy, get_message, Node, QoSProfile
from rcbf_ros.ros.scene_node import marker_array
from sim_nodes import lidar_world as lw
from sim_nodes.packaged import declare_with_packaged_defaults, packaged_interface

MAX_BEAMS = 100_000
"""The most beams a scan may have (the filter reads at most 200,000 points a message)."""


@dataclass(frozen=True)
class LidarRobotSettings:
    """The node's own parameters."""

    world_seed: int = setting(-1, minimum=-1, description='-1: the packaged obstacles.* posts '
                                                          'in a walled arena; >= 0: the '
                                                          'seeded random world')
    """Which world (module docstring)."""
    arena_half_size: float = setting(3.5, positive=True, maximum=100.0,
                                     description='world_seed -1: half the side of the walled '
                                                 'square arena (m)')
    """Half the arena's side, world_seed -1."""
    start: tuple[float, ...] = setting((-2.5, -2.5, 0.0), length=3, maximum=100.0,
                                       description='world_seed -1: the start pose x, y, yaw '
                                                   '(m, rad); odom starts there')
    """The start pose, world_seed -1."""
    rate_hz: float = setting(50.0, minimum=RATE_LIMITS_HZ[0], maximum=1000.0,
                             description='base steps and odometry per second')
    """Base steps (and Odometry, /tf) per second."""
    scan_rate_hz: float = setting(10.0, minimum=RATE_LIMITS_HZ[0], maximum=100.0,
                                  description='scans per second')
    """Scans per second (at most ``rate_hz``)."""
    beams: int = setting(360, minimum=8, maximum=MAX_BEAMS, description='beams per scan')
    """Beams over a full turn."""
    range_max: float = setting(8.0, positive=True, maximum=100.0,
                               description="the lidar's range (m): +inf beyond")
    """The lidar's range."""
    laser_mount: tuple[float, ...] = setting(
        (0.0, 0.0, 0.0), length=3, maximum=10.0,
        description='the laser frame on base_link: x, y, yaw (m, rad; /tf_static)')
    """The laser's pose on base_link."""
    cmd_timeout_s: float = setting(0.5, minimum=PERIOD_LIMITS_S[0], maximum=60.0,
                                   description='stop when the latest cmd_vel is older (s)')
    """How long a command holds."""
    noise_seed: int = setting(0, minimum=0, description="seed of the base's slip, odometry "
                                                        "and the lidar's noise")
    """Seed of the noise."""
    odom_frame_id: str = setting('odom', nonempty=True, description="the odometry's frame")
    """The Odometry's header.frame_id."""
    base_frame_id: str = setting('base_link', nonempty=True, description="the robot's frame")
    """The Odometry's child_frame_id."""
    laser_frame_id: str = setting('laser', nonempty=True, description="the scan's frame")
    """The LaserScan's header.frame_id."""
    wait_for_subscribers: tuple[str, ...] = setting(
        (), description='node names (the recorder) that must subscribe to odom, scan, /tf and '
                        'cmd_vel before the robot starts (recorded launches: a bag from the '
                        'first step)')
    """Nodes that hold the start until each subscribes to every topic of :data:`WAITED`."""


NODE_PARAMETERS: tuple[ParameterSpec, ...] = parameter_specs(LidarRobotSettings,
                                                             mark_read_only=False)
"""The node's own parameters."""

TOPICS: tuple[TopicSpec, ...] = (
    TopicSpec('scan', 'pub', 'sensor_msgs/msg/LaserScan',
              'the lidar in laser_frame_id; REP 117: +inf beyond range, NaN dropped beams',
              'best effort, keep last 5'),
    TopicSpec('odom', 'pub', 'nav_msgs/msg/Odometry',
              'odom -> base_link from the wheel encoders (drifts from the true pose)'),
    TopicSpec('/tf', 'pub', 'tf2_msgs/msg/TFMessage', 'odom -> base_link'),
    TopicSpec('/tf_static', 'pub', 'tf2_msgs/msg/TFMessage', 'base_link -> laser, once',
              'reliable, transient local, keep-last 1'),
    TopicSpec('world_markers', 'pub', 'visualization_msgs/msg/MarkerArray',
              "ground truth for a viewer: the world's true posts and walls in odom_frame_id "
              '(where odometry starts on the world), once', 'reliable, transient local, '
              'keep-last 1'),
    TopicSpec('cmd_vel', 'sub', 'geometry_msgs/msg/Twist',
              'linear.x (m/s), angular.z (rad/s); held cmd_timeout_s'),
)


def unicycle_lidar_interface(argv: Sequence[str] = ()) -> NodeInterface:
    """Topics and parameters of the node."""
    return packaged_interface(
        argv, node='unicycle_lidar', section='unicycle_lidar', topics=TOPICS,
        own=NODE_PARAMETERS,
        summary='A simulated differential-drive robot with a 2-D lidar: scan, odom and /tf out, '
                'cmd_vel in, as a real base and its driver have them.')


WAITED = ('odom', 'scan', '/tf', 'cmd_vel')
"""The topics (before remapping) each ``wait_for_subscribers`` node subscribes to before the
robot starts: what it publishes every step and the commands it takes."""


def waits_for(subscribed: Mapping[str, Mapping[str, bool]]) -> str:
    """What the start still waits for, in one line ('' once every named node subscribes to
    every topic): ``subscribed`` maps each ``wait_for_subscribers`` node to each resolved
    topic of :data:`WAITED` -> whether it holds a subscription there."""
    for name, topics in subscribed.items():
        for topic, held in topics.items():
            if not held:
                return f'{name} to subscribe to {topic}'
    return ''


def settings_from_params(params: Mapping[str, Any]) -> LidarRobotSettings:
    """The node's settings from flat parameters.

    Raises:
        ValueError: one line naming the bad key.
    """
    settings = read_parameters(LidarRobotSettings, params)
    if settings.scan_rate_hz > settings.rate_hz:
        raise ValueError(f'scan_rate_hz: {settings.scan_rate_hz:g} exceeds rate_hz '
                         f'{settings.rate_hz:g}')
    range_min = lw.Lidar.range_min
    if not settings.range_max > range_min:
        raise ValueError(f"range_max: {settings.range_max:g} m is not above the lidar's "
                         f'range_min {range_min:g} m (every beam would read -inf)')
    frames = {'odom_frame_id': settings.odom_frame_id,
              'base_frame_id': settings.base_frame_id,
              'laser_frame_id': settings.laser_frame_id}
    for key, frame in frames.items():
        why = frame_name_refusal(frame)
        if why:
            raise ValueError(f'{key}: {why}')
    for (other, first), (key, frame) in itertools.combinations(frames.items(), 2):
        if frame == first:
            raise ValueError(f'{key}: {quoted(frame)} is {other} too (the tf tree needs three '
                             'frames: a frame cannot be its own parent)')
    return settings


def build_world(settings: LidarRobotSettings, params: Mapping[str, Any]) -> lw.World:
    """The node's world: the seeded random one, or the packaged ``obstacles.x/.y/.radius``
    posts (none when absent) in a walled arena from ``start``.

    Raises:
        ValueError: naming the key of an unusable world.
    """
    if settings.world_seed >= 0:
        return lw.random_world(settings.world_seed)
    keys = ('obstacles.x', 'obstacles.y', 'obstacles.radius')
    columns = [np.asarray(params.get(key, []), dtype=np.float64).reshape(-1) for key in keys]
    if len({len(c) for c in columns}) != 1:
        raise ValueError(f'obstacles.x: {len(columns[0])} values, obstacles.y '
                         f'{len(columns[1])}, obstacles.radius {len(columns[2])}')
    for key, column in zip(keys, columns):
        bad = np.flatnonzero(~np.isfinite(column))
        if bad.size:
            raise ValueError(f'{key}: value {int(bad[0])} is {column[bad[0]]}, not finite')
    if (columns[2] <= 0).any():
        index = int(np.flatnonzero(columns[2] <= 0)[0])
        raise ValueError(f'obstacles.radius: value {index} is {columns[2][index]:g}, not > 0')
    circles = np.stack(columns, axis=1)
    half = settings.arena_half_size
    world = lw.World(half_size=half, circles=circles,
                     segments=np.array(lw._arena(half), dtype=np.float64),
                     start=np.array(settings.start, dtype=np.float64), goal=np.zeros(2),
                     kind='posts', seed=-1)
    if lw.clearance(world, world.start[:2])[0] <= lw.BaseModel().radius:
        raise ValueError(f"start: {list(settings.start)} is within the robot's radius of an "
                         'obstacle or outside the arena')
    if np.abs(world.start[:2]).max() >= half:
        raise ValueError(f'start: {list(settings.start)} is outside the arena of half size '
                         f'{half:g}')
    return world


class LidarRobot:
    """The simulated robot without middleware: steps, odometry, scans, the command held."""

    def __init__(self, world: lw.World, settings: LidarRobotSettings,
                 model: lw.BaseModel | None = None) -> None:
        self.world, self.settings = world, settings
        self.model = model or lw.BaseModel()
        self.lidar = lw.Lidar(beams=settings.beams, rate_hz=settings.scan_rate_hz,
                              range_max=settings.range_max, mount=tuple(settings.laser_mount),
                              frame_id=settings.laser_frame_id)
        self.state = lw.start_state(world)
        self.rng = np.random.default_rng(settings.noise_seed)
        self.dt = 1.0 / settings.rate_hz
        self.time = 0.0
        self.command = np.zeros(2)
        self.command_time = -math.inf
        self._next_scan = 0.0
        self.collided = False
        """Whether the true body touches a surface now."""

    def take_command(self, v: float, omega: float) -> str:
        """Hold (v, omega) from now on: '' when taken, else why not (a non-finite value; the
        base then stops)."""
        if not (math.isfinite(v) and math.isfinite(omega)):
            self.command, self.command_time = np.zeros(2), self.time
            return f'cmd_vel: not finite (linear.x {v}, angular.z {omega}); stopping'
        self.command, self.command_time = np.array([v, omega]), self.time
        return ''

    def step(self) -> None:
        """One base step with the held command (zero once it is older than cmd_timeout_s)."""
        fresh = self.time - self.command_time <= self.settings.cmd_timeout_s
        command = self.command if fresh else np.zeros(2)
        self.state = lw.step_base(self.state, command, self.dt, self.model, self.rng)
        self.time += self.dt
        gap = float(lw.clearance(self.world, self.state.pose[:2])[0]) - self.model.radius
        self.collided = gap < 0.0

    def scan_due(self) -> bool:
        """Whether a scan is due now (then the next one is scheduled)."""
        if self.time + 1e-9 < self._next_scan:
            return False
        self._next_scan += 1.0 / self.settings.scan_rate_hz
        return True

    def scan(self) -> np.ndarray:
        """One scan from the true pose: (beams,) float32 ranges (REP 117)."""
        return lw.scan_ranges(self.world, self.state.pose, self.lidar, self.rng)

    def odometry(self) -> tuple[np.ndarray, np.ndarray]:
        """The odometry's pose (x, y, yaw) and twist (v, omega: the encoders' wheels)."""
        return self.state.odom.copy(), self.state.wheels.copy()


GROUND_TRUTH = (0.60, 0.45, 0.30, 0.35)
"""Colour (r, g, b, a) of the world's true geometry: translucent, apart from the scene's."""
GROUND_TRUTH_HEIGHT = 0.5
"""Height (m) the true posts and walls are drawn with."""


def world_markers(world: lw.World, *, frame_id: str) -> list[dict[str, Any]]:
    """The world's true geometry as marker dicts (the fields of
    :func:`rcbf_ros.node_logic.scene.scene_markers`'s, ns ``ground_truth``): a cylinder per
    post, a box per wall (its centre line, ``wall_thickness`` thick) and a label saying what
    they are. ``frame_id`` is the odometry's frame: odometry starts on the world's start pose,
    so the world's coordinates are odom's until odometry drifts (the scan's points then slide
    off the true posts by the drift)."""
    height = GROUND_TRUTH_HEIGHT

    def marker(index: int, kind: int, position: Sequence[float], scale: Sequence[float],
               yaw: float = 0.0, text: str = '') -> dict[str, Any]:
        item = {'frame_id': frame_id, 'ns': 'ground_truth', 'id': index, 'type': kind,
                'position': tuple(float(v) for v in position),
                'orientation': yaw_quaternion(yaw),
                'scale': tuple(float(v) for v in scale), 'color': GROUND_TRUTH}
        if text:
            item['text'] = text
        return item

    out = [marker(i, CYLINDER, (x, y, height / 2), (2 * r, 2 * r, height))
           for i, (x, y, r) in enumerate(world.circles.tolist())]
    thickness = world.wall_thickness
    for x0, y0, x1, y1 in world.segments.tolist():
        length = math.hypot(x1 - x0, y1 - y0) + thickness
        out.append(marker(len(out), CUBE, ((x0 + x1) / 2, (y0 + y1) / 2, height / 2),
                          (length, thickness, height), yaw=math.atan2(y1 - y0, x1 - x0)))
    half = world.half_size
    out.append(marker(len(out), TEXT_VIEW_FACING, (-half, half + 0.3, height), (0.0, 0.0, 0.25),
                      text='ground truth (simulator): the true posts and walls'))
    return out


def yaw_quaternion(yaw: float) -> tuple[float, float, float, float]:
    """The quaternion x, y, z, w of a rotation by ``yaw`` about z."""
    return 0.0, 0.0, math.sin(yaw / 2.0), math.cos(yaw / 2.0)


def _transform(stamp: Any, parent: str, child: str, x: float, y: float, yaw: float) -> Any:
    msg = get_message('geometry_msgs/msg/TransformStamped')()
    msg.header.stamp, msg.header.frame_id, msg.child_frame_id = stamp, parent, child
    msg.transform.translation.x, msg.transform.translation.y = float(x), float(y)
    r = msg.transform.rotation
    r.x, r.y, r.z, r.w = yaw_quaternion(yaw)
    return msg


class UnicycleLidarNode(Node):
    """cmd_vel -> the simulated base -> odom, /tf, scan (module docstring)."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__('unicycle_lidar',
                         automatically_declare_parameters_from_overrides=True, **kwargs)
        params = declare_with_packaged_defaults(self, 'unicycle_lidar', own=NODE_PARAMETERS)
        settings = settings_from_params(params)
        self.settings = settings
        self.robot = LidarRobot(build_world(settings, params), settings)
        self.scan_publisher = self.create_publisher(
            get_message('sensor_msgs/msg/LaserScan'), 'scan', QoSProfile(depth=5))
        self.odom_publisher = self.create_publisher(
            get_message('nav_msgs/msg/Odometry'), 'odom', QoSProfile(depth=10))
        self.tf_publisher = self.create_publisher(
            get_message('tf2_msgs/msg/TFMessage'), '/tf', QoSProfile(depth=100))
        static = self.create_publisher(
            get_message('tf2_msgs/msg/TFMessage'), '/tf_static',
            QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL))
        commands = self.create_subscription(get_message('geometry_msgs/msg/Twist'), 'cmd_vel',
                                            self.on_cmd_vel, QoSProfile(depth=10))
        self._waited = (self.odom_publisher.topic_name, self.scan_publisher.topic_name,
                        self.tf_publisher.topic_name, commands.topic_name)
        """The resolved topics of :data:`WAITED`."""
        self.waiting_for = self._waits_for()
        """What the start waits for ('' once started)."""
        if self.waiting_for:
            self.get_logger().info(f'the robot waits for {self.waiting_for}')
        mx, my, myaw = settings.laser_mount
        tf_static = get_message('tf2_msgs/msg/TFMessage')()
        tf_static.transforms = [_transform(self.get_clock().now().to_msg(),
                                           settings.base_frame_id, settings.laser_frame_id,
                                           mx, my, myaw)]
        static.publish(tf_static)
        self._static = static  # kept: transient local serves late subscribers from it
        truth = self.create_publisher(
            get_message('visualization_msgs/msg/MarkerArray'), 'world_markers',
            QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL))
        truth.publish(marker_array(world_markers(self.robot.world,
                                                 frame_id=settings.odom_frame_id),
                                   stamp=self.get_clock().now().to_msg()))
        self._truth = truth  # kept, as _static
        self._touching = False
        self.create_timer(1.0 / settings.rate_hz, self.on_timer)
        world = self.robot.world
        self.get_logger().info(
            f'unicycle_lidar: {world.kind} world (seed {world.seed}), {len(world.circles)} '
            f'posts, {len(world.segments)} walls; {settings.beams} beams at '
            f'{settings.scan_rate_hz:g} Hz in {settings.laser_frame_id}')

    def on_cmd_vel(self, msg: Any) -> None:
        reason = self.robot.take_command(float(msg.linear.x), float(msg.angular.z))
        if reason:
            self.get_logger().error(reason)

    def _waits_for(self) -> str:
        """:func:`waits_for` on what discovery shows now."""
        if not self.settings.wait_for_subscribers:
            return ''
        subscriptions = {topic: {e.node_name for e in self.get_subscriptions_info_by_topic(topic)}
                         for topic in self._waited}
        return waits_for({name: {topic: name in subscriptions[topic] for topic in self._waited}
                          for name in self.settings.wait_for_subscribers})

    def on_timer(self) -> None:
        if self.waiting_for:  # the base holds still and says nothing until it is recorded
            waiting_for = self._waits_for()
            if waiting_for and waiting_for != self.waiting_for:
                self.get_logger().info(f'the robot waits for {waiting_for}')
            self.waiting_for = waiting_for
            if waiting_for:
                return
            self.get_logger().info('the robot starts: every wait_for_subscribers node listens')
        robot, settings = self.robot, self.settings
        robot.step()
        if robot.collided != self._touching:
            self._touching = robot.collided
            if robot.collided:
                self.get_logger().warning('the robot touches an obstacle (true pose)')
        stamp = self.get_clock().now().to_msg()
        pose, twist = robot.odometry()
        odom = get_message('nav_msgs/msg/Odometry')()
        odom.header.stamp, odom.header.frame_id = stamp, settings.odom_frame_id
        odom.child_frame_id = settings.base_frame_id
        odom.pose.pose.position.x, odom.pose.pose.position.y = float(pose[0]), float(pose[1])
        q = odom.pose.pose.orientation
        q.x, q.y, q.z, q.w = yaw_quaternion(float(pose[2]))
        odom.twist.twist.linear.x, odom.twist.twist.angular.z = float(twist[0]), float(twist[1])
        self.odom_publisher.publish(odom)
        tf = get_message('tf2_msgs/msg/TFMessage')()
        tf.transforms = [_transform(stamp, settings.odom_frame_id, settings.base_frame_id,
                                    *pose)]
        self.tf_publisher.publish(tf)
        if robot.scan_due():
            fields = lw.scan_fields(robot.scan(), robot.lidar, stamp_ns=0)
            scan = get_message('sensor_msgs/msg/LaserScan')()
            scan.header.stamp, scan.header.frame_id = stamp, fields['frame_id']
            for key in ('angle_min', 'angle_max', 'angle_increment', 'time_increment',
                        'scan_time', 'range_min', 'range_max'):
                setattr(scan, key, float(fields[key]))
            scan.ranges = fields['ranges']
            self.scan_publisher.publish(scan)


def main(args: Sequence[str] | None = None) -> int:
    """Console script ``unicycle_lidar``. Returns 2 on invalid parameters."""
    return run_node('unicycle_lidar', UnicycleLidarNode, args, setup_errors=(ValueError,),
                    interface=unicycle_lidar_interface)


if __name__ == '__main__':
    sys.exit(main())
