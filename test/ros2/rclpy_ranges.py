"""Run by the ros2 tier under a real Jazzy: rclpy's serialized sensor_msgs/Range readings.

Prints a JSON list of [reading, field_of_view, hex of serialize_message(Range)] for the
readings of ``READINGS`` (in frame ``sonar``, stamp 12 s 345 ns, min_range 0.02, max_range 4).
Uses nothing of rcbf_ros.
"""
import json
import math

from rclpy.serialization import serialize_message
from sensor_msgs.msg import Range

READINGS = [(1.5, 0.5), (-math.inf, 0.5), (math.inf, 0.5), (math.nan, 0.5), (2.0, 2 * math.pi),
            (0.7, 0.0)]
out = []
for reading, field_of_view in READINGS:
    msg = Range()
    msg.header.frame_id = 'sonar'
    msg.header.stamp.sec, msg.header.stamp.nanosec = 12, 345
    msg.radiation_type = Range.ULTRASOUND
    msg.field_of_view, msg.min_range, msg.max_range = field_of_view, 0.02, 4.0
    msg.range = reading
    out.append([str(reading), field_of_view, serialize_message(msg).hex()])
print(json.dumps(out))
