"""Demo: the drop-in safety filter between a simulated robot and a go-to-goal controller.

    ros2 launch rcbf_ros unicycle_robot.launch.py [cmd_in:=... cmd_out:=... odom:=...]

The simulator stands in for a robot (nav_msgs/Odometry on ``odom``, Twist velocity input on
``cmd_out``), the nominal controller drives straight at the goal (Twist on ``cmd_in``), and the
safety filter sits between them exactly as ``safety_filter.launch.py`` puts it in front of a
real robot, with the same arguments; the recorder writes every topic to MCAP. The nodes come
from ``rcbf_ros.launch.table`` (``unicycle_robot``), the table ``rcbf_ros launch
unicycle_robot`` also starts without ROS.
"""
from rcbf_ros.launch.description import describe


def generate_launch_description():
    return describe('unicycle_robot')
