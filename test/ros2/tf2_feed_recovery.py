"""Run under a real Jazzy with rcbf_ros importable: the filter's tf2 feed
(rcbf_ros.ros.tf2_buffer.Tf2Feed) over tf2_ros's Buffer recovers from time going back, a
far-future stamp, a flood of samples and a flood of frames.

    python tf2_feed_recovery.py

Prints one JSON line: per scenario, what the feed said and what the lookup laser -> odom (and
base_link -> laser, the static link) answered after it.
"""
import json

from rclpy.duration import Duration
from tf2_lookups import stamped
import tf2_ros

from rcbf_ros.node_logic.tf_buffer import NoTransform
from rcbf_ros.ros.tf2_buffer import Tf2Feed, Tf2Lookup

S = 1_000_000_000
UNIT = (0.0, 0.0, 0.0, 1.0)


class Message:
    def __init__(self, *transforms):
        self.transforms = list(transforms)


def rig(**bounds):
    def new_buffer():
        return tf2_ros.Buffer(cache_time=Duration(seconds=10))

    def renew():
        lookup.buffer = new_buffer()
        return lookup.buffer

    lookup = Tf2Lookup(new_buffer())
    feed = Tf2Feed(lookup.buffer, dict.fromkeys(('messages', 'refused', 'transforms_refused'),
                                                0), renew=renew, **bounds)
    assert feed.take(Message(stamped('base_link', 'laser', 0, (0.1, 0.0, 0.0), UNIT)),
                     static=True, now_ns=S) == ''
    return feed, lookup


def odom(feed, stamp_ns, x, now_ns):
    return feed.take(Message(stamped('odom', 'base_link', stamp_ns, (x, 0.0, 0.0), UNIT)),
                     static=False, now_ns=now_ns)


def where(lookup, target, source, time_ns):
    found = lookup.lookup_transform(target, source, time_ns)
    return found.kind if isinstance(found, NoTransform) else found.translation[0]


def main():
    out = {}
    # ROS time goes back (a simulator restarted): tf2's dynamic data cleared, static kept
    feed, lookup = rig()
    assert odom(feed, 100 * S, 1.0, 100 * S) == ''
    out['jump'] = {'said': odom(feed, 5 * S, 2.0, 5 * S), 'clears': feed.clears,
                   'old': where(lookup, 'odom', 'base_link', 100 * S),
                   'new': where(lookup, 'odom', 'laser', 5 * S),
                   'static': where(lookup, 'base_link', 'laser', 0)}
    # a far-future stamp: refused, the next good one taken
    feed, lookup = rig()
    assert odom(feed, 10 * S, 1.0, 10 * S) == ''
    out['future'] = {'said': odom(feed, (2**31 - 1) * S, 9.0, 10 * S),
                     'next': odom(feed, 10 * S + S // 50, 1.5, 10 * S + S // 50),
                     'new': where(lookup, 'odom', 'laser', 10 * S + S // 50)}
    # joints flood the total bound, then stop: tf2 keeps their samples, the feed clears them
    feed, lookup = rig(max_total_samples=200)
    said = []
    for k in range(300):  # 30 s at 10 Hz, the joints for the first 10
        t = 10 * S + k * S // 10
        if k < 100:
            for j in range(5):
                feed.take(Message(stamped('base_link', f'joint_{j}', t, (0.0, 0.0, 0.0),
                                          UNIT)), static=False, now_ns=t)
        said.append(odom(feed, t, 2.0, t))
    out['flood'] = {'refused': sum(bool(why) for why in said), 'last': said[-1],
                    'clears': feed.clears, 'new': where(lookup, 'odom', 'laser', t)}
    # a flood of frame names: tf2 keeps every name; the feed renews its buffer
    feed, lookup = rig(max_frames=10)
    said = [feed.take(Message(stamped('base_link', f'f{k}', 5 * S, (0.0, 0.0, 0.0), UNIT)),
                      static=False, now_ns=5 * S) for k in range(50)]
    first = lookup.buffer
    later = 16 * S
    out['frames'] = {'refused': sum(bool(why) for why in said),
                     'next': odom(feed, later, 3.0, later), 'renewals': feed.renewals,
                     'renewed': lookup.buffer is not first and feed.buffer is lookup.buffer,
                     'new': where(lookup, 'odom', 'laser', later),
                     'gone': where(lookup, 'base_link', 'f0', 5 * S)}
    print(json.dumps(out))


if __name__ == '__main__':
    main()
