"""Run under a real Jazzy with rcbf_ros importable: the filter's tf2 lookup
(rcbf_ros.ros.tf2_buffer.Tf2Lookup) over tf2_ros's Buffer answers a JSON case file.

    python tf2_held_lookups.py CASES.json

CASES.json: as tf2_lookups.py's, each lookup [target, source, time_ns, tolerance_ns]. Prints
one JSON line: per world, per lookup [[tx, ty, tz], [qx, qy, qz, qw]] or [kind, reason].
"""
import json
import sys

from rclpy.duration import Duration
from tf2_lookups import stamped
import tf2_ros

from rcbf_ros.node_logic.tf_buffer import NoTransform
from rcbf_ros.ros.tf2_buffer import Tf2Lookup


def answers(cases):
    buffer = tf2_ros.Buffer(cache_time=Duration(seconds=10))
    for item in cases['static']:
        buffer.set_transform_static(stamped(*item), 'oracle')
    for item in cases['dynamic']:
        buffer.set_transform(stamped(*item), 'oracle')
    lookup = Tf2Lookup(buffer)
    out = []
    for target, source, time_ns, tolerance_ns in cases['lookups']:
        found = lookup.lookup_transform(target, source, time_ns, tolerance_ns=tolerance_ns)
        if isinstance(found, NoTransform):
            out.append([found.kind, found.reason])
        else:
            out.append([list(found.translation), list(found.rotation)])
    return out


def main(path):
    with open(path) as stream:
        worlds = json.load(stream)
    print(json.dumps([answers(world) for world in worlds]))


if __name__ == '__main__':
    main(sys.argv[1])
