"""No message kills the safety_filter node: a fuzz barrage over real Cyclone DDS (loopback).

The node runs as its own process with config/unicycle.yaml. A probe in this process publishes
raw CDR payloads on ``cmd_proposed`` and ``state`` through the runtime's writers (a publisher
takes serialized bytes as rclpy's does): random bytes, bit-flipped valid samples, truncated and
extended samples, labels that are not UTF-8 or are very long, huge sequence length fields, and
other types' payloads under the array type. A second participant publishes other message types
(Twist, String) under the same topic names. The node has a LaserScan source (``front``) and a
PointCloud2 source (``cloud``), and the barrage covers them too: random bytes, bit flips,
truncations, NaN ranges and geometry, counts beyond every bound, and clouds of wrong layouts
(missing, overlapping or unknown fields, steps that do not add up, data shorter than declared).
The tf subscriptions the sources bring get their share on ``/tf`` and ``/tf_static``: NaN and
infinite translations, zero and far-from-unit quaternions, a frame its own parent, empty and
over-long frame ids, counts beyond the bound, bit flips, truncations and random bytes.
Fixed seed, a few hundred samples.

Cyclone checks a sample's structure against the type on both ends (a writer refuses bytes that
are not a well-formed Float64MultiArray, a reader drops them), so what reaches the node is
structurally valid CDR that may still be undecodable (a label that is not UTF-8, an encapsulation
the header misstates) or decodable but unusable (sizes that do not add up, NaN, odd labels).

Afterwards the node is alive, its diagnostics count dropped and refused samples (the sources'
messages and refusals too), its stderr has no traceback, and, given a valid scan and cloud
again, it answers the probe proposals as it did when it was fresh: bit for bit where
the proposal passes through, and to the solver's tolerance where the QP is active (OSQP warm
starts from its previous solution, so even a fresh node's second answer differs in the last
bits).
"""
from __future__ import annotations

import collections
import math
from pathlib import Path
import signal
import struct
import subprocess
import sys
import threading
import time
from typing import Any, Callable

from dds_harness import node_runtime, subprocess_env  # this directory: on sys.path
import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[2]
UNICYCLE = str(REPO / 'config' / 'unicycle.yaml')
ARRAY = 'std_msgs/msg/Float64MultiArray'
WAIT_S = 60.0
SEED = 20240611
BARRAGE = 400

# Probe proposals, each carrying its own state (no staleness, no dependence on /state).
PASS_THROUGH = {'u': [0.4, 0.1], 'state': [2.0, 0.0, 0.0]}       # far from every obstacle
ACTIVE = {'u': [2.5, 0.0], 'state': [-0.85, 0.0, 0.0]}            # full speed at the centre one

EVERY_DIAGNOSTIC = ('-p', 'diagnostics.min_period_s:=0.0')
SENSORS = ('-p', 'observation_sources:=[front, cloud]', '-p', 'front.type:=scan',
           '-p', 'front.topic:=/scan', '-p', 'front.timeout_s:=30.0',
           '-p', 'cloud.type:=pointcloud', '-p', 'cloud.topic:=/points',
           '-p', 'cloud.timeout_s:=30.0', '-p', 'footprint.radius:=0.2')
"""Two sources whose valid samples put points far behind the probe states (no row binds): the
answers are those of the static obstacles."""
SCAN = 'sensor_msgs/msg/LaserScan'
CLOUD = 'sensor_msgs/msg/PointCloud2'
SENSOR_BARRAGE = 240
TF = 'tf2_msgs/msg/TFMessage'
TF_BARRAGE = 80
"""A diagnostic with every answer (the default rate-limits OK ones): each exchange reads the
counts from its own answer's diagnostic."""

pytestmark = pytest.mark.integration


def _cdr(sections: dict) -> bytes:
    from rcbf_ros.messages.conversions import sections_to_msg
    from rcbf_ros.ros.runtime import serialize_message  # the runtime conversions build for
    return serialize_message(sections_to_msg(sections))


class Probe:
    """A node of this process: raw writers on both inputs, readers of both outputs."""

    def __init__(self, domain_id: int, node_alive: Callable[[], None]) -> None:
        """Args: node_alive: raises AssertionError (with the node's stderr) once it is dead."""
        from rcbf_ros.messages.classes import get_message
        from rcbf_ros.ros.dds import rclpy_compat as rclpy
        from rcbf_ros.ros.dds.node import Node
        from rcbf_ros.ros.dds.qos import DurabilityPolicy, QoSProfile
        rclpy.init(args=[], domain_id=domain_id)
        self.rclpy = rclpy
        self.node_alive = node_alive
        self.node = Node('fuzz_probe')
        self.lock = threading.Lock()
        self.received: dict[str, list] = collections.defaultdict(list)
        array = get_message(ARRAY)
        self.writers = {topic: self.node.create_publisher(array, topic, QoSProfile(depth=10))
                        for topic in ('/cmd_proposed', '/state')}
        for topic, kind in (('/scan', SCAN), ('/points', CLOUD), ('/tf', TF)):
            self.writers[topic] = self.node.create_publisher(get_message(kind), topic,
                                                             QoSProfile(depth=10))
        self.writers['/tf_static'] = self.node.create_publisher(  # tf2_ros's static QoS
            get_message(TF), '/tf_static',
            QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL))
        self._subscribe(array, '/cmd_safe', _sections)
        self._subscribe(array, '/filter_info', lambda m: np.array(m.data, dtype=np.float64))
        self._subscribe(get_message('diagnostic_msgs/msg/DiagnosticArray'), '/diagnostics',
                        _diagnostic)
        self._running = True
        self._thread = threading.Thread(target=self._spin, daemon=True)
        self._thread.start()

    def _subscribe(self, msg_type: Any, topic: str, convert: Callable[[Any], Any]) -> None:
        from rcbf_ros.ros.dds.qos import QoSProfile

        def store(msg: Any) -> None:
            with self.lock:
                self.received[topic].append(convert(msg))
        self.node.create_subscription(msg_type, topic, store, QoSProfile(depth=1000))

    def _spin(self) -> None:
        while self._running and self.rclpy.ok():
            self.rclpy.spin_once(self.node, timeout_sec=0.05)

    def write(self, topic: str, data: bytes) -> bool:
        """Publish raw CDR bytes; False when the writer refuses them as malformed."""
        try:
            self.writers[topic].publish(data)
        except RuntimeError:
            return False
        return True

    def count(self, topic: str) -> int:
        with self.lock:
            return len(self.received[topic])

    def wait_for(self, topic: str, count: int) -> list:
        deadline = time.monotonic() + WAIT_S
        while self.count(topic) < count:
            assert time.monotonic() < deadline, f'{topic}: {self.count(topic)} of {count}'
            time.sleep(0.01)
        with self.lock:
            return list(self.received[topic])

    def settle(self) -> None:
        """Wait until no answer has arrived for 0.5 s and every answer has its diagnostics."""
        settled = -1
        while settled != self.count('/cmd_safe'):
            settled = self.count('/cmd_safe')
            time.sleep(0.5)
        self.wait_for('/diagnostics', settled)

    def exchange(self, topic: str, data: bytes) -> tuple[dict, tuple[int, str, dict]]:
        """Publish one sample; return the answer and its diagnostics (repeat until matched)."""
        for _ in range(100):
            self.node_alive()
            before = self.count('/cmd_safe')
            assert self.write(topic, data)
            deadline = time.monotonic() + 0.5
            while self.count('/cmd_safe') == before and time.monotonic() < deadline:
                time.sleep(0.01)
            if self.count('/cmd_safe') > before:
                self.settle()
                self.node_alive()
                with self.lock:
                    return self.received['/cmd_safe'][-1], self.received['/diagnostics'][-1]
        raise AssertionError('the safety_filter never answered')

    def close(self) -> None:
        self._running = False
        self._thread.join(timeout=5)
        self.node.destroy_node()
        self.rclpy.try_shutdown()


def _sections(msg: Any) -> dict[str, np.ndarray]:
    from rcbf_ros.messages.conversions import msg_to_sections
    return {key: value.copy() for key, value in msg_to_sections(msg).items()}


def _diagnostic(msg: Any) -> tuple[int, str, dict[str, str]]:
    status = msg.status[0]
    return int(status.level), status.message, {kv.key: kv.value for kv in status.values}


def _intruders(domain_id: int) -> tuple[Any, list[tuple[Any, Any]]]:
    """Another participant with other types on the filter's topic names."""
    from rcbf_ros.messages.classes import get_message
    from rcbf_ros.ros.dds.context import Context
    from rcbf_ros.ros.dds.node import Node
    context = Context()
    context.init(args=[], domain_id=domain_id)
    node = Node('fuzz_intruder', context=context)
    twist, text = get_message('geometry_msgs/msg/Twist'), get_message('std_msgs/msg/String')
    moving = twist()
    moving.linear.x = 2.5
    writers = [(node.create_publisher(twist, '/cmd_proposed', 10), moving),
               (node.create_publisher(text, '/state', 10), text(data='-0.85 0.0 0.0'))]
    return context, writers


def _barrage(rng: np.random.Generator) -> list[tuple[str, str, bytes]]:
    """(kind, topic, bytes) samples of every malformed class, in a seeded random order."""
    from rcbf_ros.messages.conversions import array_to_twist, sections_to_msg
    from rcbf_ros.ros.runtime import get_message, serialize_message
    valid = {'/cmd_proposed': [_cdr(ACTIVE), _cdr(PASS_THROUGH), _cdr({'u': [1.0, 0.0]}),
                               _cdr({'u': [0.5, 0.2], 'disturbance_mean': [0.0] * 3,
                                     'disturbance_std': [0.1] * 3})],
             '/state': [_cdr({'state': [-0.85, 0.0, 0.0]}), _cdr({'state': [1.0, 1.0, 0.5]})]}
    others = [serialize_message(array_to_twist([0.0, 0.0], ['linear.x', 'angular.z'])),
              serialize_message(array_to_twist([2.5, 1.0], ['linear.x', 'angular.z'])),
              serialize_message(get_message('std_msgs/msg/String')(data='u')),
              serialize_message(get_message('std_msgs/msg/Float64')(data=2.5))]

    def label_bytes(base: bytes, replacement: bytes) -> bytes:
        data = bytearray(base)
        data[12:13] = replacement  # first byte of the first label ('u' or 's')
        return bytes(data)

    def long_label(length: int) -> bytes:
        message = sections_to_msg({'u': [1.0, 0.0]})
        message.layout.dim[0].label = 'u' * length
        return serialize_message(message)

    def patched(base: bytes, offset: int, value: int) -> bytes:
        data = bytearray(base)
        struct.pack_into('<I', data, offset, value)
        return bytes(data)

    makers: dict[str, Callable[[bytes], bytes]] = {
        'random bytes': lambda base: rng.integers(
            0, 256, int(rng.integers(0, 160)), dtype=np.uint8).tobytes(),
        'random body': lambda base: b'\x00\x01\x00\x00' + rng.integers(
            0, 256, int(rng.integers(0, 160)), dtype=np.uint8).tobytes(),
        'bit flips': lambda base: _flipped(rng, base, int(rng.integers(1, 4))),
        'header flip': lambda base: bytes([base[0], base[1] ^ 1]) + base[2:],
        'truncated': lambda base: base[:int(rng.integers(0, len(base)))],
        'extended': lambda base: base + rng.integers(
            0, 256, int(rng.integers(1, 64)), dtype=np.uint8).tobytes(),
        'non-UTF-8 label': lambda base: label_bytes(base, bytes([int(rng.integers(0x80, 0x100))])),
        'very long label': lambda base: long_label(int(rng.choice([65, 4096, 200_000]))),
        'huge dimension count': lambda base: patched(base, 4, 0xFFFFFFFF),
        'huge label length': lambda base: patched(base, 8, 0xFFFFFFF0),
        'huge data count': lambda base: patched(_cdr({'u': [1.0, 0.0]}), 28, 0xFFFFFFFF),
        'other type payload': lambda base: others[int(rng.integers(0, len(others)))],
    }
    samples = []
    kinds = sorted(makers)
    for index in range(BARRAGE):
        kind = kinds[index % len(kinds)]
        topic = '/cmd_proposed' if rng.random() < 0.6 else '/state'
        base = valid[topic][int(rng.integers(0, len(valid[topic])))]
        samples.append((kind, topic, makers[kind](base)))
    order = rng.permutation(len(samples))
    return [samples[i] for i in order]


def _stamp() -> Any:
    from rcbf_ros.messages.typestore import jazzy_typestore
    t = jazzy_typestore().types
    now = time.time_ns()
    return t['builtin_interfaces/msg/Time'](sec=now // 10**9, nanosec=now % 10**9)


def _scan_cdr(ranges: Any = None, **changes: Any) -> bytes:
    """A LaserScan in base_link stamped now (rosbags' encoder): by default 90 beams 8 m behind
    the robot (angles pi -+ 0.45), far from every probe state's obstacles."""
    from rcbf_ros.messages.typestore import jazzy_typestore
    store = jazzy_typestore()
    t = store.types
    ranges = np.full(90, 8.0) if ranges is None else ranges
    fields = dict(
        header=t['std_msgs/msg/Header'](stamp=_stamp(), frame_id='base_link'),
        angle_min=math.pi - 0.45, angle_max=math.pi + 0.45, angle_increment=0.01,
        time_increment=0.0, scan_time=0.1, range_min=0.05, range_max=10.0,
        ranges=np.asarray(ranges, np.float32), intensities=np.zeros(0, np.float32))
    fields.update(changes)
    return bytes(store.serialize_cdr(t[SCAN](**fields), SCAN))


def _cloud_cdr(points: Any = None, **changes: Any) -> bytes:
    """A PointCloud2 of float32 x, y, z in odom stamped now: by default 50 points around
    (-12, 8, 0.2), far from every probe state's obstacles; ``changes`` override any field
    (wrong layouts)."""
    from rcbf_ros.messages.typestore import jazzy_typestore
    store = jazzy_typestore()
    t = store.types
    if points is None:
        points = np.column_stack([np.linspace(-12.5, -11.5, 50), np.full(50, 8.0),
                                  np.full(50, 0.2)])
    data = np.ascontiguousarray(points, dtype='<f4').view(np.uint8).ravel()
    field = t['sensor_msgs/msg/PointField']
    fields = dict(
        header=t['std_msgs/msg/Header'](stamp=_stamp(), frame_id='odom'), height=1,
        width=len(points), fields=[field(name=name, offset=4 * k, datatype=7, count=1)
                                   for k, name in enumerate('xyz')],
        is_bigendian=False, point_step=12, row_step=12 * len(points), data=data,
        is_dense=True)
    fields.update(changes)
    return bytes(store.serialize_cdr(t[CLOUD](**fields), CLOUD))


def _sensor_barrage(rng: np.random.Generator) -> list[tuple[str, str, bytes]]:
    """(kind, topic, bytes) hostile samples of the two sources, in a seeded random order."""
    from rcbf_ros.messages.typestore import jazzy_typestore
    field = jazzy_typestore().types['sensor_msgs/msg/PointField']

    def xyz(offsets: tuple[int, ...] = (0, 4, 8), datatype: int = 7, count: int = 1,
            names: str = 'xyz') -> list[Any]:
        return [field(name=name, offset=offset, datatype=datatype, count=count)
                for name, offset in zip(names, offsets)]

    nan = float('nan')
    scans: dict[str, Callable[[], bytes]] = {
        'scan NaN ranges': lambda: _scan_cdr(np.full(90, nan)),
        'scan inf and negative ranges': lambda: _scan_cdr(
            rng.choice([np.inf, -np.inf, -1.0, 0.0, 1e30], 90)),
        'scan NaN geometry': lambda: _scan_cdr(**{str(rng.choice(
            ['angle_min', 'angle_increment', 'range_min', 'range_max'])): nan}),
        'scan huge angles': lambda: _scan_cdr(angle_min=3.0e38, angle_increment=1.0e37),
        'scan too many beams': lambda: _scan_cdr(np.ones(200_001)),
        'scan huge range count': lambda: _patched_count(_scan_cdr(), 'scan'),
        'scan truncated': lambda: (lambda b: b[:int(rng.integers(0, len(b)))])(_scan_cdr()),
        'scan bit flips': lambda: _flipped(rng, _scan_cdr(), int(rng.integers(1, 6))),
        'scan random bytes': lambda: b'\x00\x01\x00\x00' + rng.integers(
            0, 256, int(rng.integers(0, 400)), dtype=np.uint8).tobytes(),
    }
    clouds: dict[str, Callable[[], bytes]] = {
        'cloud NaN points': lambda: _cloud_cdr(np.full((20, 3), nan)),
        'cloud without z': lambda: _cloud_cdr(fields=xyz(names='xy')),
        'cloud overlapping fields': lambda: _cloud_cdr(fields=xyz(offsets=(0, 0, 2))),
        'cloud unknown datatype': lambda: _cloud_cdr(fields=xyz(datatype=int(
            rng.choice([0, 1, 5, 9, 255])))),
        'cloud field count 0': lambda: _cloud_cdr(fields=xyz(count=0)),
        'cloud fields beyond the step': lambda: _cloud_cdr(point_step=8),
        'cloud huge width and height': lambda: _cloud_cdr(width=2**31 - 1, height=2**31 - 1),
        'cloud row step short': lambda: _cloud_cdr(row_step=5),
        'cloud data short': lambda: _cloud_cdr(width=5000, row_step=60_000),
        'cloud big-endian flag': lambda: _cloud_cdr(is_bigendian=True),
        'cloud huge point step': lambda: _cloud_cdr(point_step=2**32 - 1),
        'cloud huge data count': lambda: _patched_count(_cloud_cdr(), 'cloud'),
        'cloud truncated': lambda: (lambda b: b[:int(rng.integers(0, len(b)))])(_cloud_cdr()),
        'cloud bit flips': lambda: _flipped(rng, _cloud_cdr(), int(rng.integers(1, 6))),
        'cloud random bytes': lambda: b'\x00\x01\x00\x00' + rng.integers(
            0, 256, int(rng.integers(0, 400)), dtype=np.uint8).tobytes(),
    }
    makers = [(kind, '/scan', make) for kind, make in sorted(scans.items())] + [
        (kind, '/points', make) for kind, make in sorted(clouds.items())]
    samples = [(kind, topic, make()) for index in range(SENSOR_BARRAGE)
               for kind, topic, make in (makers[index % len(makers)],)]
    order = rng.permutation(len(samples))
    return [samples[i] for i in order]


def _tf_cdr(parent: str = 'map', child: str = 'fuzz', translation: Any = (1.0, 2.0, 0.0),
            rotation: Any = (0.0, 0.0, 0.0, 1.0), copies: int = 1) -> bytes:
    """A TFMessage of ``copies`` transforms stamped now (rosbags' encoder); by default of frames
    no source uses, so that whatever a flip leaves valid places no point elsewhere."""
    from rcbf_ros.messages.typestore import jazzy_typestore
    store = jazzy_typestore()
    t = store.types
    transform = t['geometry_msgs/msg/TransformStamped'](
        header=t['std_msgs/msg/Header'](stamp=_stamp(), frame_id=parent), child_frame_id=child,
        transform=t['geometry_msgs/msg/Transform'](
            translation=t['geometry_msgs/msg/Vector3'](*map(float, translation)),
            rotation=t['geometry_msgs/msg/Quaternion'](*map(float, rotation))))
    return bytes(store.serialize_cdr(t[TF](transforms=[transform] * copies), TF))


def _tf_barrage(rng: np.random.Generator) -> list[tuple[str, str, bytes]]:
    """(kind, topic, bytes) hostile samples of /tf and /tf_static, in a seeded random order.
    The transforms naming the sources' frames (odom -> base_link) are all refused."""
    nan, inf = float('nan'), float('inf')
    makers: dict[str, Callable[[], bytes]] = {
        'tf NaN translation': lambda: _tf_cdr('odom', 'base_link', (nan, 0.0, 0.0)),
        'tf infinite translation': lambda: _tf_cdr('odom', 'base_link', (0.0, -inf, 0.0)),
        'tf NaN rotation': lambda: _tf_cdr('odom', 'base_link', rotation=(0.0, 0.0, nan, 1.0)),
        'tf zero quaternion': lambda: _tf_cdr('odom', 'base_link', rotation=(0.0,) * 4),
        'tf long quaternion': lambda: _tf_cdr('odom', 'base_link', rotation=(0.0, 0.0, 1.0,
                                                                              1.0)),
        'tf own parent': lambda: _tf_cdr('base_link', 'base_link'),
        'tf empty frame': lambda: _tf_cdr('', 'base_link'),
        'tf long frame id': lambda: _tf_cdr('odom', 'b' * 5000),
        'tf too many transforms': lambda: _tf_cdr(copies=1025),
        'tf huge count': lambda: (lambda b: b[:4] + struct.pack('<I', 0xFFFFFFF0) + b[8:])(
            _tf_cdr()),
        'tf truncated': lambda: (lambda b: b[:int(rng.integers(0, len(b)))])(_tf_cdr()),
        'tf bit flips': lambda: _flipped(rng, _tf_cdr(), int(rng.integers(1, 6))),
        'tf random bytes': lambda: b'\x00\x01\x00\x00' + rng.integers(
            0, 256, int(rng.integers(0, 200)), dtype=np.uint8).tobytes(),
    }
    kinds = sorted(makers)
    samples = [(kinds[index % len(kinds)], '/tf_static' if rng.random() < 0.3 else '/tf',
                makers[kinds[index % len(kinds)]]()) for index in range(TF_BARRAGE)]
    order = rng.permutation(len(samples))
    return [samples[i] for i in order]


def _patched_count(data: bytes, kind: str) -> bytes:
    """The length field of a scan's ranges or a cloud's data set huge (default samples)."""
    out = bytearray(data)
    if kind == 'scan':  # ranges (90 floats): its length just before, then empty intensities
        struct.pack_into('<I', out, len(out) - 4 - 360 - 4, 0xFFFFFFF0)
    else:  # data (600 bytes by default): its length just before, is_dense (1 byte) after
        struct.pack_into('<I', out, len(out) - 1 - 600 - 4, 0xFFFFFFF0)
    return bytes(out)


def _flipped(rng: np.random.Generator, data: bytes, flips: int) -> bytes:
    out = bytearray(data)
    for _ in range(flips):
        out[int(rng.integers(0, len(out)))] ^= 1 << int(rng.integers(0, 8))
    return bytes(out)


def _sensed_exchange(probe: Probe, sections: dict) -> tuple[dict, tuple[int, str, dict]]:
    """A valid scan and cloud, then the proposal; again until the answer uses both sources (a
    sample may be lost, or arrive after the proposal)."""
    for _ in range(50):
        assert probe.write('/scan', _scan_cdr()) and probe.write('/points', _cloud_cdr())
        time.sleep(0.1)
        answer = probe.exchange('/cmd_proposed', _cdr(sections))
        if not answer[1][1].startswith('source '):
            return answer
    raise AssertionError(f'the sources were never used: {answer[1][1]}')


def test_fuzz_barrage_never_kills_the_node(ros_domain_id, tmp_path):
    stdout, stderr = tmp_path / 'stdout.txt', tmp_path / 'stderr.txt'
    env = subprocess_env(ros_domain_id)
    env['PYTHONUNBUFFERED'] = '1'
    with open(stdout, 'wb') as out, open(stderr, 'wb') as err:
        process = subprocess.Popen(
            [sys.executable, '-m', 'rcbf_ros.ros.safety_filter_node', '--ros-args',
             '--params-file', UNICYCLE, *EVERY_DIAGNOSTIC, *SENSORS], env=env, cwd=REPO,
            stdout=out,
            stderr=err)

    def node_alive() -> None:
        assert process.poll() is None, f'the node died:\n{stderr.read_text()[-4000:]}'
    probe = Probe(ros_domain_id, node_alive)
    intruder_context, intruders = _intruders(ros_domain_id)
    try:
        fresh = {name: _sensed_exchange(probe, sections)
                 for name, sections in (('pass', PASS_THROUGH), ('active', ACTIVE))}
        fresh['repeat'] = _sensed_exchange(probe, ACTIVE)
        answered_before = probe.count('/cmd_safe')

        rng = np.random.default_rng(SEED)
        delivered: collections.Counter = collections.Counter()
        refused: collections.Counter = collections.Counter()
        samples = _barrage(rng) + _sensor_barrage(rng) + _tf_barrage(rng)
        samples = [samples[i] for i in rng.permutation(len(samples))]
        for index, (kind, topic, data) in enumerate(samples):
            (delivered if probe.write(topic, data) else refused)[kind] += 1
            if index % 40 == 0:
                for writer, message in intruders:
                    writer.publish(message)
            if index % 8 == 7:
                time.sleep(0.01)  # let the node's keep-last-10 readers drain
        probe.settle()
        node_alive()
        answered = probe.count('/cmd_safe') - answered_before

        after = {name: _sensed_exchange(probe, sections)
                 for name, sections in (('pass', PASS_THROUGH), ('active', ACTIVE))}
        node_alive()
    finally:
        intruder_context.try_shutdown()
        probe.close()
        if process.poll() is None:
            process.send_signal(signal.SIGINT)
        try:
            code = process.wait(timeout=20)
        except subprocess.TimeoutExpired:
            process.kill()
            code = process.wait()
    errors = stderr.read_text(errors='replace')
    assert code == 0, errors[-4000:]
    assert 'Traceback' not in errors, errors[-4000:]

    # The barrage reached the node: some samples passed the writer's checks and were answered.
    assert sum(delivered.values()) > 100 and answered > 50, (delivered, refused, answered)
    for kind in ('non-UTF-8 label', 'very long label', 'extended', 'other type payload'):
        assert delivered[kind] > 0, (kind, delivered, refused)
    # One-line, throttled reports (a second per reason key at most): no flood.
    assert len(errors.splitlines()) < 200, errors[-4000:]
    # rmw_cyclonedds hands the node's raw readers none of the samples that do not decode
    # (truncated, impossible lengths): on rclpy the node's own decoding never refuses one.
    undecodable_delivered = node_runtime() != 'rclpy'
    assert ('undecodable proposal' in errors) == undecodable_delivered, errors[-4000:]

    # The diagnostics count what was dropped and refused, cumulatively.
    level, message, values = after['active'][1]
    assert (int(values['dropped_samples']) > 0) == undecodable_delivered, values
    assert int(values['refused_proposals']) > 0 and int(values['refused_states']) > 0, values
    # ... and the sources' messages and refusals: hostile scans and clouds reached them.
    sensor_kinds = [kind for kind in delivered if kind.startswith(('scan ', 'cloud '))]
    assert sum(delivered[kind] for kind in sensor_kinds) > 50, (delivered, refused)
    for kind in ('scan NaN geometry', 'scan too many beams', 'cloud without z',
                 'cloud data short', 'cloud huge width and height'):
        assert delivered[kind] > 0, (kind, delivered, refused)
    for name in ('front', 'cloud'):
        assert int(values[f'{name}.messages']) > int(fresh['active'][1][2][f'{name}.messages'])
        assert int(values[f'{name}.refused']) > 0, values
    # ... and tf's: whole messages refused (bounds, layout) and transforms refused alone.
    for kind in ('tf NaN translation', 'tf zero quaternion', 'tf too many transforms'):
        assert delivered[kind] > 0, (kind, delivered, refused)
    assert int(values['tf.messages']) > 20 and int(values['tf.refused']) > 0, values
    assert int(values['tf.transforms_refused']) >= delivered['tf zero quaternion'], values
    # The same answers as when fresh: exactly where nothing is solved, to the solver's
    # tolerance where the QP is active (as between two answers of a fresh node).
    for name in ('pass', 'active'):
        (command, (level, message, values)), (fresh_command, fresh_diagnostic) = (
            after[name], fresh[name])
        assert (level, message) == fresh_diagnostic[:2] and level == 0, (name, message)
        assert list(command) == list(fresh_command) == ['u']  # the command alone
    # Every answer had its filter_info, and none of them, fail-safes included, holds NaN.
    infos = probe.wait_for('/filter_info', probe.count('/cmd_safe'))
    assert all(np.all(np.isfinite(info)) for info in infos)
    np.testing.assert_array_equal(after['pass'][0]['u'], fresh['pass'][0]['u'])
    np.testing.assert_array_equal(after['pass'][0]['u'], PASS_THROUGH['u'])
    assert 0.0 < after['active'][0]['u'][0] < 2.5
    np.testing.assert_allclose(after['active'][0]['u'], fresh['active'][0]['u'], atol=1e-6)
    np.testing.assert_allclose(fresh['repeat'][0]['u'], fresh['active'][0]['u'], atol=1e-6)
