"""Demo: the drop-in safety filter on a laser scan, in front of a simulated lidar robot.

    ros2 launch rcbf_ros unicycle_lidar.launch.py [cmd_in:=... cmd_out:=... odom:=...]

The ``unicycle_lidar`` node stands in for a base and its lidar driver (LaserScan on ``scan``
in frame ``laser``, Odometry on ``odom``, ``/tf`` odom -> base_link, ``/tf_static``
base_link -> laser; Twist velocity input on ``cmd_out``), the nominal controller drives
straight at the goal (Twist on ``cmd_in``), and the safety filter sits between them as
``safety_filter.launch.py`` puts it in front of a real robot, its obstacles the scan's points
placed through tf (``config/unicycle_lidar.yaml``); ``scene_markers`` draws the robot, its
footprint, the scan points that bind and the active rows in ``odom``; the recorder writes
every topic to MCAP.
The nodes come from ``rcbf_ros.launch.table`` (``unicycle_lidar``), the table ``rcbf_ros
launch unicycle_lidar`` also starts without ROS.
"""
from rcbf_ros.launch.description import describe


def generate_launch_description():
    return describe('unicycle_lidar')
