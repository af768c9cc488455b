"""The ``simulator`` node: one of :mod:`rcbf_ros.envs` on topics, lock-step or real-time.

It stands in for a robot: publishes the state (and ``sim/step``, all of one plant step for the
learner) and applies the action it gets. Lock-step drops stale answers, so runs repeat exactly.
Topics and parameters: :func:`simulator_interface` (``simulator --help``); protocol and modes:
docs/NODES.md.
"""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass
import json
import math
import sys
import time
from typing import Any, Mapping, Sequence

import numpy as np

from rcbf_ros.envs import make_env
from rcbf_ros.messages import conversions
from rcbf_ros.messages.conversions import msg_to_sections, sections_to_msg
from rcbf_ros.messages.tf import frame_name_refusal, quoted
from rcbf_ros.node_logic.edges import MessageSettings, SIM_STEP_SECTIONS
from rcbf_ros.node_logic.interface import (
    COMMAND_TOPIC_TYPES,
    FLOAT64_MULTIARRAY,
    NodeInterface,
    parameter_specs,
    ParameterSpec,
    STATE_TOPIC_TYPES,
    TopicSpec,
)
from rcbf_ros.parameters.reader import (
    PERIOD_LIMITS_S,
    RATE_LIMITS_HZ,
    read_parameters,
    setting,
)
from rcbf_ros.ros.node_main import run_node, spin_once
from rcbf_ros.ros.runtime import DurabilityPolicy, get_message, Node, QoSProfile, rclpy
from sim_nodes.packaged import (
    declare_with_packaged_defaults,
    packaged_interface,
)

MODES = ('lockstep', 'realtime')
"""``mode``: step when the action arrives, or at ``rate_hz``."""


@dataclass(frozen=True)
class SimulatorSettings(MessageSettings):
    """The simulator's own parameters (besides ``system`` and its env's)."""

    mode: str = setting('lockstep', choices=MODES,
                        description='lockstep (step when the action for the pending state '
                                    'arrives) or realtime (step at rate_hz, holding the last '
                                    'action)')
    """lockstep or realtime (module docstring)."""
    rate_hz: float = setting(50.0, minimum=RATE_LIMITS_HZ[0], maximum=RATE_LIMITS_HZ[1],
                             description='steps per second in realtime mode')
    """Steps per second in realtime mode."""
    seed: int = setting(0, description="the first reset's seed (later episodes continue its "
                                       'generator)')
    """The first reset's seed."""
    max_episodes: int = setting(0, minimum=0,
                                description='episodes to run, then the node exits (0: forever)')
    """Episodes to run (0: forever)."""
    action_timeout_s: float = setting(
        1.0, minimum=PERIOD_LIMITS_S[0], maximum=PERIOD_LIMITS_S[1],
        description='lockstep: publish the pending state again after this '
                                        'long without an action (s)')
    """Lock-step: publish the pending state again after this long without an action."""
    frame_id: str = setting('map', description="state_type odometry: the Odometry's "
                                               "header.frame_id (the obstacles' frame)")
    """The Odometry's header.frame_id."""
    child_frame_id: str = setting('base_link', description="state_type odometry: the "
                                                           "Odometry's child_frame_id (the "
                                                           "robot's frame)")
    """The Odometry's child_frame_id."""
    wait_for_publishers: tuple[str, ...] = setting(
        (), description='the first episode waits until each of these topics has a publisher '
                        'that listens to the simulator (launches: cmd_safe and cmd_proposed)')
    """Topics whose publishers the first episode waits for."""
    wait_for_subscribers: tuple[str, ...] = setting(
        (), description='the first episode waits until each of these nodes subscribes to '
                        'every topic the simulator publishes and every wait_for_publishers '
                        'topic (recorded launches: the recorder)')
    """Nodes whose subscription to ``state`` the first episode waits for."""

    def __post_init__(self) -> None:
        """With state_type odometry, refuse frame ids the tf and state readers do not take
        (:func:`frame_name_refusal`) or one frame as both, in one line naming the key."""
        if self.state_type != 'odometry':
            return
        for key in ('frame_id', 'child_frame_id'):
            why = frame_name_refusal(getattr(self, key))
            if why:
                raise ValueError(f'{key}: {why}')
        if self.frame_id == self.child_frame_id:
            raise ValueError(f'child_frame_id: {quoted(self.child_frame_id)} is frame_id too')


NODE_PARAMETERS: tuple[ParameterSpec, ...] = parameter_specs(SimulatorSettings,
                                                             mark_read_only=False)
"""The simulator's own parameters (declared before the packaged ones, which cannot replace
them)."""


TOPICS: tuple[TopicSpec, ...] = (
    TopicSpec('state', 'pub', STATE_TOPIC_TYPES,
              'state_type array: section `state`, n_x values in the state layout; odometry: '
              'pose [x, y, yaw], twist [v, omega], stamped with the simulation clock'),
    TopicSpec('cmd_safe', 'sub', COMMAND_TOPIC_TYPES,
              'the action: array: first section u (n_u), optional section `state` it answers '
              "(the filter's `filter_info`; launches remap cmd_safe to it); twist(_stamped): "
              'u in twist_fields, the stamp of the state it answers'),
    TopicSpec('sim/step', 'pub', FLOAT64_MULTIARRAY,
              "the simulator's per-step sections: " + ', '.join(SIM_STEP_SECTIONS)),
    TopicSpec('observation', 'pub', FLOAT64_MULTIARRAY,
              "section `observation`: the policy's input"),
    TopicSpec('h_true', 'pub', FLOAT64_MULTIARRAY,
              'section `h_true`: true signed clearances (names in the episode start event)'),
    TopicSpec('reward', 'pub', 'std_msgs/msg/Float64', 'reward of the last step'),
    TopicSpec('episode', 'pub', 'std_msgs/msg/String',
              'one JSON object per episode start and end',
              'reliable, transient local, keep-last 10'),
)

EPISODE_HISTORY_DEPTH = 10
"""Episode events kept for late subscribers (``episode`` is transient local): the run's first
start event and those of the next few episodes."""


def simulator_interface(argv: Sequence[str] = ()) -> NodeInterface:
    """Topics and parameters of the simulator for the ``system`` of a command line."""
    return packaged_interface(
        argv, node='simulator', section='simulator', topics=TOPICS, own=NODE_PARAMETERS,
        summary='One of the simulated systems (rcbf_ros.envs) on topics, lock-step or '
                'real-time.')


def action_from_msg(msg: Any) -> tuple[np.ndarray, np.ndarray | None]:
    """(u, answered state or None) from a Float64MultiArray.

    u is the first section (the whole data when unlabelled); the answered state is the section
    labelled ``state`` when present (and not the first).
    """
    sections = msg_to_sections(msg, default_label='u')
    if not sections:
        raise ValueError('cmd_safe: empty message')
    labels = list(sections)
    answered = sections['state'] if 'state' in labels[1:] else None
    return sections[labels[0]], answered


def message_settings(params: Mapping[str, Any], *, system: str, n_u: int) -> MessageSettings:
    """``state_type``, ``command_type`` and ``twist_fields``, checked.

    Raises:
        ValueError: naming the key (an unknown type, odometry for a system it cannot hold,
            twist fields that are not n_u known distinct names).
    """
    settings = read_parameters(MessageSettings, params)
    if settings.state_type == 'odometry':
        conversions.check_odometry_support(system)
    settings.check_inputs(n_u=n_u, system=system)
    return settings


def episode_event(event: str, **fields: Any) -> str:
    """One ``episode`` JSON object (numpy scalars converted, NaN as null)."""
    def plain(value: Any) -> Any:
        if isinstance(value, (np.floating, float)):
            return None if not math.isfinite(float(value)) else float(value)
        if isinstance(value, (np.integer,)):
            return int(value)
        if isinstance(value, (np.bool_,)):
            return bool(value)
        if isinstance(value, (list, tuple)):
            return [plain(v) for v in value]
        return value
    return json.dumps({'event': event, **{k: plain(v) for k, v in fields.items()}})


def loop_waits_for(*, state_topic: str, matched: Mapping[str, int],
                   readers: Mapping[str, Sequence[bytes]],
                   loop_publishers: Mapping[str, Sequence[bytes]],
                   listeners: Mapping[str, Mapping[str, Sequence[bytes]]] | None = None) -> str:
    """What the first episode still waits for, in one line; ``''`` once the loop is up.

    Args:
        state_topic: the simulator's resolved ``state`` topic.
        matched: each of the simulator's topics -> subscriptions its publisher has matched.
        readers: each of the simulator's topics -> the participants (GUID prefixes, one per
            process) of the subscriptions that discovery shows on it.
        loop_publishers: each ``wait_for_publishers`` topic -> the participants of its
            publishers in the graph.
        listeners: each ``wait_for_subscribers`` node name -> ``state_topic``, each of the
            simulator's other topics and each ``wait_for_publishers`` topic -> the participants
            of that node's subscriptions there (a recorder must not miss the first states,
            proposals, answers or true barrier values).

    The loop is up when ``state`` has a matched subscription, every ``wait_for_publishers``
    topic has a publisher, every such publisher's process subscribes to one of the simulator's
    topics, and the simulator's publishers have matched at least as many subscriptions on each
    topic as those processes hold there. Each ``wait_for_subscribers`` node joins the loop once
    it subscribes to every topic ``listeners`` names for it; other processes
    (a ``ros2 topic echo``) neither hold the start back nor count.
    """
    if matched.get(state_topic, 0) < 1:
        return f'a subscriber on {state_topic}'
    loop = set()
    for name, topics in (listeners or {}).items():
        for topic, owners in topics.items():
            if not owners:
                return f'{name} to subscribe to {topic}'
            loop.update(owners)
    for topic, owners in loop_publishers.items():
        if not owners:
            return f'a publisher on {topic}'
        loop.update(owners)
    listening = {owner for owners in readers.values() for owner in owners}
    for topic, owners in loop_publishers.items():
        if not set(owners) <= listening:
            return f'the publisher on {topic} to subscribe to the simulator'
    for topic, owners in readers.items():
        needed = sum(1 for owner in owners if owner in loop)
        if matched.get(topic, 0) < needed:
            return f'{needed} subscription(s) on {topic} to match ({matched.get(topic, 0)} so far)'
    return ''


def _participant(endpoint: Any) -> bytes:
    """The GUID prefix (participant, one per process) of a discovered endpoint."""
    return bytes(list(endpoint.endpoint_gid)[:12])


class SimulatorNode(Node):
    """Wraps one env; see the module docstring."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__('simulator', automatically_declare_parameters_from_overrides=True,
                         **kwargs)
        params = declare_with_packaged_defaults(self, 'simulator', own=NODE_PARAMETERS)
        wait_for = params.get('wait_for_publishers', [])
        if not isinstance(wait_for, list) or not all(isinstance(t, str) and t for t in wait_for):
            raise ValueError(f'wait_for_publishers: expected a list of topic names, got '
                             f'{wait_for!r}')
        settings = read_parameters(SimulatorSettings, params)
        self.system = str(params['system'])
        self.mode, self.rate_hz, self.seed = settings.mode, settings.rate_hz, settings.seed
        self.max_episodes = settings.max_episodes
        self.action_timeout_s = settings.action_timeout_s
        self.wait_for_publishers = [self.resolve_topic_name(t)
                                    for t in settings.wait_for_publishers]
        self.wait_for_subscribers = list(settings.wait_for_subscribers)
        self.env = make_env(self.system, params)
        self.n_u = self.env.nominal_system.n_u
        messages = message_settings(params, system=self.system, n_u=self.n_u)
        self.state_type, self.command_type = messages.state_type, messages.command_type
        self.twist_fields = messages.twist_fields
        self.frame_id, self.child_frame_id = settings.frame_id, settings.child_frame_id
        self.dt_ns = int(round(float(self.env.dt) * 1e9))
        self.clock_ns = 0
        """Simulation clock: the stamp of the latest state (``dt`` per new state)."""
        self.earlier_stamps: deque[int] = deque(maxlen=1000)
        """Stamps of recent states before the latest one (a TwistStamped answering one of them
        is late)."""

        array = get_message('std_msgs/msg/Float64MultiArray')
        qos = QoSProfile(depth=10)
        self.state_pub = self.create_publisher(
            get_message(conversions.STATE_MESSAGES[self.state_type]), 'state', qos)
        self.observation_pub = self.create_publisher(array, 'observation', qos)
        self.h_true_pub = self.create_publisher(array, 'h_true', qos)
        self.reward_pub = self.create_publisher(get_message('std_msgs/msg/Float64'), 'reward', qos)
        self.episode_pub = self.create_publisher(
            get_message('std_msgs/msg/String'), 'episode',
            QoSProfile(depth=EPISODE_HISTORY_DEPTH, durability=DurabilityPolicy.TRANSIENT_LOCAL))
        self.step_pub = self.create_publisher(array, 'sim/step', qos)
        self.create_subscription(
            get_message(conversions.COMMAND_MESSAGES[self.command_type]), 'cmd_safe',
            self.on_action, qos)

        self.done = False
        self.episode = 0
        self.episode_return = 0.0
        self.violations = 0
        self.observation = np.zeros(0)
        self.info: dict[str, Any] = {}
        self.last_action = np.zeros(self.n_u)
        self.applied = np.zeros(self.n_u)
        self.awaiting_action = False
        self.last_state_time = 0.0
        self.started = False
        self.waiting_for = ''
        if self.mode == 'lockstep':
            self.create_timer(min(0.05, self.action_timeout_s / 4.0), self.on_watchdog)
        else:
            self.create_timer(1.0 / self.rate_hz, self.on_tick)
        self.get_logger().info(
            f'{self.system} simulator, {self.mode} mode, dt = {self.env.dt} s, '
            f'n_x = {self.env.nominal_system.n_x}, n_u = {self.n_u}, seed = {self.seed}, '
            f'state_type {self.state_type}, command_type {self.command_type}')

    # -- episodes --------------------------------------------------------------------------

    def start_episode(self) -> None:
        self.observation, self.info = self.env.reset(seed=self.seed if self.episode == 0
                                                     else None)
        self.episode += 1
        self.episode_return = 0.0
        self.violations = int(self.info['violation'])
        self.applied = np.zeros(self.n_u)
        self.started = True
        self._advance_clock()
        self.publish_string(episode_event(
            'start', episode=self.episode, system=self.system, seed=self.seed,
            layout_seed=self.info.get('layout_seed'), h_true_names=self.env.h_true_names,
            n_x=int(self.info['state'].size), n_u=self.n_u))
        self.publish_state()

    def end_episode(self, terminated: bool, truncated: bool) -> None:
        self.publish_string(episode_event(
            'end', episode=self.episode, **{'return': self.episode_return},
            steps=self.env.steps, violations=self.violations,
            goal_reached=bool(self.info['goal_reached']), terminated=terminated,
            truncated=truncated))
        self.get_logger().info(
            f'episode {self.episode}: return {self.episode_return:.3f}, {self.env.steps} '
            f'steps, {self.violations} violations, goal {self.info["goal_reached"]}')
        if self.max_episodes and self.episode >= self.max_episodes:
            self.done = True
            self.awaiting_action = False
        else:
            self.start_episode()

    # -- stepping --------------------------------------------------------------------------

    def apply(self, u: np.ndarray) -> None:
        self.applied = self.env.saturate(np.asarray(u, dtype=np.float64))
        self.observation, reward, terminated, truncated, self.info = self.env.step(u)
        self._advance_clock()
        self.episode_return += reward
        self.violations += int(self.info['violation'])
        msg = get_message('std_msgs/msg/Float64')()
        msg.data = float(reward)
        self.reward_pub.publish(msg)
        self.publish_state(reward=reward, terminated=terminated, truncated=truncated)
        if terminated or truncated:
            self.end_episode(terminated, truncated)

    def _advance_clock(self) -> None:
        """A new state: the next stamp of the simulation clock."""
        if self.clock_ns:
            self.earlier_stamps.append(self.clock_ns)
        self.clock_ns += self.dt_ns

    def state_message(self) -> Any:
        """The ``state`` message of the current state (``state_type``)."""
        if self.state_type == 'odometry':
            return conversions.state_to_odometry(
                self.info['state'], system=self.system, stamp_ns=self.clock_ns,
                frame_id=self.frame_id, child_frame_id=self.child_frame_id,
                command=self.applied)
        return sections_to_msg({'state': self.info['state']})

    def publish_state(self, *, reward: float = 0.0, terminated: bool = False,
                      truncated: bool = False) -> None:
        self.state_pub.publish(self.state_message())
        self.observation_pub.publish(sections_to_msg({'observation': self.observation}))
        self.h_true_pub.publish(sections_to_msg({'h_true': self.info['h_true']}))
        self.step_pub.publish(sections_to_msg({
            'state': self.info['state'], 'observation': self.observation, 'reward': [reward],
            'action': self.applied,
            'terminated': [float(terminated)], 'truncated': [float(truncated)],
            'violation': [float(self.info['violation'])],
            'goal_reached': [float(self.info['goal_reached'])],
            'episode': [float(self.episode)], 'step': [float(self.env.steps)]}))
        self.last_state_time = time.monotonic()
        self.awaiting_action = self.mode == 'lockstep' and not self.done

    def publish_string(self, text: str) -> None:
        msg = get_message('std_msgs/msg/String')()
        msg.data = text
        self.episode_pub.publish(msg)

    # -- callbacks ---------------------------------------------------------------------------

    def action(self, msg: Any) -> tuple[np.ndarray, bool]:
        """(u, whether it answers an earlier state than the pending one) of a ``cmd_safe``.

        Raises:
            ValueError: naming ``cmd_safe`` (wrong length, NaN or inf, an empty array).
        """
        stale = False
        if self.command_type == 'array':
            u, answered = action_from_msg(msg)
            stale = answered is not None and not np.array_equal(answered,
                                                                self.info.get('state'))
        elif self.command_type == 'twist_stamped':
            u = conversions.twist_stamped_to_array(msg, self.twist_fields)
            stamp = conversions.stamp_ns(msg.header)
            stale = stamp != self.clock_ns and stamp in self.earlier_stamps
        else:
            u = conversions.twist_to_array(msg, self.twist_fields)
        if u.size != self.n_u:
            raise ValueError(f'cmd_safe: expected {self.n_u} values in the first section, '
                             f'got {u.size}')
        if not np.all(np.isfinite(u)):
            raise ValueError('cmd_safe: contains NaN or inf')
        return u, stale

    def on_action(self, msg: Any) -> None:
        try:
            u, stale = self.action(msg)
        except ValueError as exc:
            self.get_logger().error(f'{exc}; action ignored')
            return
        if self.mode == 'lockstep' and stale:
            self.get_logger().debug('cmd_safe answers another state than the pending one; '
                                    'dropped as stale')
            return
        self.last_action = u
        if self.mode == 'lockstep' and self.awaiting_action and not self.done:
            self.awaiting_action = False
            self.apply(u)

    def _running(self) -> bool:
        """Whether an episode is under way; starts the first one once the loop is up.

        False after the last episode and until then.
        """
        if self.done:
            return False
        if not self.started:
            waiting_for = self._loop_waits_for()
            if not waiting_for:
                self.start_episode()
            elif waiting_for != self.waiting_for:
                self.get_logger().info(f'first episode waits for {waiting_for}')
            self.waiting_for = waiting_for
            return False
        return True

    def _loop_waits_for(self) -> str:
        """:func:`loop_waits_for` on what discovery shows now (graph queries only when needed)."""
        publishers = (self.state_pub, self.observation_pub, self.h_true_pub, self.reward_pub,
                      self.episode_pub, self.step_pub)
        matched = {p.topic_name: p.get_subscription_count() for p in publishers}
        state_topic = self.state_pub.topic_name
        if matched[state_topic] < 1 or not (self.wait_for_publishers
                                            or self.wait_for_subscribers):
            return loop_waits_for(state_topic=state_topic, matched=matched, readers={},
                                  loop_publishers={})
        loop_publishers = {topic: [_participant(e)
                                   for e in self.get_publishers_info_by_topic(topic)]
                           for topic in self.wait_for_publishers}
        subscriptions = {topic: self.get_subscriptions_info_by_topic(topic)
                         for topic in (*matched, *self.wait_for_publishers)}
        readers = {topic: [_participant(e) for e in subscriptions[topic]] for topic in matched}
        # a named listener (a recorder) holds the start until it has every topic of the loop
        # and every one the simulator publishes: a run recorded from its first step
        listeners = {name: {topic: [_participant(e) for e in subscriptions[topic]
                                    if e.node_name == name]
                            for topic in dict.fromkeys((state_topic, *self.wait_for_publishers,
                                                        *matched))}
                     for name in self.wait_for_subscribers}
        return loop_waits_for(state_topic=state_topic, matched=matched, readers=readers,
                              loop_publishers=loop_publishers, listeners=listeners)

    def on_watchdog(self) -> None:
        if not self._running():
            return
        if self.awaiting_action and (time.monotonic() - self.last_state_time
                                     > self.action_timeout_s):
            self.get_logger().warning(
                f'no cmd_safe within {self.action_timeout_s} s of the state of step '
                f'{self.env.steps}; publishing it again')
            self.publish_state()

    def on_tick(self) -> None:
        if self._running():
            self.apply(self.last_action)


def spin_until_done(node: Any, linger_s: float = 0.5) -> None:
    """Spin until the node is done (or shutdown), then briefly more so last samples go out."""
    while rclpy.ok() and not node.done:
        spin_once(node, timeout_sec=0.1)
    deadline = time.monotonic() + linger_s
    while rclpy.ok() and time.monotonic() < deadline:
        spin_once(node, timeout_sec=0.05)


def main(args: Sequence[str] | None = None) -> int:
    """Console script ``simulator``. Returns 2 on invalid parameters."""
    return run_node('simulator', SimulatorNode, args, run=spin_until_done,
                    setup_errors=(ValueError,), interface=simulator_interface)


if __name__ == '__main__':
    sys.exit(main())
