"""A bag that real rosbag2 records of a running filter launch, read by our replay and refilter.

``ros2 bag record`` (Jazzy, MCAP) records ``rcbf_ros launch unicycle_filter`` running on our
runtime (short episodes). Then our replay node plays the bag to an rclpy subscriber, and
``rcbf_ros refilter`` filters its proposals again; what comes out is checked against what the
bag holds (read with rosbags) and, for refilter, against the barriers (the QP rows evaluated
at each new command).
"""
from __future__ import annotations

import json
import os
from pathlib import Path
import subprocess
import sys
import time
from typing import Any

import numpy as np
import pytest
from rosbags.highlevel import AnyReader
import torch

from rcbf_ros.ros.loopback import ensure_loopback

pytestmark = pytest.mark.ros2
HERE = Path(__file__).resolve().parent
REPO = HERE.parents[1]
sys.path.insert(0, str(REPO / 'test'))
from conftest import Jazzy, stop_group  # noqa: E402

RECORDED = ('/state', '/cmd_proposed', '/cmd_safe', '/filter_info', '/episode')
EPISODES, MAX_STEPS = 2, 200
"""The run ``ros2 bag record`` records. The recorder subscribes to a topic only once a
publisher of it is in the graph, and the lockstep run does not wait for the recorder, so its
first steps may go unrecorded: the run is long enough (and the recorder polls the graph
every 10 ms) that they stay far below the half the test asks for."""


def ours_env(domain_id: int) -> dict[str, str]:
    """Our runtime's environment (this checkout's Python, loopback Cyclone)."""
    env = dict(os.environ, RCBF_ROS_RUNTIME='cyclone', ROS_DOMAIN_ID=str(domain_id),
               PYTHONUNBUFFERED='1', OMP_NUM_THREADS='1')
    ensure_loopback(env, force=True)
    return env


def wait_for_text(path: Path, text: str, timeout: float) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if path.exists() and text in path.read_text():
            return
        time.sleep(0.2)
    raise AssertionError(f'{text!r} not in {path} after {timeout} s:\n{path.read_text()[-3000:]}')


def bag_messages(bag: Path) -> dict[str, list[Any]]:
    """Every message of a bag by topic, in log-time order (rosbags)."""
    found: dict[str, list[Any]] = {}
    with AnyReader([bag]) as reader:
        for connection, _, raw in reader.messages():
            found.setdefault(connection.topic, []).append(
                reader.deserialize(raw, connection.msgtype))
    return found


def sections(msg: Any) -> dict[str, np.ndarray]:
    """A Float64MultiArray's labelled sections (rosbags' message)."""
    data, start, out = np.asarray(msg.data, dtype=np.float64), 0, {}
    for dim in msg.layout.dim:
        out[dim.label] = data[start:start + dim.size]
        start += dim.size
    return out


@pytest.fixture(scope='module')
def recorded(jazzy: Jazzy, tmp_path_factory) -> tuple[Path, int]:
    """The rosbag2 bag of a unicycle_filter launch, and the domain it ran on."""
    domain_id = 1 + (os.getpid() * 7 + 131) % 200
    where = tmp_path_factory.mktemp('recorded')
    bag, log = where / 'bag', where / 'record.log'
    record = jazzy.start(f'ros2 bag record -s mcap --polling-interval 10 -o {bag} '
                         f'{" ".join(RECORDED)}',
                         domain_id=domain_id, log=log)
    try:
        wait_for_text(log, 'Listening for topics', 60)
        launch = subprocess.run(
            [sys.executable, '-m', 'rcbf_ros.launch.local', 'unicycle_filter',
             '--domain-id', str(domain_id), '--without', 'recorder', '--without',
             'scene_markers', '-p', f'simulator:max_episodes:={EPISODES}',
             '-p', f'simulator:max_steps:={MAX_STEPS}'],
            env=ours_env(domain_id), cwd=REPO, capture_output=True, text=True, timeout=300)
        assert launch.returncode == 0, (launch.stdout + launch.stderr)[-4000:]
        time.sleep(1.0)  # the last samples reach the recorder
    finally:
        code = stop_group(record)
    assert code == 0, log.read_text()[-3000:]
    return bag, domain_id


def test_ros2_bag_record_holds_the_run(recorded, jazzy):
    bag, domain_id = recorded
    messages = bag_messages(bag)
    info = jazzy.run(f'ros2 bag info {bag}', domain_id=domain_id, timeout=60)
    assert info.returncode == 0 and 'Storage id:        mcap' in info.stdout, info.stdout
    for topic in RECORDED:
        assert f'Topic: {topic} | ' in info.stdout, info.stdout
        assert f'Count: {len(messages.get(topic, []))} |' in info.stdout.split(
            f'Topic: {topic} | ')[1].splitlines()[0], info.stdout
    ends = [json.loads(m.data) for m in messages['/episode'] if '"end"' in m.data]
    assert [e['episode'] for e in ends] == list(range(1, EPISODES + 1)), ends
    assert len(messages['/cmd_proposed']) >= EPISODES * MAX_STEPS // 2


def test_our_replay_plays_the_rosbag2_bag_to_rclpy(recorded, jazzy, tmp_path):
    bag, domain_id = recorded
    expected = bag_messages(bag)
    out, log = tmp_path / 'received.json', tmp_path / 'listener.log'
    listener = jazzy.start(
        f'"$(head -1 "$(command -v ros2)" | cut -c3-)" {HERE / "rclpy_listener.py"} {out} 3 '
        '/state:std_msgs/msg/Float64MultiArray /cmd_safe:std_msgs/msg/Float64MultiArray',
        domain_id=domain_id, log=log)
    try:
        wait_for_text(log, 'listening', 60)
        replay = subprocess.run(
            [sys.executable, '-m', 'rcbf_ros.ros.replay_node', '--ros-args',
             '-p', f'bag:={bag}', '-p', "topics:=['/state', '/cmd_safe']", '-p', 'rate:=5.0',
             '-p', 'wait_for_subscribers_s:=30.0', '-p', 'linger_s:=1.0'],
            env=ours_env(domain_id), cwd=REPO, capture_output=True, text=True, timeout=180)
        assert replay.returncode == 0, replay.stdout + replay.stderr
        listener.wait(timeout=60)
    finally:
        stop_group(listener)
    received = json.loads(out.read_text())
    for topic in ('/state', '/cmd_safe'):
        assert len(received[topic]) == len(expected[topic]), (topic, log.read_text()[-2000:])
        got = [list(message['data']) for message in received[topic]]
        assert got == [list(map(float, m.data)) for m in expected[topic]], topic
        assert [[d['label'] for d in message['layout']['dim']] for message in received[topic]] \
            == [[d.label for d in m.layout.dim] for m in expected[topic]]


def test_refilter_reads_the_rosbag2_bag_and_its_commands_satisfy_the_barriers(recorded, jazzy,
                                                                              tmp_path):
    from rcbf_ros.bag.refilter import build_filter
    from rcbf_ros.parameters.rules import find_config, load_params
    bag, domain_id = recorded
    out, summary_path = tmp_path / 'refiltered', tmp_path / 'summary.json'
    done = subprocess.run(
        [sys.executable, '-m', 'rcbf_ros.bag.refilter', str(bag), str(out), '--params-file',
         'unicycle', '--json', str(summary_path)],
        env=ours_env(domain_id), capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stdout + done.stderr
    summary = json.loads(summary_path.read_text())
    source, written = bag_messages(bag), bag_messages(out)
    assert summary['proposals'] == len(source['/cmd_proposed'])
    assert summary['processed'] + summary['skipped_total'] == summary['proposals']
    assert summary['processed'] > 0 and summary['fail_safe'] == 0, summary
    # The parameters the run was recorded with: the recorded commands, again.
    assert summary['recorded_topic'] == '/filter_info' and summary['compared'] > 0, summary
    assert summary['changed'] == 0, summary
    for topic, items in source.items():
        assert len(written[topic]) == len(items), topic
    infos = [sections(m) for m in written['/refilter/filter_info']]
    commands = [sections(m)['u'] for m in written['/refilter/cmd_safe']]
    assert len(commands) == len(infos) == summary['processed']
    info = jazzy.run(f'ros2 bag info {out}', domain_id=domain_id, timeout=60)
    assert info.returncode == 0, info.stdout
    assert (f'Topic: /refilter/cmd_safe | Type: std_msgs/msg/Float64MultiArray | Count: '
            f'{len(commands)} |') in info.stdout, info.stdout

    # Every new command meets every QP row (barriers, robust margins, limits) at its state,
    # evaluated anew from the constraint assembly rather than read from the solver.
    config, _, safety_filter = build_filter(load_params(find_config('unicycle'),
                                                        'safety_filter'))
    n_x = safety_filter.n_x
    mean = torch.tensor([list(config.static_mean or [0.0] * n_x)], dtype=torch.float64)
    std = torch.tensor([list(config.static_std or [0.0] * n_x)], dtype=torch.float64)
    worst = np.inf
    for info_sections, command in zip(infos, commands):
        np.testing.assert_array_equal(info_sections['u'], command)
        state = torch.from_numpy(info_sections['state'].copy()).unsqueeze(0)
        u = torch.from_numpy(command.copy()).unsqueeze(0)
        qp = safety_filter.problem.qp(state, u, mean, std)
        worst = min(worst, float(qp.h.min()))  # rows G z <= h at z = (u_S, slack) = 0
    assert worst >= -1e-6, worst
