"""Which nodes a launch starts, with which remaps: ONE table for ``ros2 launch`` and our launcher.

``launch/<name>.launch.py`` (launch_ros ``Node`` actions, for a ROS 2 install) and
``rcbf_ros_launch <name>`` (:mod:`rcbf_ros.launch_local`, separate ``python -m`` processes, for
machines without ROS) both read :data:`LAUNCHES`, so the two cannot drift. Pure data and string
building: no ROS, no processes.

Wiring of ``<system>_filter`` (the nodes' own relative names meet; a namespace moves the whole
graph)::

    simulator --state--> nominal_controller --cmd_proposed (u, state)--> safety_filter
        ^                                                                      |
        +------------------- filter_info (u, u_rl, u_s, ..., state) ----------+
                             (cmd_safe: the command u alone, for a robot)
    scene_markers: state + diagnostics -> scene_markers (MarkerArray)
    recorder: every topic -> MCAP
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any, Mapping

PACKAGE = 'rcbf_ros'


@dataclass(frozen=True)
class NodeEntry:
    """One node of a launch."""

    name: str
    """Node name; also its section in the params file (``/<name>: ros__parameters``)."""
    executable: str
    """console_scripts name (``ros2 run rcbf_ros <executable>``)."""
    module: str
    """Python module with ``main()`` run by the local launcher (``python -m <module>``)."""
    remappings: tuple[tuple[str, str], ...] = ()
    """Topic remaps (from, to) applied on top of the node's own names."""
    parameters: tuple[tuple[str, Any], ...] = ()
    """Parameter overrides that win over the params file (see :func:`ros_arguments` and
    :func:`rcbf_ros.launch_description.describe` for how each launcher makes them win)."""
    required: bool = True
    """A failure of this node (non-zero exit, or not stopping when asked) fails the launch."""
    ends_launch: bool = False
    """When this node exits, every other node is stopped (launch's ``on_exit=Shutdown()``)."""
    sigint_timeout_s: float = 5.0
    """Seconds the node gets to stop after SIGINT before it is sent SIGTERM (launch's
    ``sigterm_timeout``): what its exit work needs, with room for a loaded machine."""

    def __post_init__(self) -> None:
        if not self.sigint_timeout_s > 0:
            raise ValueError(f'{self.name}: sigint_timeout_s must be > 0, '
                             f'got {self.sigint_timeout_s}')


@dataclass(frozen=True)
class LaunchSetup:
    """A set of nodes sharing one params file."""

    name: str
    """Launch name: ``launch/<name>.launch.py`` and ``rcbf_ros_launch <name>``."""
    config: str
    """Params file name in ``config/`` (``ros__parameters`` per node, ``/**`` shared)."""
    nodes: tuple[NodeEntry, ...]
    """Nodes in start order."""
    description: str = ''
    """One line for ``--help``."""

    def node(self, name: str) -> NodeEntry:
        """The entry named ``name`` (KeyError naming the known ones otherwise)."""
        for entry in self.nodes:
            if entry.name == name:
                return entry
        raise KeyError(f'{self.name}: no node {name!r} (nodes: {[n.name for n in self.nodes]})')


SIMULATOR = NodeEntry(name='simulator', executable='simulator',
                      module='sim_nodes.simulator_node', ends_launch=True,
                      remappings=(('cmd_safe', 'filter_info'),))
SAFETY_FILTER = NodeEntry(name='safety_filter', executable='safety_filter',
                          module='rcbf_ros.ros.safety_filter_node')
RECORDER = NodeEntry(name='recorder', executable='recorder', module='rcbf_ros.ros.recorder_node',
                     sigint_timeout_s=10.0)
SCENE = NodeEntry(name='scene_markers', executable='scene_markers',
                  module='rcbf_ros.ros.scene_node', required=False)
"""The entries every launch shares; each launch adds the node that proposes actions.

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
        *simulator.parameters, ('wait_for_publishers', ['cmd_safe', 'cmd_proposed'])))
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


LAUNCHES: dict[str, LaunchSetup] = {
    setup.name: setup for setup in (
        _filter_loop('unicycle'), _filter_loop('pvtol'), _filter_loop('car_following'),
        _learner_loop('unicycle'), _learner_loop('pvtol'), _learner_loop('car_following'),
        _policy_loop('unicycle'), _policy_loop('pvtol'), _policy_loop('car_following'))
}


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
    would lose to the file's ``/<name>`` section; see :mod:`rcbf_ros.params`).
    """
    args = ['--ros-args', '-r', f'__node:={entry.name}', '--params-file', params_file]
    for source, target in entry.remappings:
        args += ['-r', f'{source}:={target}']
    for key, value in (*entry.parameters, *(overrides or {}).items()):
        args += ['-p', f'{entry.name}:{key}:={format_parameter(value)}']
    return args
