"""Which nodes a launch starts, with which remaps: ONE table for ``ros2 launch`` and our launcher.

``launch/<name>.launch.py`` (for a ROS 2 install) and ``rcbf_ros launch <name>``
(``rcbf_ros.launch.local``, for machines without ROS) both read ``LAUNCHES``, so the two cannot
drift; launch arguments and respawn settings are declared here for both. Pure data and string
building: no ROS, no processes.

The wiring, the arguments and respawn: docs/NODES.md#launches-one-table
"""
from __future__ import annotations

from dataclasses import dataclass, replace
import math
from typing import Any, Callable, Mapping, Sequence

import yaml

from rcbf_ros.messages import systems
from rcbf_ros.parameters import bounded_yaml

PACKAGE = 'rcbf_ros'
PARAMS_FILE_ARGUMENT = 'params_file'
"""The launch argument every launch takes: the params file of every node (default: the
packaged ``config/<LaunchSetup.config>``)."""
MAX_TIMEOUT_S = 3600.0
"""The longest escalation timeout (SIGINT to SIGTERM, SIGTERM to SIGKILL) a launch takes: a
child that ignores its signals is still stopped within the hour; an infinite timeout would
leave it running for good."""


@dataclass(frozen=True)
class Argument:
    """Where a table entry's remap target or parameter value is a launch argument's value."""

    name: str
    """The :class:`LaunchArgument` it reads."""


@dataclass(frozen=True)
class LaunchArgument:
    """A launch argument (``name:=value``) of a launch."""

    name: str
    """Its name on the command line."""
    default: str
    """Its value when not given."""
    description: str
    """One line for ``--show-args`` (and ros2 launch's)."""
    choices: tuple[str, ...] = ()
    """The values it may take (empty: any)."""

    def __post_init__(self) -> None:
        if self.name == PARAMS_FILE_ARGUMENT:
            raise ValueError(f'{self.name}: every launch declares it already')
        if self.choices and self.default not in self.choices:
            raise ValueError(f'{self.name}: default {self.default!r} is not one of '
                             f'{list(self.choices)}')


@dataclass(frozen=True)
class NodeEntry:
    """One node of a launch."""

    name: str
    """Node name; also its section in the params file (``/<name>: ros__parameters``)."""
    executable: str
    """console_scripts name (``ros2 run rcbf_ros <executable>``)."""
    module: str
    """Python module with ``main()`` run by the local launcher (``python -m <module>``)."""
    remappings: tuple[tuple[str, str | Argument], ...] = ()
    """Topic remaps (from, to) applied on top of the node's own names; ``to`` may be a launch
    argument's value."""
    parameters: tuple[tuple[str, Any], ...] = ()
    """Parameter overrides that win over the params file (see :func:`ros_arguments` and
    :func:`rcbf_ros.launch.description.describe` for how each launcher makes them win). A value
    (or an item of a list value) may be an :class:`Argument`, typed from its text as YAML, as
    launch_ros types a substitution."""
    required: bool = True
    """A failure of this node (non-zero exit, or not stopping when asked) fails the launch."""
    ends_launch: bool = False
    """When this node exits, every other node is stopped (launch's ``on_exit=Shutdown()``)."""
    sigint_timeout_s: float = 5.0
    """Seconds the node gets to stop after SIGINT before it is sent SIGTERM (launch's
    ``sigterm_timeout``): what its exit work needs, with room for a loaded machine."""
    respawn: bool | Argument = False
    """Start the node again whenever it exits while the launch runs (launch_ros ``respawn``);
    may be a launch argument's value, read by :func:`launch_bool`."""
    respawn_delay_s: float | Argument = 0.0
    """Seconds from its exit to its new start (launch_ros ``respawn_delay``); may be a launch
    argument's value, read by :func:`respawn_delay`."""

    def __post_init__(self) -> None:
        if not 0 < self.sigint_timeout_s <= MAX_TIMEOUT_S:
            raise ValueError(f'{self.name}: sigint_timeout_s must be > 0 and <= '
                             f'{MAX_TIMEOUT_S:g}, '
                             f'got {self.sigint_timeout_s}')
        if not isinstance(self.respawn, (bool, Argument)):
            raise ValueError(f'{self.name}: respawn must be a bool or an Argument, '
                             f'got {self.respawn!r}')
        if not isinstance(self.respawn_delay_s, Argument):
            respawn_delay(f'{self.name}: respawn_delay_s', str(self.respawn_delay_s))


@dataclass(frozen=True)
class LaunchSetup:
    """A launch: nodes in start order sharing one params file, and the arguments they read.

    ``launch/<name>.launch.py`` turns it into launch_ros actions
    (:func:`rcbf_ros.launch.description.describe`), ``rcbf_ros launch <name>`` into processes
    (:func:`rcbf_ros.launch.local.child_commands`).
    """

    name: str
    """Launch name: ``launch/<name>.launch.py`` and ``rcbf_ros launch <name>``."""
    config: str
    """Params file name in ``config/`` (``ros__parameters`` per node, ``/**`` shared)."""
    nodes: tuple[NodeEntry, ...]
    """Nodes in start order."""
    description: str = ''
    """One line for ``--help``."""
    arguments: tuple[LaunchArgument, ...] = ()
    """Its launch arguments besides ``params_file``."""

    def __post_init__(self) -> None:
        names = [argument.name for argument in self.arguments]
        if len(set(names)) != len(names):
            raise ValueError(f'{self.name}: launch arguments declared twice: {names}')
        for entry in self.nodes:
            for used in entry_arguments(entry):
                if used not in names:
                    raise ValueError(f'{self.name}: node {entry.name} reads launch argument '
                                     f'{used!r}, which the launch does not declare ({names})')

    def node(self, name: str) -> NodeEntry:
        """The entry named ``name`` (KeyError naming the known ones otherwise)."""
        for entry in self.nodes:
            if entry.name == name:
                return entry
        raise KeyError(f'{self.name}: no node {name!r} (nodes: {[n.name for n in self.nodes]})')


def substitute(value: Any, resolve: Callable[[Argument], Any]) -> Any:
    """``value`` with every :class:`Argument` in it (itself, or items of a list or tuple)
    replaced by ``resolve(argument)``."""
    if isinstance(value, Argument):
        return resolve(value)
    if isinstance(value, (list, tuple)):
        return type(value)(substitute(item, resolve) for item in value)
    return value


def entry_arguments(entry: NodeEntry) -> list[str]:
    """The names of the launch arguments ``entry`` reads, in order of appearance."""
    found: list[str] = []

    def note(argument: Argument) -> Argument:
        found.append(argument.name)
        return argument

    substitute([target for _, target in entry.remappings], note)
    substitute([value for _, value in entry.parameters], note)
    substitute([entry.respawn, entry.respawn_delay_s], note)
    return list(dict.fromkeys(found))


def launch_bool(what: str, text: str) -> bool:
    """A launch argument's text as a bool, as launch coerces one (``respawn``): ``1`` and
    ``0``, or what YAML reads as a bool (``true``, ``False``, ...).

    Raises:
        ValueError: one line naming ``what`` and the text.
    """
    parsed = _BOOL_WORDS.get(text)
    if parsed is None:
        shown = text if len(text) <= 40 else text[:37] + '...'
        raise ValueError(f'{what}:={shown!r}: expected true or false')
    return parsed


_BOOL_WORDS: dict[str, bool] = {
    '1': True, '0': False,
    **{word: True for base in ('true', 'yes', 'on')
       for word in (base, base.capitalize(), base.upper())},
    **{word: False for base in ('false', 'no', 'off')
       for word in (base, base.capitalize(), base.upper())},
}
"""The texts YAML 1.1 (PyYAML) reads as a bool, and launch's ``1`` / ``0``: looked up, not
parsed, so that no text can cost more than a dictionary look-up."""


def respawn_delay(what: str, text: str) -> float:
    """A respawn delay's text as seconds: a finite number >= 0.

    Raises:
        ValueError: one line naming ``what`` and the text.
    """
    try:
        seconds = float(text)
    except ValueError:
        seconds = math.nan
    if not (math.isfinite(seconds) and seconds >= 0.0):
        raise ValueError(f'{what}:={text!r}: expected seconds >= 0')
    return seconds


def respawn_settings(entry: NodeEntry, text_of: Callable[[Argument], str]) -> tuple[bool, float]:
    """``(respawn, respawn_delay_s)`` of ``entry``, its launch arguments read through
    ``text_of`` (the argument's text) with :func:`launch_bool` and :func:`respawn_delay`.

    Raises:
        ValueError: one line naming the launch argument whose text is no such value.
    """
    respawn, delay = entry.respawn, entry.respawn_delay_s
    if isinstance(respawn, Argument):
        respawn = launch_bool(f'launch argument {respawn.name}', text_of(respawn))
    if isinstance(delay, Argument):
        delay = respawn_delay(f'launch argument {delay.name}', text_of(delay))
    return bool(respawn), float(delay)


def parse_launch_arguments(texts: Sequence[str]) -> dict[str, str]:
    """``name:=value`` texts (as ``ros2 launch`` takes them after the launch file) -> dict.

    Raises:
        ValueError: naming a text that is not ``name:=value`` with a non-empty name.
    """
    values: dict[str, str] = {}
    for text in texts:
        name, sep, value = text.partition(':=')
        if not sep or not name:
            raise ValueError(f'launch argument {text!r}: expected name:=value')
        values[name] = value
    return values


def argument_values(setup: LaunchSetup, given: Mapping[str, str]) -> dict[str, str]:
    """Every launch argument of ``setup`` (not ``params_file``): ``given`` over the defaults.

    Raises:
        ValueError: one line naming the arguments ``setup`` does not declare, or a value
            outside an argument's choices.
    """
    declared = {argument.name: argument for argument in setup.arguments}
    unknown = sorted(set(given) - set(declared) - {PARAMS_FILE_ARGUMENT})
    if unknown:
        raise ValueError(f'{setup.name}: unknown launch argument(s) {", ".join(unknown)} '
                         f'(arguments: {", ".join([*declared, PARAMS_FILE_ARGUMENT])})')
    values = {name: given.get(name, argument.default) for name, argument in declared.items()}
    for name, argument in declared.items():
        if argument.choices and values[name] not in argument.choices:
            raise ValueError(f'{setup.name}: launch argument {name}:={values[name]!r} is not '
                             f'one of {", ".join(argument.choices)}')
    return values


def typed_value(text: str) -> Any:
    """A launch argument's text as a parameter value, typed as launch_ros types a
    substitution's result (YAML; ``''`` stays the empty string; other YAML stays text)."""
    if text == '':
        return ''
    try:
        value = bounded_yaml.safe_load(text, source='launch argument')
    except yaml.YAMLError:  # not YAML, or past a limit (bounded_yaml): the text itself
        return text
    return value if isinstance(value, (bool, int, float, str, list)) else text


def resolve_entry(entry: NodeEntry, values: Mapping[str, str]) -> NodeEntry:
    """``entry`` with its launch arguments replaced by ``values`` (see :func:`argument_values`):
    remap targets as text, parameters typed (:func:`typed_value`), respawn settings read
    (:func:`respawn_settings`).

    Raises:
        ValueError: one line naming a respawn argument whose value is no such setting.
    """
    remappings = tuple((source, substitute(target, lambda a: values[a.name]))
                       for source, target in entry.remappings)
    parameters = tuple((key, substitute(value, lambda a: typed_value(values[a.name])))
                       for key, value in entry.parameters)
    respawn, delay = respawn_settings(entry, lambda a: values[a.name])
    return replace(entry, remappings=remappings, parameters=parameters, respawn=respawn,
                   respawn_delay_s=delay)


SIMULATOR = NodeEntry(name='simulator', executable='simulator',
                      module='sim_nodes.simulator_node', ends_launch=True,
                      remappings=(('cmd_safe', 'filter_info'),))
SAFETY_FILTER = NodeEntry(name='safety_filter', executable='safety_filter',
                          module='rcbf_ros.ros.safety_filter_node')
RECORDER = NodeEntry(name='recorder', executable='recorder', module='rcbf_ros.ros.recorder_node',
                     sigint_timeout_s=10.0)
SCENE = NodeEntry(name='scene_markers', executable='scene_markers',
                  module='rcbf_ros.ros.scene_node', required=False)
"""The entries the launches share; each closed loop adds the node that proposes actions.

The recorder is required: a launch asked to record that cannot (the bag directory exists, is
read-only, ...) stops with a failure instead of running unrecorded (``--without recorder`` runs
without one). It gets longer to stop than the others because closing writes the bag's summary.
"""


def _closed_loop(system: str, kind: str, description: str, proposer: NodeEntry,
                 simulator: NodeEntry = SIMULATOR) -> LaunchSetup:
    """simulator -> <proposer> --cmd_proposed--> safety_filter --filter_info--> simulator,
    recorded.

    Nodes meet on their own relative topic names; the one remap gives the simulator the
    filter's ``filter_info`` as its action: the command ``u`` with the ``state`` it answers, so
    that lock-step drops a late answer to a state published again (``cmd_safe`` carries the
    command alone). The simulator starts the first episode once the filter and the proposer
    listen to it (its ``cmd_safe``, remapped, is the filter's ``filter_info``).
    """
    simulator = replace(simulator, parameters=(
        *simulator.parameters, ('wait_for_publishers', ['cmd_safe', 'cmd_proposed']),
        ('wait_for_subscribers', [RECORDER.name])))
    return LaunchSetup(name=f'{system}_{kind}', config=f'{system}.yaml',
                       description=description,
                       nodes=(simulator, SAFETY_FILTER, proposer, SCENE, RECORDER))


def _filter_loop(system: str) -> LaunchSetup:
    """The deliberately unsafe nominal controller behind the filter."""
    return _closed_loop(
        system, 'filter',
        f'{system} simulator driven by the deliberately unsafe nominal controller through the '
        'safety filter, recorded to MCAP',
        NodeEntry(name='nominal_controller', executable='nominal_controller',
                  module='sim_nodes.nominal_controller_node'))


def _learner_loop(system: str) -> LaunchSetup:
    """SAC-RCBF training as separate processes (paper Fig. 1 / Algorithm 1)::

        simulator --sim/step--> learner --cmd_proposed (u_RL, GP mean/std, state)--> filter
            ^                                                                          |
            +------------------------- filter_info (u*, ..., state) -----------------+

    The learner ends the launch; the simulator waits longer for actions, because GP refits
    and checkpoints pause the learner for a second or two. Stopped early, the learner still
    writes its checkpoint, policy and reward curve, which grow with the replay buffer: it gets
    30 s for that.
    """
    return _closed_loop(
        system, 'learner',
        f'train SAC-RCBF on {system}: simulator + safety_filter + learner + recorder; ends '
        'when the learner has run its episodes',
        NodeEntry(name='learner', executable='learner', module='rcbf_ros.ros.learner_node',
                  parameters=(('system', system),), ends_launch=True, sigint_timeout_s=30.0),
        simulator=replace(SIMULATOR, ends_launch=False,
                          parameters=(('action_timeout_s', 10.0),)))


def _policy_loop(system: str) -> LaunchSetup:
    """A trained policy behind the safety filter, no learner (deployment-like)."""
    return _closed_loop(
        system, 'policy',
        f'run a trained {system} policy (-p policy:policy_path:=.../policy.pt) behind the '
        'safety filter, recorded',
        NodeEntry(name='policy', executable='policy', module='rcbf_ros.ros.policy_node'))


RESPAWN_ARGUMENTS = (
    LaunchArgument('respawn', 'false',
                   'start the filter again when it dies: true or false (launch_ros respawn)'),
    LaunchArgument('respawn_delay', '1.0',
                   "seconds from the filter's exit to its new start, with respawn:=true"),
)
"""The drop-in filter's respawn, with launch_ros's names, off by default.

Off, as launch_ros's ``Node`` and Nav2's ``use_respawn`` have it: a filter that dies stops the
robot's commands (a base with a command timeout halts) and it stays stopped until someone
looks, instead of driving again on its own after a fault that may come back. On, a dead filter
is back after ``respawn_delay`` plus its start-up; the delay keeps a filter that exits at once
(parameters it refuses) to one start, and one line of why, a second.
"""

ROBOT_ARGUMENTS = (
    LaunchArgument('cmd_in', 'cmd_vel_nav',
                   "the controller's command the filter takes (command_type)"),
    LaunchArgument('cmd_out', 'cmd_vel', "the robot's velocity input: the safe command"),
    LaunchArgument('odom', 'odom', "the robot's nav_msgs/Odometry (the state)"),
    LaunchArgument('command_type', 'twist', 'type of cmd_in and cmd_out',
                   choices=('twist', 'twist_stamped', 'array')),
    *RESPAWN_ARGUMENTS,
)
"""The arguments of the drop-in filter.

The defaults follow common ROS 2 names so that a stock robot needs few of them: bases, their
simulators and teleop take ``cmd_vel`` and odometry sources publish ``odom``; ``cmd_vel_nav``
is what Nav2's bringup names its controller's output. Any other controller: ``cmd_in:=`` its
output topic. ``respawn`` and ``respawn_delay``: :data:`RESPAWN_ARGUMENTS`.
"""

DROP_IN_FILTER = replace(
    SAFETY_FILTER,
    remappings=(('state', Argument('odom')), ('cmd_proposed', Argument('cmd_in')),
                ('cmd_safe', Argument('cmd_out'))),
    parameters=(('state_type', 'odometry'), ('command_type', Argument('command_type')),
                ('refilter_on_state', True)),
    respawn=Argument('respawn'), respawn_delay_s=Argument('respawn_delay'))
"""The safety filter in front of a robot: odometry in, the controller's command in, the safe
command out in the same type, respawned on ``respawn:=true``; every odometry message filters
the command in force again (``refilter_on_state``: a base holds the last command it got, which
must stay safe while the robot moves and the controller is slow or quiet). The one wiring both
robot launches share."""


ROBOT_CONTROLLER = NodeEntry(
    name='nominal_controller', executable='nominal_controller',
    module='sim_nodes.nominal_controller_node',
    remappings=(('state', Argument('odom')), ('cmd_proposed', Argument('cmd_in'))),
    parameters=(('state_type', 'odometry'), ('command_type', Argument('command_type'))))
"""The demos' go-to-goal controller, blind to obstacles, as a robot's controller is wired: the
robot's odometry in, its command on ``cmd_in`` (the drop-in filter's input)."""


def _drop_in_filter() -> LaunchSetup:
    """Only the safety filter, between a robot's controller and its velocity input."""
    return LaunchSetup(
        name='safety_filter', config='unicycle.yaml', arguments=ROBOT_ARGUMENTS,
        description='the safety filter alone in front of a robot: odom + cmd_in -> cmd_out',
        nodes=(DROP_IN_FILTER,))


def _unicycle_robot() -> LaunchSetup:
    """The drop-in filter in front of a simulated robot, wired as a real one would be::

        simulator --odom--> nominal_controller --cmd_in--> safety_filter --cmd_out--> simulator
                   (odom)-------------------------------------^

    The simulator stands in for the robot: Odometry on ``odom``, velocity input ``cmd_out``
    (lock-step: it steps when a command arrives, so runs do not depend on the machine's load).
    The go-to-goal controller drives straight at the goal through the obstacles; the filter
    steers it around. The first episode waits until the filter and the controller listen.
    """
    robot = replace(
        SIMULATOR, remappings=(('state', Argument('odom')), ('cmd_safe', Argument('cmd_out'))),
        parameters=(('state_type', 'odometry'), ('command_type', Argument('command_type')),
                    ('wait_for_publishers', ['cmd_safe', Argument('cmd_in')]),
                    ('wait_for_subscribers', [RECORDER.name])))
    return LaunchSetup(
        name='unicycle_robot', config='unicycle.yaml', arguments=ROBOT_ARGUMENTS,
        description='demo: a simulated unicycle robot (odom, cmd_out) and a go-to-goal '
        'controller (cmd_in) with the drop-in safety filter between them, recorded',
        nodes=(robot, lockstep(DROP_IN_FILTER), ROBOT_CONTROLLER, RECORDER))


ROBOT_SCENE = replace(SCENE, remappings=(('state', Argument('odom')),),
                      parameters=(('state_type', 'odometry'),))
"""The scene markers beside the drop-in filter: the robot's odometry as the state, the filter's
``filter_info`` and ``diagnostics`` on their own names."""


LIDAR_ARGUMENTS = (
    *(argument for argument in ROBOT_ARGUMENTS if argument.name in ('cmd_in', 'cmd_out', 'odom')),
    LaunchArgument('command_type', 'twist', 'type of cmd_in and cmd_out (the base takes a '
                   'Twist)', choices=('twist',)),
    *RESPAWN_ARGUMENTS,
)
"""The drop-in filter's arguments with the command a Twist: the lidar robot takes no other."""


def _unicycle_lidar() -> LaunchSetup:
    """The drop-in filter on a laser scan in front of a simulated lidar robot::

        unicycle_lidar --odom--> nominal_controller --cmd_in--> safety_filter --cmd_out--+
              ^   --odom, scan, /tf, /tf_static-----------------------^ |                |
              |   --odom--> scene_markers <--filter_info, diagnostics--+                 |
              +----------------------------------- cmd_vel ------------------------------+

    The robot (:mod:`sim_nodes.unicycle_lidar_node`) runs in real time, as a base does: it
    holds the latest command, and the filter answers every Odometry (``refilter_on_state``).
    The go-to-goal controller is blind to the obstacles; the filter sees them only through the
    scan, in the laser's frame, placed through tf. The world, the laser's mount and the
    filter's sources, footprint and input limits: ``config/unicycle_lidar.yaml``. The scene
    markers draw, in ``odom`` (the filter's state frame), the robot, its footprint, the scan
    points closest to binding and the active rows; the robot node publishes the world's true
    posts and walls beside them (``world_markers``).

    The robot starts once the recorder subscribes to its topics (``wait_for_subscribers``),
    so that the bag holds its first steps and the filter's first answers.
    """
    robot = NodeEntry(
        name='unicycle_lidar', executable='unicycle_lidar',
        module='sim_nodes.unicycle_lidar_node',
        remappings=(('odom', Argument('odom')), ('cmd_vel', Argument('cmd_out'))),
        parameters=(('wait_for_subscribers', [RECORDER.name]),))  # recorded from the start
    return LaunchSetup(
        name='unicycle_lidar', config='unicycle_lidar.yaml', arguments=LIDAR_ARGUMENTS,
        description='demo: a simulated lidar robot (scan, odom, /tf; cmd_out) and a blind '
        'go-to-goal controller (cmd_in) with the drop-in filter on the scan, recorded',
        nodes=(robot, DROP_IN_FILTER, ROBOT_CONTROLLER, ROBOT_SCENE, RECORDER))


def lockstep(entry: NodeEntry) -> NodeEntry:
    """``entry`` answering proposals only (``refilter_on_state`` false): in front of a
    lock-step simulator, which steps on any command while it waits for one, an answer per
    state besides the answer per proposal would step it on the previous proposal's command."""
    return replace(entry, parameters=tuple(
        (key, False if key == 'refilter_on_state' else value) for key, value in entry.parameters))


CLOSED_LOOPS: tuple[LaunchSetup, ...] = tuple(
    make(system) for make in (_filter_loop, _learner_loop, _policy_loop)
    for system in systems.system_names())
"""The launches of :func:`_closed_loop`: the simulator takes the filter's ``filter_info``."""
ROBOT_LAUNCHES: tuple[LaunchSetup, ...] = (_drop_in_filter(), _unicycle_robot(),
                                           _unicycle_lidar())
"""The drop-in filter, alone and in the demos: the robot takes ``cmd_safe`` (``cmd_out``)."""
LAUNCHES: dict[str, LaunchSetup] = {setup.name: setup
                                    for setup in (*ROBOT_LAUNCHES, *CLOSED_LOOPS)}


def launch_setup(name: str) -> LaunchSetup:
    """The launch called ``name``.

    Raises:
        ValueError: naming the unknown launch and listing the known ones.
    """
    if name not in LAUNCHES:
        raise ValueError(f'launch: unknown launch {name!r}; known: {sorted(LAUNCHES)}')
    return LAUNCHES[name]


def format_parameter(value: Any) -> str:
    """A parameter value as ``-p name:=<text>`` takes it (YAML scalar or flow list)."""
    if isinstance(value, bool):
        return 'true' if value else 'false'
    if isinstance(value, (list, tuple)):
        return '[' + ', '.join(format_parameter(v) for v in value) + ']'
    if isinstance(value, str):
        return "'" + value.replace("'", "''") + "'"
    return repr(value)


def ros_arguments(entry: NodeEntry, *, params_file: str,
                  overrides: Mapping[str, Any] | None = None) -> list[str]:
    """The ``--ros-args`` part of a node's command line (local launcher).

    ``-r __node:=<name>`` names the node so that its params-file section applies; then the
    params file, the entry's remaps, its parameters and finally ``overrides`` (which win).

    The parameters are written ``-p <name>:<key>:=<value>``, AFTER the params file: rcl files
    them under the node key ``<name>``, which appears after the file's ``/**`` and
    ``/<name>`` sections and so wins over both (a bare ``-p key:=value`` goes to ``/**`` and
    would lose to the file's ``/<name>`` section; see :mod:`rcbf_ros.parameters.rules`).

    Raises:
        ValueError: ``entry`` still reads launch arguments (:func:`resolve_entry` first).
    """
    if entry_arguments(entry):
        raise ValueError(f'{entry.name}: launch arguments {entry_arguments(entry)} are not '
                         'resolved (resolve_entry)')
    args = ['--ros-args', '-r', f'__node:={entry.name}', '--params-file', params_file]
    for source, target in entry.remappings:
        args += ['-r', f'{source}:={target}']
    for key, value in (*entry.parameters, *(overrides or {}).items()):
        args += ['-p', f'{entry.name}:{key}:={format_parameter(value)}']
    return args
