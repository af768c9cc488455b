"""The package built with colcon as README.md says, run by ros2 run and ros2 launch on rclpy.

The overlay (:mod:`colcon_overlay`) follows README.md "On a ROS 2 Jazzy machine".
"""
from __future__ import annotations

import re
from typing import Callable

from colcon_overlay import Overlay, overlay_fixture, stop_group, wait_for
import pytest
import yaml

pytestmark = pytest.mark.ros2
overlay = overlay_fixture()


def _param(overlay: Overlay, verb: str, node: str, names: str, domain_id: int
           ) -> Callable[[], str | None]:
    def check() -> str | None:
        done = overlay.jazzy.run(f'ros2 param {verb} --no-daemon {node} {names}',
                                 domain_id=domain_id, timeout=60)
        return done.stdout if done.returncode == 0 else None
    return check


def test_the_nodes_start_on_rclpy_with_the_pvtol_config(overlay, tmp_path, ros_domain_id):
    """pvtol.yaml (no empty lists): every node starts; descriptors describe each parameter."""
    config = overlay.share() / 'config' / 'pvtol.yaml'
    nodes = {
        'safety_filter': '', 'simulator': '', 'nominal_controller': '',
        'learner': f'-p learner:out_dir:={tmp_path / "learner"}',
    }
    processes = {
        name: overlay.jazzy.start(overlay.script(
            f'ros2 run rcbf_ros {name} --ros-args --params-file {config} {extra}'),
            domain_id=ros_domain_id, log=tmp_path / f'{name}.log')
        for name, extra in nodes.items()}
    try:
        described = wait_for(_param(
            overlay, 'describe', '/safety_filter',
            'max_state_age_s qos.reliable qos.depth bands.tilt.index', ros_domain_id),
            90, 'ros2 param describe /safety_filter')
        for name, kind in (('max_state_age_s', 'double'), ('qos.reliable', 'boolean'),
                           ('qos.depth', 'integer'), ('bands.tilt.index', 'integer')):
            assert f'Parameter name: {name}\n  Type: {kind}\n' in described, described
        for name in nodes:
            wait_for(lambda n=name: '' if 'INFO' in (tmp_path / f'{n}.log').read_text()
                      else None, 90, f'{name} started')
            assert processes[name].poll() is None, (tmp_path / f'{name}.log').read_text()
    finally:
        codes = {name: stop_group(process) for name, process in processes.items()}
    logs = {name: (tmp_path / f'{name}.log').read_text() for name in nodes}
    assert all(code == 0 for code in codes.values()), (codes, logs)
    assert not any('Traceback' in log for log in logs.values()), logs


def test_the_recorder_takes_a_topic_list_on_rclpy(overlay, tmp_path, ros_domain_id):
    bag = tmp_path / 'bag'
    recorder = overlay.jazzy.start(overlay.script(
        f"ros2 run rcbf_ros recorder --ros-args -p 'topics:=[/state, /other]' -p output:={bag}"),
        domain_id=ros_domain_id, log=tmp_path / 'recorder.log')
    try:
        got = wait_for(_param(overlay, 'get', '/recorder', 'topics', ros_domain_id), 90,
                        'ros2 param get /recorder topics')
    finally:
        code = stop_group(recorder)
    assert "String values are: ['/state', '/other']" in got
    assert code == 0, (tmp_path / 'recorder.log').read_text()


def test_the_learner_launch_runs_and_its_own_parameters_win(overlay, tmp_path, ros_domain_id):
    """ros2 launch of unicycle_learner to its end; the table's action_timeout_s: 10.0 for the
    simulator wins over the params file's /simulator section (1.0) under rcl's rules."""
    params = yaml.safe_load((overlay.share() / 'config' / 'unicycle.yaml').read_text())
    assert params['/simulator']['ros__parameters']['action_timeout_s'] == 1.0
    params['/simulator']['ros__parameters'].update(max_steps=150, max_episodes=0)
    params['/learner']['ros__parameters'].update(
        episodes=1, start_steps=40, update_after=40, batch_size=16, gp_refit_interval=100,
        out_dir=str(tmp_path / 'learner'))
    params['/recorder'] = {'ros__parameters': {'output': str(tmp_path / 'bag')}}
    params_file = tmp_path / 'params.yaml'
    params_file.write_text(yaml.safe_dump(params))
    launch = overlay.jazzy.start(overlay.script(
        f'ros2 launch rcbf_ros unicycle_learner.launch.py params_file:={params_file}'),
        domain_id=ros_domain_id, log=tmp_path / 'launch.log')
    try:
        got = wait_for(_param(overlay, 'get', '/simulator', 'action_timeout_s', ros_domain_id),
                        90, 'ros2 param get /simulator action_timeout_s')
        launch.wait(timeout=240)
    finally:
        code = stop_group(launch)
    log = (tmp_path / 'launch.log').read_text()
    assert 'Double value is: 10.0' in got, got
    assert code == 0 and 'Traceback' not in log, log[-4000:]
    assert re.search(r'\[learner-\d+\] .*episode +1/1 ', log), log[-4000:]
    info = overlay.jazzy.run(f'ros2 bag info {tmp_path / "bag"}', domain_id=ros_domain_id)
    assert info.returncode == 0 and 'Topic: /cmd_safe' in info.stdout, info.stdout
