"""Run by the ros2 tier under a real Jazzy: an rclpy node ``/oracle/jazzy_talker`` with a
std_msgs/String publisher on ``chatter``, spinning until SIGINT."""
import rclpy
from rclpy.node import Node
from rclpy_spin import spin_until_stopped
from std_msgs.msg import String

rclpy.init()
node = Node('jazzy_talker', namespace='/oracle')
node.create_publisher(String, 'chatter', 10)
spin_until_stopped(node)
