"""The safety filter alone, in front of an existing robot.

    ros2 launch rcbf_ros safety_filter.launch.py cmd_in:=/my_controller/cmd_vel \
        cmd_out:=/cmd_vel odom:=/odom [command_type:=twist_stamped] [params_file:=robot.yaml] \
        [respawn:=true respawn_delay:=1.0]

The filter reads the robot's nav_msgs/Odometry on ``odom`` and the controller's command on
``cmd_in`` and publishes the safe command alone, in the same type, on ``cmd_out`` (what it did
goes to ``filter_info`` and ``diagnostics``). The defaults are the names a stock ROS 2 robot
uses, so most robots need only ``cmd_in``: bases, their simulators and teleop take ``cmd_vel``,
odometry sources publish ``odom``, and ``cmd_vel_nav`` is the name Nav2's bringup gives its
controller's output. ``command_type``: twist (default), twist_stamped or array.
``params_file`` (default: the packaged ``config/unicycle.yaml``) holds the robot's model,
obstacles and limits. ``respawn:=true`` starts the filter again ``respawn_delay`` seconds
(default 1.0) after it dies (default: off; set the base's command timeout either way, since
nothing is published on ``cmd_out`` while the filter is down). The wiring comes from
``rcbf_ros.launch.table`` (``safety_filter``), the table ``rcbf_ros launch safety_filter
cmd_in:=...`` also starts without ROS.
"""
from rcbf_ros.launch.description import describe


def generate_launch_description():
    return describe('safety_filter')
