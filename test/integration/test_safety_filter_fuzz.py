"""No message kills the safety_filter node: a fuzz barrage over real Cyclone DDS (loopback).

The node runs as its own process with config/unicycle.yaml. A probe in this process publishes
raw CDR payloads on ``cmd_proposed`` and ``state`` through the runtime's writers (a publisher
takes serialized bytes as rclpy's does): random bytes, bit-flipped valid samples, truncated and
extended samples, labels that are not UTF-8 or are very long, huge sequence length fields, and
other types' payloads under the array type. A second participant publishes other message types
(Twist, String) under the same topic names. Fixed seed, a few hundred samples.

Cyclone checks a sample's structure against the type on both ends (a writer refuses bytes that
are not a well-formed Float64MultiArray, a reader drops them), so what reaches the node is
structurally valid CDR that may still be undecodable (a label that is not UTF-8, an encapsulation
the header misstates) or decodable but unusable (sizes that do not add up, NaN, odd labels).

Afterwards the node is alive, its diagnostics count dropped and refused samples, its stderr has
no traceback, and it answers the probe proposals as it did when it was fresh: bit for bit where
the proposal passes through, and to the solver's tolerance where the QP is active (OSQP warm
starts from its previous solution, so even a fresh node's second answer differs in the last
bits).
"""
from __future__ import annotations

import collections
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
        from rcbf_ros.ros.dds.qos import QoSProfile
        rclpy.init(args=[], domain_id=domain_id)
        self.rclpy = rclpy
        self.node_alive = node_alive
        self.node = Node('fuzz_probe')
        self.lock = threading.Lock()
        self.received: dict[str, list] = collections.defaultdict(list)
        array = get_message(ARRAY)
        self.writers = {topic: self.node.create_publisher(array, topic, QoSProfile(depth=10))
                        for topic in ('/cmd_proposed', '/state')}
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


def _flipped(rng: np.random.Generator, data: bytes, flips: int) -> bytes:
    out = bytearray(data)
    for _ in range(flips):
        out[int(rng.integers(0, len(out)))] ^= 1 << int(rng.integers(0, 8))
    return bytes(out)


def test_fuzz_barrage_never_kills_the_node(ros_domain_id, tmp_path):
    stdout, stderr = tmp_path / 'stdout.txt', tmp_path / 'stderr.txt'
    env = subprocess_env(ros_domain_id)
    env['PYTHONUNBUFFERED'] = '1'
    with open(stdout, 'wb') as out, open(stderr, 'wb') as err:
        process = subprocess.Popen(
            [sys.executable, '-m', 'rcbf_ros.ros.safety_filter_node', '--ros-args',
             '--params-file', UNICYCLE, *EVERY_DIAGNOSTIC], env=env, cwd=REPO, stdout=out,
            stderr=err)

    def node_alive() -> None:
        assert process.poll() is None, f'the node died:\n{stderr.read_text()[-4000:]}'
    probe = Probe(ros_domain_id, node_alive)
    intruder_context, intruders = _intruders(ros_domain_id)
    try:
        fresh = {name: probe.exchange('/cmd_proposed', _cdr(sections))
                 for name, sections in (('pass', PASS_THROUGH), ('active', ACTIVE))}
        fresh['repeat'] = probe.exchange('/cmd_proposed', _cdr(ACTIVE))
        answered_before = probe.count('/cmd_safe')

        rng = np.random.default_rng(SEED)
        delivered: collections.Counter = collections.Counter()
        refused: collections.Counter = collections.Counter()
        for index, (kind, topic, data) in enumerate(_barrage(rng)):
            (delivered if probe.write(topic, data) else refused)[kind] += 1
            if index % 40 == 0:
                for writer, message in intruders:
                    writer.publish(message)
            if index % 8 == 7:
                time.sleep(0.01)  # let the node's keep-last-10 readers drain
        probe.settle()
        node_alive()
        answered = probe.count('/cmd_safe') - answered_before

        after = {name: probe.exchange('/cmd_proposed', _cdr(sections))
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
