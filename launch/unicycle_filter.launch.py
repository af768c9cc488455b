"""Unicycle simulator + safety_filter + unsafe nominal controller + recorder (ros2 launch).

    ros2 launch rcbf_ros unicycle_filter.launch.py [params_file:=/path/to/unicycle.yaml]

The nodes, remaps and parameters come from ``rcbf_ros.launch_table`` (``unicycle_filter``), the
same table ``rcbf_ros_launch unicycle_filter`` starts without ROS, so the two cannot drift.
"""
# ruff takes the `launch` package for this folder (first-party); it is ROS 2's launch.
from __future__ import annotations  # noqa: I001

import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, Shutdown
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

from rcbf_ros.launch_table import launch_setup, PACKAGE

LAUNCH_NAME = 'unicycle_filter'


def generate_launch_description() -> LaunchDescription:
    """One launch_ros Node per table entry, all reading the ``params_file`` argument."""
    setup = launch_setup(LAUNCH_NAME)
    default_params = os.path.join(get_package_share_directory(PACKAGE), 'config', setup.config)
    params_file = LaunchConfiguration('params_file')
    actions = [DeclareLaunchArgument('params_file', default_value=default_params,
                                     description='ROS 2 params file of every node')]
    for entry in setup.nodes:
        parameters = [params_file]
        if entry.parameters:
            parameters.append(dict(entry.parameters))
        actions.append(Node(
            package=PACKAGE, executable=entry.executable, name=entry.name, output='screen',
            parameters=parameters, remappings=list(entry.remappings),
            on_exit=Shutdown(reason=f'{entry.name} exited') if entry.ends_launch else None))
    return LaunchDescription(actions)
