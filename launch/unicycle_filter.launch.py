"""Unicycle simulator + safety_filter + unsafe nominal controller + recorder.

    ros2 launch rcbf_ros unicycle_filter.launch.py [params_file:=/path/to/unicycle.yaml]

The nodes come from ``rcbf_ros.launch.table`` (``unicycle_filter``), the table ``rcbf_ros launch
unicycle_filter`` also starts without ROS.
"""
from rcbf_ros.launch.description import describe


def generate_launch_description():
    return describe('unicycle_filter')
