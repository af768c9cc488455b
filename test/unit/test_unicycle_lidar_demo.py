"""The ``unicycle_lidar`` demo's wiring and params file: the filter sees only its robot's scan,
through the robot's frames, with the base's body and limits (no processes)."""
from __future__ import annotations

from repo_files import REPO

from rcbf_ros.core.config import filter_config_from_params
from rcbf_ros.launch.table import (
    Argument,
    argument_values,
    DROP_IN_FILTER,
    launch_setup,
    resolve_entry,
)
from rcbf_ros.parameters.rules import load_params
from sim_nodes import lidar_world as lw
from sim_nodes.unicycle_lidar_node import (
    build_world,
    settings_from_params,
    TOPICS,
    unicycle_lidar_interface,
)

CONFIG = REPO / 'config' / 'unicycle_lidar.yaml'


def test_the_filter_sees_the_scan_only_with_the_base_s_body_and_limits():
    params = load_params(CONFIG, 'safety_filter')
    config = filter_config_from_params(params)
    assert config.problem.n_barriers == 0   # no obstacles given: the scan is the only source
    ((name, source),) = config.sources.sources
    assert (name, source.type, source.topic) == ('scan', 'scan', 'scan')
    base = lw.BaseModel()
    assert params['footprint.radius'] == base.radius
    assert params['input_limits.min'] == [-base.v_max, -base.omega_max]
    assert params['input_limits.max'] == [base.v_max, base.omega_max]


def test_the_robot_s_frames_are_the_filter_s_and_its_laser_sits_off_base_link():
    robot = load_params(CONFIG, 'unicycle_lidar')
    settings = settings_from_params(robot)
    sources = filter_config_from_params(load_params(CONFIG, 'safety_filter')).sources
    assert (settings.odom_frame_id, settings.base_frame_id) == (sources.odom_frame_id,
                                                                sources.base_frame_id)
    assert settings.laser_frame_id not in (settings.odom_frame_id, settings.base_frame_id)
    assert settings.laser_mount[0] > 0.0   # tf's base_link -> laser is no identity
    world = build_world(settings, robot)
    assert len(world.circles) == 5 and lw.clearance(world, world.start[:2])[0] > 0.2


def test_the_launch_puts_the_drop_in_filter_between_controller_and_base():
    setup = launch_setup('unicycle_lidar')
    assert setup.config == CONFIG.name
    assert setup.node('safety_filter') == DROP_IN_FILTER   # refilter_on_state, respawn
    robot, controller = setup.node('unicycle_lidar'), setup.node('nominal_controller')
    assert dict(robot.remappings) == {'odom': Argument('odom'), 'cmd_vel': Argument('cmd_out')}
    assert dict(controller.remappings) == {'state': Argument('odom'),
                                           'cmd_proposed': Argument('cmd_in')}
    assert dict(controller.parameters)['state_type'] == 'odometry'
    assert 'scan' in {topic.name for topic in TOPICS}   # the source's topic, not remapped
    assert [a.choices for a in setup.arguments if a.name == 'command_type'] == [('twist',)]


def test_a_command_type_the_base_does_not_take_is_refused_in_one_line(capsys):
    from rcbf_ros.launch import local as launch_local
    assert launch_local.main(['unicycle_lidar', 'command_type:=twist_stamped', '--print']) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["rcbf_ros launch: unicycle_lidar: launch argument "
                   "command_type:='twist_stamped' is not one of twist"], err


def test_the_launch_draws_the_scene_from_the_robot_and_the_filter():
    """The scene node of the lidar launch: each topic it reads but ``obstacles`` (none in this
    demo) is published in the launch, after every node's remaps at the arguments' defaults, in
    the type it reads; its state is the filter's; its markers are recorded."""
    from rcbf_ros.node_logic.interface import DIAGNOSTIC_ARRAY, FLOAT64_MULTIARRAY
    from rcbf_ros.node_logic.safety_filter_interface import INTERFACE as FILTER
    from rcbf_ros.ros.scene_node import INTERFACE as SCENE
    setup = launch_setup('unicycle_lidar')
    nodes = {entry.name: resolve_entry(entry, argument_values(setup, {}))
             for entry in setup.nodes}
    assert list(nodes).index('scene_markers') < list(nodes).index('recorder')
    scene = nodes['scene_markers']
    assert not scene.required   # a picture: its failure stops nothing

    def topic(node: str, name: str) -> str:
        name = dict(nodes[node].remappings).get(name, name)
        return name if name.startswith('/') else f'/{name}'

    published: dict[str, set[str]] = {}
    for node, interface in (('unicycle_lidar', unicycle_lidar_interface()),
                            ('safety_filter', FILTER), ('scene_markers', SCENE)):
        for spec in interface.topics:
            if spec.direction == 'pub':
                published.setdefault(topic(node, spec.name), set()).add(spec.type)
    reads = {spec.name: topic('scene_markers', spec.name) for spec in SCENE.topics
             if spec.direction == 'sub' and spec.name != 'obstacles'}
    assert reads == {'state': '/odom', 'diagnostics': '/diagnostics',
                     'filter_info': '/filter_info'}
    assert published[reads['state']] == {'nav_msgs/msg/Odometry'}
    assert published[reads['diagnostics']] == {DIAGNOSTIC_ARRAY}
    assert published[reads['filter_info']] == {FLOAT64_MULTIARRAY}
    assert reads['state'] == topic('safety_filter', 'state')
    assert dict(scene.parameters)['state_type'] == 'odometry' == dict(
        nodes['safety_filter'].parameters)['state_type']
    assert '/world_markers' in published and '/scene_markers' in published
    assert not load_params(CONFIG, 'recorder').get('topics')   # every topic recorded


def test_the_lidar_foxglove_layout_shows_the_scan_and_the_scene_in_odom():
    """``config/foxglove_layout_lidar.json``: one 3D panel in the filter's state frame with the
    scan, the scene and the ground truth; the plots read topics and data indexes the demo
    publishes (the commands on the launch's defaults, filter_info's u_s and fail_safe)."""
    import json

    from rcbf_ros.core.filter_info import INFO_SECTIONS
    layout = json.loads((REPO / 'config' / 'foxglove_layout_lidar.json').read_text())
    panels = layout['configById']

    def leaves(node):
        return [node] if isinstance(node, str) else leaves(node['first']) + leaves(
            node['second'])
    assert sorted(leaves(layout['layout'])) == sorted(panels)   # every panel placed, once
    (scene,) = [config for name, config in panels.items() if name.startswith('3D!')]
    odom = filter_config_from_params(load_params(CONFIG, 'safety_filter')).sources.odom_frame_id
    assert scene['followTf'] == odom == scene['layers']['grid']['frameId']
    assert all(scene['topics'][topic]['visible']
               for topic in ('/scan', '/scene_markers', '/world_markers'))
    values = argument_values(launch_setup('unicycle_lidar'), {})
    n_u = 2
    start = {label: sum(n_u if size == 'n_u' else 1 for _, size, _ in INFO_SECTIONS[:i])
             for i, (label, _, _) in enumerate(INFO_SECTIONS[:5])}
    allowed = {f'/{values["cmd_in"]}.linear.x', f'/{values["cmd_in"]}.angular.z',
               f'/{values["cmd_out"]}.linear.x', f'/{values["cmd_out"]}.angular.z',
               *(f'/filter_info.data[{start["u_s"] + i}]' for i in range(n_u)),
               f'/filter_info.data[{start["fail_safe"]}]'}
    plotted = {p['value'] for name, config in panels.items() if name.startswith('Plot!')
               for p in config['paths']}
    assert plotted == allowed


def test_the_robot_starts_once_the_recorder_listens_and_alone_without_one():
    """The first half second, with the filter's first fail-safe answers, was not in the bag:
    the robot waits for the recorder on every topic it publishes and on its commands."""
    from rcbf_ros.launch import local as launch_local
    from rcbf_ros.parameters.arguments import parse_ros_arguments
    setup = launch_setup('unicycle_lidar')
    assert dict(setup.node('unicycle_lidar').parameters)['wait_for_subscribers'] == [
        'recorder']

    def robot_parameters(**kwargs):
        children = launch_local.child_commands(setup, params_file=str(CONFIG), python='py',
                                               **kwargs)
        (robot,) = [c for c in children if c.name == 'unicycle_lidar']
        return parse_ros_arguments(robot.command).parameter_rules.sections().get(
            'unicycle_lidar', {})
    assert robot_parameters()['wait_for_subscribers'] == ['recorder']
    assert 'wait_for_subscribers' not in robot_parameters(without=['recorder'])


def test_what_the_robot_waits_for_is_the_first_topic_a_named_node_lacks():
    from sim_nodes.unicycle_lidar_node import WAITED, waits_for
    topics = ('/odom', '/scan', '/tf', '/cmd_out')
    assert len(WAITED) == len(topics)
    every = {topic: True for topic in topics}
    assert waits_for({}) == ''
    assert waits_for({'recorder': every}) == ''
    assert waits_for({'recorder': {**every, '/tf': False}}) == 'recorder to subscribe to /tf'
    assert waits_for({'recorder': every, 'logger': {**every, '/scan': False}}) == (
        'logger to subscribe to /scan')
    assert settings_from_params({}).wait_for_subscribers == ()
