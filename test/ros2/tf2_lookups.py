"""Run under a real Jazzy: tf2_ros's Buffer answers the lookups of a JSON case file.

    python tf2_lookups.py CASES.json

CASES.json: a list of worlds, each {"static": [T...], "dynamic": [T...], "lookups": [[target,
source, time_ns]...]} with T = [parent, child, stamp_ns, [tx, ty, tz], [qx, qy, qz, qw]]; each
world in a buffer of its own. Prints one JSON line: per world, per lookup [[tx, ty, tz], [qx,
qy, qz, qw]] or the name of tf2's exception.
"""
import json
import sys

from geometry_msgs.msg import TransformStamped
from rclpy.duration import Duration
from rclpy.time import Time
import tf2_ros


def stamped(parent, child, stamp_ns, translation, rotation):
    t = TransformStamped()
    t.header.frame_id, t.child_frame_id = parent, child
    t.header.stamp.sec, t.header.stamp.nanosec = divmod(int(stamp_ns), 1_000_000_000)
    (t.transform.translation.x, t.transform.translation.y,
     t.transform.translation.z) = translation
    (t.transform.rotation.x, t.transform.rotation.y, t.transform.rotation.z,
     t.transform.rotation.w) = rotation
    return t


def answers(cases):
    buffer = tf2_ros.Buffer(cache_time=Duration(seconds=10))
    for item in cases['static']:
        buffer.set_transform_static(stamped(*item), 'oracle')
    for item in cases['dynamic']:
        buffer.set_transform(stamped(*item), 'oracle')
    out = []
    for target, source, time_ns in cases['lookups']:
        try:
            found = buffer.lookup_transform(target, source, Time(nanoseconds=int(time_ns)))
        except Exception as exc:  # noqa: BLE001 - tf2's exception type is the answer
            out.append(type(exc).__name__)
            continue
        tr, q = found.transform.translation, found.transform.rotation
        out.append([[tr.x, tr.y, tr.z], [q.x, q.y, q.z, q.w]])
    return out


def main(path):
    with open(path) as stream:
        worlds = json.load(stream)
    print(json.dumps([answers(world) for world in worlds]))


if __name__ == '__main__':
    main(sys.argv[1])
