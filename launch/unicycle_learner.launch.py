"""Train SAC-RCBF on the Unicycle: simulator + safety_filter + learner + recorder.

    ros2 launch rcbf_ros unicycle_learner.launch.py [params_file:=/path/to/unicycle.yaml]

The nodes come from ``rcbf_ros.launch.table`` (``unicycle_learner``), the table ``rcbf_ros launch
unicycle_learner`` also starts without ROS.
"""
from rcbf_ros.launch.description import describe


def generate_launch_description():
    return describe('unicycle_learner')
