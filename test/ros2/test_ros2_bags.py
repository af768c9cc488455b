"""rosbag2 Jazzy reads and plays the bags our recorder writes (``ros2 bag info`` / ``play``)."""
from __future__ import annotations

import os
from pathlib import Path
import subprocess
import sys
import time

import pytest

from rcbf_ros.bag import BagWriter, RecordedQos
from rcbf_ros.ros.loopback import ensure_loopback

pytestmark = pytest.mark.ros2
REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO / 'test'))
from conftest import stop_group  # noqa: E402


def _record_with_our_recorder(jazzy, bag: Path, domain_id: int, tmp_path: Path) -> str:
    """Our recorder (Cyclone runtime) records 20 messages that ros2 topic pub sends."""
    env = dict(os.environ, RCBF_ROS_RUNTIME='cyclone', ROS_DOMAIN_ID=str(domain_id),
               PYTHONUNBUFFERED='1')
    ensure_loopback(env, force=True)
    log = tmp_path / 'recorder.log'
    recorder = subprocess.Popen(
        [sys.executable, '-m', 'rcbf_ros.ros.recorder_node', '--ros-args',
         '-p', f'output:={bag}', '-p', 'topics:=[/state]', '-p', 'discovery_period_s:=0.3',
         '-p', 'flush_period_s:=0.2'], env=env, cwd=tmp_path, start_new_session=True,
        stdout=log.open('w'), stderr=subprocess.STDOUT)
    try:
        published = jazzy.run(
            'ros2 topic pub --times 20 --rate 20 -w 1 /state std_msgs/msg/Float64MultiArray '
            '"{data: [1.0, 2.5]}"', domain_id=domain_id, timeout=90)
        assert published.returncode == 0, published.stdout[-2000:]
        time.sleep(1.0)  # the last samples reach the recorder
    finally:
        code = stop_group(recorder)
    assert code == 0, log.read_text()[-3000:]
    return log.read_text()


def test_ros2_bag_info_and_play_take_a_bag_of_our_recorder(jazzy, tmp_path, ros_domain_id):
    bag = tmp_path / 'bag'
    log = _record_with_our_recorder(jazzy, bag, ros_domain_id, tmp_path)
    assert '/state: 20' in log, log[-2000:]
    info = jazzy.run(f'ros2 bag info {bag}', domain_id=ros_domain_id, timeout=60)
    assert info.returncode == 0, info.stdout
    assert 'Storage id:        mcap' in info.stdout and 'Messages:          20' in info.stdout
    assert 'Topic: /state | Type: std_msgs/msg/Float64MultiArray | Count: 20' in info.stdout
    play = jazzy.start(f'ros2 bag play --loop --rate 5 {bag}', domain_id=ros_domain_id,
                       log=tmp_path / 'play.log')
    try:
        echo = jazzy.run('ros2 topic echo --once /state std_msgs/msg/Float64MultiArray',
                         domain_id=ros_domain_id, timeout=60)
    finally:
        stop_group(play)
    played = (tmp_path / 'play.log').read_text()
    assert echo.returncode == 0 and '- 2.5' in echo.stdout, echo.stdout + played
    assert 'error' not in played.lower(), played


def test_ros2_bag_info_reads_every_offered_qos(jazzy, tmp_path, ros_domain_id):
    bag = tmp_path / 'bag'
    with BagWriter(bag) as writer:
        qos = [RecordedQos.sensor_data(), RecordedQos(durability='transient_local')]
        writer.add_topic('/scan', 'std_msgs/msg/String', qos=qos)
        writer.add_topic('/state', 'std_msgs/msg/Float64MultiArray')
        for i in range(3):
            writer.write_message('/scan', {'data': f'{i}'}, 1_000 + i)
            writer.write_message('/state', {'data': [float(i)]}, 1_000 + i)
    info = jazzy.run(f'ros2 bag info {bag}', domain_id=ros_domain_id, timeout=60)
    assert info.returncode == 0, info.stdout
    assert 'Topic: /scan | Type: std_msgs/msg/String | Count: 3' in info.stdout
    assert 'Messages:          6' in info.stdout


@pytest.mark.parametrize('type_name', ['geometry_msgs/msg/Twist',
                                       'geometry_msgs/msg/TwistStamped'])
def test_ros2_bag_info_reads_refilter_commands_in_the_proposals_type(
        jazzy, tmp_path, ros_domain_id, type_name):
    import importlib.util

    from rcbf_ros.bag.refilter import refilter_bag
    spec = importlib.util.spec_from_file_location(
        'refilter_cases', REPO / 'test' / 'unit' / 'test_refilter.py')
    cases = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(cases)
    source = cases.write_twist_source(tmp_path / 'run', type_name)
    summary = refilter_bag(source, tmp_path / 'out', cases.PARAMS_B)
    info = jazzy.run(f'ros2 bag info {tmp_path / "out"}', domain_id=ros_domain_id, timeout=60)
    assert info.returncode == 0, info.stdout
    assert (f'Topic: /refilter/cmd_safe | Type: {type_name} | Count: {summary.processed} |'
            in info.stdout), info.stdout
    assert f'Topic: /cmd_proposed | Type: {type_name} | Count: {cases.N_STEPS} |' in info.stdout
