"""``ros2 launch`` descriptions built from :mod:`rcbf_ros.launch.table` (ROS 2 install only).

Every ``launch/<name>.launch.py`` is three lines calling :func:`describe` with its name, so the
launch files, the table and ``rcbf_ros launch`` (which starts the same table without ROS) cannot
drift. ROS 2's launch packages are imported when a description is built, not at import time.
"""
from __future__ import annotations

import os
from typing import Any

from rcbf_ros.launch.table import (
    Argument,
    launch_setup,
    NodeEntry,
    PACKAGE,
    PARAMS_FILE_ARGUMENT,
    respawn_settings,
    substitute,
)


def describe(name: str) -> Any:
    """A ``LaunchDescription`` with one launch_ros ``Node`` per table entry of launch ``name``.

    All nodes read the ``params_file`` launch argument (default: the packaged
    ``config/<system>.yaml``); a node marked ``ends_launch`` shuts the launch down on exit; each
    node gets its table limit from SIGINT to SIGTERM (launch's ``sigterm_timeout``).

    A table entry's own parameters follow the params file as a dict, which launch_ros writes to
    a params file of its own under the node's name only when the name is fully specified, i.e.
    when the node has a namespace: hence ``namespace=''`` (the root, or the namespace pushed by
    an enclosing launch). Without it launch_ros writes the dict under ``/**``, which rcl files
    in the ``/**`` key the params file opened first, so the file's ``/<name>`` section would win
    (see :mod:`rcbf_ros.parameters.rules`).

    The launch's own arguments (:class:`rcbf_ros.launch.table.LaunchArgument`) are declared
    with their defaults, descriptions and choices; where an entry reads one
    (:class:`rcbf_ros.launch.table.Argument`), its ``LaunchConfiguration`` stands. In a list
    parameter each such item is a one-item list: launch_ros joins a list made only of
    substitutions into ONE string, and reads a list of lists as a list of strings.

    An entry that respawns on a launch argument (``respawn``, ``respawn_delay``) is built when
    the launch runs, in an ``OpaqueFunction``: Jazzy's ``ExecuteProcess`` takes
    ``respawn_delay`` as a float only. Both values are read with
    :func:`rcbf_ros.launch.table.respawn_settings`, as ``rcbf_ros launch`` reads them, so the
    two launchers accept the same texts and refuse the others with the same line.
    """
    from ament_index_python.packages import get_package_share_directory
    from launch.actions import DeclareLaunchArgument, OpaqueFunction, Shutdown
    from launch.substitutions import LaunchConfiguration
    from launch_ros.actions import Node

    from launch import LaunchDescription

    setup = launch_setup(name)
    default_params = os.path.join(get_package_share_directory(PACKAGE), 'config', setup.config)
    params_file = LaunchConfiguration(PARAMS_FILE_ARGUMENT)
    actions = [DeclareLaunchArgument(PARAMS_FILE_ARGUMENT, default_value=default_params,
                                     description='ROS 2 params file of every node')]
    for argument in setup.arguments:
        actions.append(DeclareLaunchArgument(
            argument.name, default_value=argument.default, description=argument.description,
            **({'choices': list(argument.choices)} if argument.choices else {})))

    def configuration(argument: Argument) -> Any:
        return LaunchConfiguration(argument.name)

    def parameter(value: Any) -> Any:
        if isinstance(value, (list, tuple)) and any(isinstance(v, Argument) for v in value):
            return [[substitute(item, configuration)] for item in value]
        return substitute(value, configuration)

    def node(entry: NodeEntry, respawn: bool, respawn_delay_s: float) -> Any:
        parameters: list[Any] = [params_file]
        if entry.parameters:
            parameters.append({key: parameter(value) for key, value in entry.parameters})
        return Node(
            package=PACKAGE, executable=entry.executable, name=entry.name, namespace='',
            output='screen', parameters=parameters,
            remappings=[(source, substitute(target, configuration))
                        for source, target in entry.remappings],
            sigterm_timeout=str(entry.sigint_timeout_s),
            on_exit=Shutdown(reason=f'{entry.name} exited') if entry.ends_launch else None,
            respawn=respawn, respawn_delay=respawn_delay_s)

    def node_when_launched(entry: NodeEntry) -> Any:
        def build(context: Any) -> list[Any]:
            return [node(entry, *respawn_settings(
                entry, lambda argument: configuration(argument).perform(context)))]
        return OpaqueFunction(function=build)

    for entry in setup.nodes:
        if isinstance(entry.respawn, Argument) or isinstance(entry.respawn_delay_s, Argument):
            actions.append(node_when_launched(entry))
        else:
            actions.append(node(entry, *respawn_settings(entry, str)))
    return LaunchDescription(actions)
