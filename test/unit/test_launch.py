"""The launch table, the ros2 launch file and the local launcher (real child processes, no DDS)."""
from __future__ import annotations

import ast
import io
import math
from pathlib import Path
import signal
import sys
import textwrap
import threading
import types

from hypothesis import given, settings
from hypothesis import strategies as st
import pytest
from repo_files import LAUNCH_FILES, REPO

from rcbf_ros.launch import local as launch_local
from rcbf_ros.launch import table
from rcbf_ros.launch.table import (
    Argument,
    argument_values,
    DROP_IN_FILTER,
    format_parameter,
    launch_setup,
    LaunchArgument,
    LAUNCHES,
    LaunchSetup,
    lockstep,
    NodeEntry,
    resolve_entry,
    respawn_settings,
    ros_arguments,
    substitute,
)
from rcbf_ros.parameters.arguments import parameter_overrides, parse_ros_arguments
from rcbf_ros.ros.loopback import LOOPBACK_CYCLONEDDS_URI

# --- table -------------------------------------------------------------------------------------

def test_unicycle_filter_table_wires_the_filter_between_controller_and_simulator():
    setup = launch_setup('unicycle_filter')
    assert [n.name for n in setup.nodes] == ['simulator', 'safety_filter', 'nominal_controller',
                                             'scene_markers', 'recorder']
    assert (REPO / 'config' / setup.config).is_file()
    assert setup.node('simulator').ends_launch
    with pytest.raises(KeyError, match='simulator'):
        setup.node('planner')
    with pytest.raises(ValueError, match='unknown launch'):
        launch_setup('mars_rover')


def test_a_launch_asked_to_record_fails_without_its_recorder():
    # Every node but the scene markers (a picture, not part of the loop) is required: a
    # recorder that cannot record fails the launch, it does not run on unrecorded
    # (``--without recorder`` is the way to run without one).
    for setup in LAUNCHES.values():
        if setup.name != 'safety_filter':   # the filter alone, in front of a robot
            assert setup.node('recorder').required, setup.name
        assert all(entry.required for entry in setup.nodes
                   if entry.name != 'scene_markers'), setup.name


def test_stop_limits_fit_what_each_node_does_on_exit():
    # Measured stop times (SIGINT to exit, a sibling SIGKILLed just before) are under 2 s for
    # the simulator, filter, controllers and recorder and 2.5 s for a training learner; the
    # recorder and learner write files on exit that grow with the run.
    for setup in LAUNCHES.values():
        limits = {entry.name: entry.sigint_timeout_s for entry in setup.nodes}
        assert limits.get('simulator', 5.0) == limits['safety_filter'] == 5.0
        assert limits.get('recorder', 10.0) == 10.0
        assert limits.get('learner', 30.0) == 30.0
    for bad in (0.0, -1.0, math.nan, math.inf, 3600.5):
        with pytest.raises(ValueError, match='sigint_timeout_s'):
            NodeEntry(name='x', executable='x', module='x', sigint_timeout_s=bad)


@pytest.mark.parametrize('option', ['--sigint-timeout', '--sigterm-timeout'])
@pytest.mark.parametrize('text', ['0', '-1', 'nan', 'inf', '1e300', '3600.5', 'soon'])
def test_escalation_timeouts_are_finite_and_refused_in_one_line(capsys, option, text):
    # an infinite (or a year's) timeout would leave a child that ignores its signals running
    with pytest.raises(SystemExit) as stopped:
        launch_local.main(['safety_filter', '--print', option, text])
    assert stopped.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].endswith(f"expected seconds > 0 and <= 3600, got '{text}'"), err
    assert launch_local.main(['safety_filter', '--print', option, '3600']) == 0


def test_every_table_module_has_a_console_script_of_the_same_name():
    from test_node_interfaces import _console_scripts
    scripts = _console_scripts()   # a node_main script: the node module it hands on to
    for setup in LAUNCHES.values():
        for entry in setup.nodes:
            assert scripts.get(entry.executable) == entry.module, entry.executable


@pytest.mark.parametrize('value, text', [
    (True, 'true'), (3, '3'), (0.5, '0.5'), ('a b', "'a b'"), ([1.0, 2.5], '[1.0, 2.5]'),
    (["it's"], "['it''s']"), ('1e3', "'1e3'"), ('yes', "'yes'"),
])
def test_parameter_text_round_trips_through_the_ros_argument_parser(value, text):
    assert format_parameter(value) == text
    parsed = parse_ros_arguments(['--ros-args', '-p', f'k:={text}'])
    assert parameter_overrides([parsed], '/any')['k'] == value


def test_ros_arguments_are_understood_by_the_ros_argument_parser():
    entry = NodeEntry(name='simulator', executable='simulator', module='m',
                      remappings=(('action', 'cmd_safe'),),
                      parameters=(('dt', 0.01), ('action_timeout_s', 10.0)))
    params_file = str(REPO / 'config' / 'unicycle.yaml')
    args = ros_arguments(entry, params_file=params_file, overrides={'dt': 0.05, 'seed': 3})
    parsed = parse_ros_arguments(args)
    assert parsed.node_name == 'simulator' and parsed.params_files == (params_file,)
    assert [(r.match, r.replacement) for r in parsed.remaps] == [('action', 'cmd_safe')]
    # The file's /simulator section sets dt, seed and action_timeout_s; the entry's parameters
    # and the command-line overrides win over it under rcl's rules, the overrides last.
    params = parameter_overrides([parsed], '/simulator')
    assert (params['dt'], params['seed'], params['action_timeout_s']) == (0.05, 3, 10.0)
    assert params['system'] == 'unicycle'


def test_child_commands_and_environment():
    setup = launch_setup('unicycle_filter')
    params_file = str(REPO / 'config' / 'unicycle.yaml')
    children = launch_local.child_commands(
        setup, params_file=params_file, overrides={'simulator': {'max_episodes': 1}},
        without=['recorder', 'scene_markers'], python='py')
    assert [c.name for c in children] == ['simulator', 'safety_filter', 'nominal_controller']
    sim = children[0]
    assert sim.command[:4] == ('py', '-m', 'rcbf_ros.ros.node_main', 'sim_nodes.simulator_node')
    assert sim.sigint_timeout_s == 5.0
    parsed = parse_ros_arguments(sim.command)
    # Without the recorder, the first episode does not wait for it.
    assert parsed.parameter_rules.sections()['simulator'] == {
        'wait_for_publishers': ['cmd_safe', 'cmd_proposed'], 'max_episodes': 1}
    recorded = launch_local.child_commands(setup, params_file=params_file, python='py')
    assert parse_ros_arguments(recorded[0].command).parameter_rules.sections()['simulator'][
        'wait_for_subscribers'] == ['recorder']
    assert parameter_overrides([parsed], '/simulator')['max_episodes'] == 1
    with pytest.raises(ValueError, match="no node 'planner'"):
        launch_local.child_commands(setup, params_file='p.yaml', without=['planner'])
    env = launch_local.child_environment({'CYCLONEDDS_URI': '<remote/>', 'PATH': '/bin'},
                                         domain_id=42)
    assert env['CYCLONEDDS_URI'] == LOOPBACK_CYCLONEDDS_URI and env['ROS_DOMAIN_ID'] == '42'
    assert env['PATH'] == '/bin' and str(REPO) in env['PYTHONPATH'].split(':')
    with pytest.raises(ValueError, match='domain_id'):
        launch_local.child_environment({}, domain_id=300)


# --- launch arguments --------------------------------------------------------------------------

def test_the_drop_in_filter_is_one_entry_shared_by_both_robot_launches():
    alone, demo = launch_setup('safety_filter'), launch_setup('unicycle_robot')
    assert alone.nodes == (DROP_IN_FILTER,)
    # The demo's lock-step simulator takes one answer per proposal: no re-filter at a state.
    assert demo.node('safety_filter') == lockstep(DROP_IN_FILTER) != DROP_IN_FILTER
    assert dict(demo.node('safety_filter').parameters)['refilter_on_state'] is False
    assert alone.arguments == demo.arguments
    assert [a.name for a in alone.arguments] == ['cmd_in', 'cmd_out', 'odom', 'command_type',
                                                 'respawn', 'respawn_delay']
    assert dict(DROP_IN_FILTER.remappings) == {
        'state': Argument('odom'), 'cmd_proposed': Argument('cmd_in'),
        'cmd_safe': Argument('cmd_out')}
    assert dict(DROP_IN_FILTER.parameters) == {'state_type': 'odometry',
                                               'command_type': Argument('command_type'),
                                               'refilter_on_state': True}
    assert (DROP_IN_FILTER.respawn, DROP_IN_FILTER.respawn_delay_s) == (
        Argument('respawn'), Argument('respawn_delay'))
    # The demo's robot and controller meet the filter on the same arguments.
    assert dict(demo.node('simulator').remappings) == {'state': Argument('odom'),
                                                       'cmd_safe': Argument('cmd_out')}
    assert dict(demo.node('nominal_controller').remappings) == {
        'state': Argument('odom'), 'cmd_proposed': Argument('cmd_in')}


def test_argument_values_take_defaults_and_refuse_unknown_names_and_choices():
    setup = launch_setup('safety_filter')
    assert argument_values(setup, {}) == {'cmd_in': 'cmd_vel_nav', 'cmd_out': 'cmd_vel',
                                          'odom': 'odom', 'command_type': 'twist',
                                          'respawn': 'false', 'respawn_delay': '1.0'}
    assert argument_values(setup, {'odom': '/x', 'params_file': 'p.yaml'})['odom'] == '/x'
    with pytest.raises(ValueError, match=r'unknown launch argument\(s\) cmd_inn, foo '
                                         r'\(arguments: cmd_in, cmd_out, odom, command_type, '
                                         r'respawn, respawn_delay'):
        argument_values(setup, {'foo': '1', 'cmd_inn': '/x'})
    with pytest.raises(ValueError, match="command_type:='twists' is not one of twist, "):
        argument_values(setup, {'command_type': 'twists'})


def test_resolved_entries_type_parameters_as_launch_ros_does():
    values = argument_values(launch_setup('unicycle_robot'), {'cmd_in': '/ctl/cmd'})
    robot = resolve_entry(launch_setup('unicycle_robot').node('simulator'), values)
    assert dict(robot.remappings) == {'state': 'odom', 'cmd_safe': 'cmd_vel'}
    assert dict(robot.parameters)['wait_for_publishers'] == ['cmd_safe', '/ctl/cmd']
    entry = NodeEntry(name='n', executable='n', module='m',
                      parameters=(('a', Argument('a')), ('b', Argument('b')),
                                  ('c', Argument('c'))))
    assert dict(resolve_entry(entry, {'a': '3', 'b': 'true', 'c': ''}).parameters) == {
        'a': 3, 'b': True, 'c': ''}


def test_a_launch_refuses_an_argument_it_does_not_declare():
    entry = NodeEntry(name='n', executable='n', module='m', remappings=(('a', Argument('x')),))
    with pytest.raises(ValueError, match="node n reads launch argument 'x'"):
        LaunchSetup(name='l', config='unicycle.yaml', nodes=(entry,))
    with pytest.raises(ValueError, match='declared twice'):
        LaunchSetup(name='l', config='unicycle.yaml', nodes=(entry,),
                    arguments=(LaunchArgument('x', '', ''), LaunchArgument('x', '', '')))
    with pytest.raises(ValueError, match='not one of'):
        LaunchArgument('k', 'c', '', choices=('a', 'b'))
    with pytest.raises(ValueError, match='params_file: every launch declares it'):
        LaunchArgument('params_file', '', '')
    with pytest.raises(ValueError, match='not resolved'):
        ros_arguments(entry, params_file='p.yaml')


def test_main_takes_launch_arguments_as_ros2_launch_does(capsys):
    assert launch_local.main(['safety_filter', '--print', 'cmd_in:=/ctl/cmd', 'odom:=/robot/odom',
                              'command_type:=twist_stamped']) == 0
    out = capsys.readouterr().out
    assert out.count('\n') == 1 and out.startswith('safety_filter: ')
    assert ('-r state:=/robot/odom -r cmd_proposed:=/ctl/cmd -r cmd_safe:=cmd_vel -p '
            "safety_filter:state_type:='odometry' -p "
            "safety_filter:command_type:='twist_stamped'") in out
    assert launch_local.main(['unicycle_robot', '--print', 'params_file:=/tmp/x.yaml']) == 2
    assert "--params-file '/tmp/x.yaml'" in capsys.readouterr().err   # checked like --params-file
    config = str(REPO / 'config' / 'unicycle.yaml')
    assert launch_local.main(['safety_filter', '--print', f'params_file:={config}']) == 0
    assert f'--params-file {config}' in capsys.readouterr().out


@pytest.mark.parametrize('arguments, message', [
    (['cmd_inn:=/x', 'foo:=1'], 'rcbf_ros launch: safety_filter: unknown launch argument(s) '
                                'cmd_inn, foo (arguments: cmd_in, cmd_out, odom, command_type, '
                                'respawn, respawn_delay, params_file)'),
    (['cmd_in=/x'], "rcbf_ros launch: launch argument 'cmd_in=/x': expected name:=value"),
    (['command_type:=Twist'], "rcbf_ros launch: safety_filter: launch argument "
                              "command_type:='Twist' is not one of twist, twist_stamped, array"),
    (['--params-file', 'a.yaml', 'params_file:=b.yaml'], 'the params file is given twice'),
    (['params_file:='], "--params-file '': "),
    (['cmd_in:='], "safety_filter: launch argument cmd_in:='': topic name must not be empty"),
    (['odom:=/robot odom'], "launch argument odom:='/robot odom': invalid topic name "
                            "'/robot odom': bad token 'robot odom'"),
])
def test_main_refuses_bad_launch_arguments_with_one_line(capsys, arguments, message):
    assert launch_local.main(['safety_filter', '--print', *arguments]) == 2
    captured = capsys.readouterr()
    assert captured.out == '' and message in captured.err
    assert captured.err.count('\n') == 1 and 'Traceback' not in captured.err


def test_show_args_lists_each_argument_with_its_default(capsys):
    assert launch_local.main(['safety_filter', '--show-args']) == 0
    out = capsys.readouterr().out
    for name, default in (('params_file', 'config/unicycle.yaml of the package'),
                          ('cmd_in', 'cmd_vel_nav'), ('cmd_out', 'cmd_vel'), ('odom', 'odom'),
                          ('command_type', 'twist')):
        assert f"    '{name}':" in out and f"(default: '{default}')" in out
    assert "Valid choices are: ['twist', 'twist_stamped', 'array']" in out


# --- ros2 launch file --------------------------------------------------------------------------

@pytest.mark.parametrize('launch_file', LAUNCH_FILES, ids=lambda p: p.name)
def test_launch_file_parses_and_reads_the_table(launch_file):
    tree = ast.parse(launch_file.read_text(), filename=str(launch_file))
    functions = {n.name for n in tree.body if isinstance(n, ast.FunctionDef)}
    assert 'generate_launch_description' in functions
    imported = {n.module for n in ast.walk(tree) if isinstance(n, ast.ImportFrom)}
    assert 'rcbf_ros.launch.description' in imported
    name = launch_file.name.removesuffix('.launch.py')
    names = [n.value for n in ast.walk(tree) if isinstance(n, ast.Constant)]
    assert name in names and name in LAUNCHES


def test_launch_files_cover_the_unicycle_launches():
    assert {p.name for p in LAUNCH_FILES} >= {'unicycle_filter.launch.py',
                                              'unicycle_learner.launch.py',
                                              'safety_filter.launch.py',
                                              'unicycle_robot.launch.py'}


class _Recorded:
    """Stands in for a launch action class: records its constructor arguments."""

    def __init__(self, *args, **kwargs):
        self.args, self.kwargs = args, kwargs


class _Configuration(_Recorded):
    """Stands in for ``LaunchConfiguration``: ``perform`` reads the context's value."""

    def perform(self, context):
        return context.launch_configurations[self.args[0]]


def _describe(monkeypatch, launch_file: Path, given: dict[str, str] | None = None):
    """What ``launch_file`` builds with recording stand-ins for ROS 2's launch packages (not
    installable here): the stand-in classes by name, the actions, and its nodes, those built
    in an ``OpaqueFunction`` included (run with the declared defaults, ``given`` over them)."""
    kinds = {}
    for name in ('LaunchDescription', 'DeclareLaunchArgument', 'Shutdown', 'Node',
                 'OpaqueFunction'):
        kinds[name] = type(name, (_Recorded,), {})
    kinds['LaunchConfiguration'] = type('LaunchConfiguration', (_Configuration,), {})
    modules = {
        'launch': {'LaunchDescription': kinds['LaunchDescription']},
        'launch.actions': {'DeclareLaunchArgument': kinds['DeclareLaunchArgument'],
                           'Shutdown': kinds['Shutdown'],
                           'OpaqueFunction': kinds['OpaqueFunction']},
        'launch.substitutions': {'LaunchConfiguration': kinds['LaunchConfiguration']},
        'launch_ros': {}, 'launch_ros.actions': {'Node': kinds['Node']},
        'ament_index_python': {},
        'ament_index_python.packages': {'get_package_share_directory': lambda p: f'/share/{p}'},
    }
    for module_name, attributes in modules.items():
        module = types.ModuleType(module_name)
        module.__dict__.update(attributes)
        monkeypatch.setitem(sys.modules, module_name, module)
    namespace: dict = {'__name__': 'launch_file'}
    exec(compile(launch_file.read_text(), str(launch_file), 'exec'), namespace)
    description = namespace['generate_launch_description']()
    actions = description.args[0]
    declared = [a for a in actions if isinstance(a, kinds['DeclareLaunchArgument'])]
    context = types.SimpleNamespace(launch_configurations={
        **{a.args[0]: a.kwargs['default_value'] for a in declared}, **(given or {})})
    nodes = []
    for action in actions:
        if isinstance(action, kinds['OpaqueFunction']):
            nodes.extend(action.kwargs['function'](context))
        elif isinstance(action, kinds['Node']):
            nodes.append(action)
    return kinds, actions, nodes


@pytest.mark.parametrize('launch_file', LAUNCH_FILES, ids=lambda p: p.name)
def test_launch_description_has_one_node_per_table_entry(monkeypatch, launch_file):
    kinds, actions, nodes = _describe(monkeypatch, launch_file)
    argument = actions[0]
    setup = launch_setup(launch_file.name.removesuffix('.launch.py'))
    assert argument.args[0] == 'params_file'
    assert argument.kwargs['default_value'] == f'/share/rcbf_ros/config/{setup.config}'
    declared = [a for a in actions if isinstance(a, kinds['DeclareLaunchArgument'])]
    assert [(a.args[0], a.kwargs['default_value'], a.kwargs.get('choices', []))
            for a in declared[1:]] == [(a.name, a.default, list(a.choices))
                                       for a in setup.arguments]

    def configuration(argument):   # the recorded LaunchConfiguration, by name
        return ('$', argument.name)

    def named(value):
        if isinstance(value, kinds['LaunchConfiguration']):
            return ('$', value.args[0])
        if isinstance(value, dict):
            return {key: named(v) for key, v in value.items()}
        if isinstance(value, (list, tuple)):
            return type(value)(named(v) for v in value)
        return value

    assert len(nodes) == len(setup.nodes)
    for node, entry in zip(nodes, setup.nodes):
        assert node.kwargs['package'] == 'rcbf_ros'
        assert node.kwargs['executable'] == entry.executable
        assert node.kwargs['name'] == entry.name
        assert named(node.kwargs['remappings']) == substitute(list(entry.remappings),
                                                              configuration)
        assert isinstance(node.kwargs['parameters'][0], kinds['LaunchConfiguration'])
        # A namespace makes launch_ros write the dict under the node's own name (its
        # _create_params_file_from_dict), which wins over the params file's section.
        assert node.kwargs['namespace'] == ''
        expected = {}
        for key, value in entry.parameters:
            if isinstance(value, list) and any(isinstance(v, Argument) for v in value):
                # launch_ros joins a list made only of substitutions into one string; a list
                # of one-item lists is a list of strings.
                value = [[item] for item in value]
            expected[key] = substitute(value, configuration)
        assert named(node.kwargs['parameters'][1:]) == (
            [expected] if entry.parameters else [])
        assert isinstance(node.kwargs['on_exit'], kinds['Shutdown']) == entry.ends_launch
        assert node.kwargs['sigterm_timeout'] == str(entry.sigint_timeout_s)
        assert (node.kwargs['respawn'], node.kwargs['respawn_delay']) == respawn_settings(
            entry, lambda a: next(d.default for d in setup.arguments if d.name == a.name))


# --- local launcher: real processes ------------------------------------------------------------

def _python(code: str) -> tuple[str, ...]:
    return (sys.executable, '-c', textwrap.dedent(code))


def _ready_then(tmp_path: Path, name: str, body: str) -> tuple[str, ...]:
    """A child that installs its signal handling, says so with a file, then runs ``body``."""
    return _python(f"""
        import pathlib, signal, sys, time
        {body.split('#handlers:')[0].strip()}
        pathlib.Path({str(tmp_path / name)!r}).touch()
        {body.split('#handlers:')[1].strip() if '#handlers:' in body else ''}
    """)


def _wait_for(tmp_path: Path, names: list[str], then: str) -> tuple[str, ...]:
    paths = [str(tmp_path / n) for n in names]
    return _python(f"""
        import os, sys, time
        while not all(os.path.exists(p) for p in {paths!r}):
            time.sleep(0.01)
        print('done waiting', flush=True)
        {then}
    """)


def _run(children, **kwargs):
    sink = io.StringIO()
    env = launch_local.child_environment(dict(__import__('os').environ), domain_id=0)
    # Generous timeouts: a child that handles SIGINT must get to exit even when the machine is
    # loaded (1 s was too short under a parallel CI load and escalated to SIGTERM); children
    # that ignore a signal just cost the timeout.
    outcome = launch_local.run_processes(children, env=env, sink=sink, sigint_timeout_s=6.0,
                                         sigterm_timeout_s=4.0, **kwargs)
    return outcome, sink.getvalue()


SLEEPER = 'pass\n#handlers:\ntime.sleep(60)'
IGNORES_SIGINT = 'signal.signal(signal.SIGINT, signal.SIG_IGN)\n#handlers:\ntime.sleep(60)'
IGNORES_BOTH = ('signal.signal(signal.SIGINT, signal.SIG_IGN); '
                'signal.signal(signal.SIGTERM, signal.SIG_IGN)\n#handlers:\ntime.sleep(60)')
EXITS_ON_SIGINT = ('signal.signal(signal.SIGINT, lambda *a: sys.exit(0))\n#handlers:\n'
                   'time.sleep(60)')


def test_designated_exit_stops_everyone_with_escalation_and_prefixed_output(tmp_path):
    children = [
        launch_local.ChildSpec('polite', _ready_then(tmp_path, 'polite', EXITS_ON_SIGINT)),
        launch_local.ChildSpec('stubborn', _ready_then(tmp_path, 'stubborn', IGNORES_SIGINT)),
        launch_local.ChildSpec('sim', _wait_for(tmp_path, ['polite', 'stubborn'], 'sys.exit(0)'),
                               ends_launch=True),
    ]
    outcome, output = _run(children)
    assert outcome.reason == 'sim exited (0)'
    assert outcome.escalations == {'polite': 'SIGINT', 'stubborn': 'SIGTERM'}
    assert outcome.returncodes == {'sim': 0, 'polite': 0, 'stubborn': -signal.SIGTERM}
    assert outcome.exit_code == 0 and not outcome.failed
    assert '[sim] done waiting' in output


def test_required_failure_fails_the_launch(tmp_path):
    children = [
        launch_local.ChildSpec('filter', _ready_then(tmp_path, 'filter', SLEEPER)),
        launch_local.ChildSpec('broken', _wait_for(tmp_path, ['filter'], 'sys.exit(3)')),
    ]
    outcome, output = _run(children)
    assert outcome.exit_code == 1 and outcome.failed == ['broken']
    assert outcome.returncodes['broken'] == 3 and outcome.escalations == {'filter': 'SIGINT'}
    assert '[launch] broken failed: exited with 3' in output


def test_optional_failure_does_not_fail_the_launch_and_a_kill_does(tmp_path):
    children = [
        launch_local.ChildSpec('recorder', _python('import sys; sys.exit(4)'), required=False),
        launch_local.ChildSpec('deaf', _ready_then(tmp_path, 'deaf', IGNORES_BOTH)),
        launch_local.ChildSpec('sim', _wait_for(tmp_path, ['deaf'], 'time.sleep(0.2)'),
                               ends_launch=True),
    ]
    outcome, output = _run(children)
    assert outcome.returncodes['recorder'] == 4
    assert outcome.escalations['deaf'] == 'SIGKILL' and outcome.failed == ['deaf']
    assert outcome.exit_code == 1 and 'did not stop' in output


def _stop_a_ready_sleeper(tmp_path: Path):
    """Launch one SLEEPER child and set the stop event once it is ready; the outcome."""
    stop = threading.Event()
    children = [launch_local.ChildSpec('node', _ready_then(tmp_path, 'node', SLEEPER))]
    timer = threading.Thread(target=lambda: (_wait_file(tmp_path / 'node'), stop.set()))
    timer.start()
    outcome, _ = _run(children, stop_event=stop)
    timer.join()
    return outcome


def test_stop_event_stops_the_launch(tmp_path):
    outcome = _stop_a_ready_sleeper(tmp_path)
    assert outcome.reason == 'stop requested' and outcome.exit_code == 0
    assert outcome.returncodes['node'] == -signal.SIGINT  # Python's default: KeyboardInterrupt


def test_children_get_sigint_back_when_the_launcher_was_started_in_the_background(tmp_path):
    # A shell starts a background job with SIGINT ignored and exec keeps it ignored: a child
    # that inherited that would sit out the launcher's SIGINT (escalation to SIGTERM, -15).
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        outcome = _stop_a_ready_sleeper(tmp_path)
    finally:
        signal.signal(signal.SIGINT, previous)
    assert outcome.escalations == {'node': 'SIGINT'}
    assert outcome.returncodes['node'] == -signal.SIGINT


def _wait_file(path: Path) -> None:
    import time
    while not path.exists():
        time.sleep(0.01)


def test_main_prints_commands_and_rejects_unknown_nodes(capsys):
    assert launch_local.main(['unicycle_filter', '--print', '-p', 'simulator:seed:=4',
                              '--domain-id', '5']) == 0
    out = capsys.readouterr().out
    assert 'simulator: ' in out and '-p simulator:seed:=4' in out
    assert '__node:=safety_filter' in out
    assert launch_local.main(['unicycle_filter', '--print', '-p', 'planner:x:=1']) == 2
    with pytest.raises(SystemExit):
        launch_local.main(['unicycle_filter', '-p', 'no_equals_sign'])


def test_each_child_gets_its_own_limit_from_sigint_to_sigterm(tmp_path):
    # 'deaf' ignores SIGINT and has a short limit: it gets SIGTERM after it, while 'waiter',
    # which stops only once 'deaf' is gone, still has its own (long) limit. With one limit for
    # every child both would be sent SIGTERM together.
    deaf = _python(f"""
        import os, pathlib, signal, time
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        pathlib.Path({str(tmp_path / 'deaf.pid')!r}).write_text(str(os.getpid()))
        time.sleep(60)
    """)
    waiter = _python(f"""
        import os, pathlib, signal, sys, time
        deaf = pathlib.Path({str(tmp_path / 'deaf.pid')!r})
        def gone(pid):
            try:
                return open(f'/proc/{{pid}}/stat').read().split()[2] == 'Z'
            except OSError:
                return True
        def on_sigint(*_):
            pid = int(deaf.read_text())
            while not gone(pid):
                time.sleep(0.02)
            sys.exit(0)
        signal.signal(signal.SIGINT, on_sigint)
        pathlib.Path({str(tmp_path / 'waiter')!r}).touch()
        time.sleep(60)
    """)
    children = [
        launch_local.ChildSpec('deaf', deaf, sigint_timeout_s=0.3),
        launch_local.ChildSpec('waiter', waiter),
        launch_local.ChildSpec('sim', _wait_for(tmp_path, ['deaf.pid', 'waiter'], 'sys.exit(0)'),
                               ends_launch=True),
    ]
    outcome, _ = _run(children)
    assert outcome.escalations == {'deaf': 'SIGTERM', 'waiter': 'SIGINT'}
    assert outcome.returncodes['waiter'] == 0 and outcome.exit_code == 0


def test_a_required_child_that_dies_as_the_stop_begins_still_fails_the_launch(tmp_path):
    stop = threading.Event()
    children = [launch_local.ChildSpec('node', _ready_then(tmp_path, 'node',
                                                           'pass\n#handlers:\nsys.exit(3)'))]

    def stop_once_it_died():
        _wait_file(tmp_path / 'node')
        import time
        time.sleep(0.5)
        stop.set()

    thread = threading.Thread(target=stop_once_it_died)
    thread.start()
    outcome, _ = _run(children, stop_event=stop, poll_s=2.0)
    thread.join()
    assert outcome.returncodes['node'] == 3 and outcome.failed == ['node']
    assert outcome.exit_code == 1


# --- respawn ----------------------------------------------------------------------------------

def test_respawn_is_off_by_default_and_reaches_both_launchers_alike(monkeypatch):
    launch_file = REPO / 'launch' / 'safety_filter.launch.py'
    setup = launch_setup('safety_filter')
    for arguments, expected in (({}, (False, 1.0)),
                            ({'respawn': 'true', 'respawn_delay': '0.5'}, (True, 0.5)),
                            ({'respawn': 'True', 'respawn_delay': '0'}, (True, 0.0)),
                            ({'respawn': '0'}, (False, 1.0))):
        _, _, (node,) = _describe(monkeypatch, launch_file, arguments)
        assert (node.kwargs['respawn'], node.kwargs['respawn_delay']) == expected, arguments
        (child,) = launch_local.child_commands(setup, params_file='p.yaml', arguments=arguments)
        assert (child.respawn, child.respawn_delay_s) == expected, arguments
    # Only the drop-in filter respawns: every other entry keeps launch_ros's default.
    for other in LAUNCHES.values():
        for entry in other.nodes:
            if entry not in (DROP_IN_FILTER, lockstep(DROP_IN_FILTER)):
                assert (entry.respawn, entry.respawn_delay_s) == (False, 0.0), entry.name


@pytest.mark.parametrize('name, expected', [('safety_filter', True),
                                            ('unicycle_robot', False),
                                            ('unicycle_lidar', True)])
def test_refilter_on_state_reaches_both_launchers_alike(monkeypatch, name, expected):
    """On in front of a robot, off in front of the demo's lock-step simulator: ros2 launch's
    node and the local launcher's command line set the same value."""
    _, _, nodes = _describe(monkeypatch, REPO / 'launch' / f'{name}.launch.py')
    (node,) = [n for n in nodes if n.kwargs['name'] == 'safety_filter']
    assert node.kwargs['parameters'][1]['refilter_on_state'] is expected
    (child,) = [c for c in launch_local.child_commands(launch_setup(name), params_file='p.yaml')
                if c.name == 'safety_filter']
    flag = f'safety_filter:refilter_on_state:={format_parameter(expected)}'
    assert flag in child.command and 'refilter_on_state' not in ' '.join(
        item for item in child.command if item != flag)


@pytest.mark.parametrize('argument, text, message', [
    ('respawn', 'maybe', "launch argument respawn:='maybe': expected true or false"),
    ('respawn', '', "launch argument respawn:='': expected true or false"),
    ('respawn', '[true]', "launch argument respawn:='[true]': expected true or false"),
    ('respawn_delay', '-1', "launch argument respawn_delay:='-1': expected seconds >= 0"),
    ('respawn_delay', 'nan', "launch argument respawn_delay:='nan': expected seconds >= 0"),
    ('respawn_delay', 'inf', "launch argument respawn_delay:='inf': expected seconds >= 0"),
    ('respawn_delay', '1 s', "launch argument respawn_delay:='1 s': expected seconds >= 0"),
])
def test_a_bad_respawn_argument_is_refused_alike_by_both_launchers(monkeypatch, capsys,
                                                                   argument, text, message):
    assert launch_local.main(['safety_filter', '--print', f'{argument}:={text}']) == 2
    captured = capsys.readouterr()
    assert captured.out == '' and captured.err == (
        f'rcbf_ros launch: safety_filter: {message}\n')
    with pytest.raises(ValueError) as refused:   # ros2 launch: its OpaqueFunction raises
        _describe(monkeypatch, REPO / 'launch' / 'safety_filter.launch.py', {argument: text})
    assert str(refused.value) == message


@settings(max_examples=300, deadline=None)
@given(text=st.text(max_size=12) | st.sampled_from(['1', '0', 'true', 'FALSE', 'yes', 'off',
                                                     '1e3', '0.0', '-0.0', '1e309']))
def test_respawn_texts_read_as_a_setting_or_one_line(text):
    for read, kind in ((table.launch_bool, bool), (table.respawn_delay, float)):
        try:
            value = read('x', text)
        except ValueError as exc:
            assert str(exc).startswith(f'x:={text!r}: expected ') and '\n' not in str(exc)
            continue
        assert type(value) is kind
        if kind is float:
            assert value >= 0.0 and value < float('inf')


def _respawner(tmp_path: Path, name: str, *, runs_before_it_stays: int) -> tuple[str, ...]:
    """A child that exits with 3 on its first ``runs_before_it_stays`` starts (counted in a
    file), then says so with the file ``<name>.stays`` and sleeps."""
    count = tmp_path / f'{name}.runs'
    return _python(f"""
        import pathlib, sys, time
        count = pathlib.Path({str(count)!r})
        runs = int(count.read_text()) + 1 if count.exists() else 1
        count.write_text(str(runs))
        if runs <= {runs_before_it_stays}:
            sys.exit(3)
        pathlib.Path({str(tmp_path / (name + '.stays'))!r}).touch()
        time.sleep(60)
    """)


def test_a_respawning_child_is_started_again_and_its_exit_fails_nothing(tmp_path):
    children = [
        launch_local.ChildSpec('filter', _respawner(tmp_path, 'filter', runs_before_it_stays=2),
                               respawn=True, respawn_delay_s=0.0),
        launch_local.ChildSpec('sim', _wait_for(tmp_path, ['filter.stays'], 'sys.exit(0)'),
                               ends_launch=True),
    ]
    outcome, output = _run(children)
    assert outcome.respawns == {'filter': 2} and (tmp_path / 'filter.runs').read_text() == '3'
    assert outcome.exit_code == 0 and not outcome.failed, output
    assert output.count('[launch] filter exited with 3; respawning in 0 s') == 2
    assert output.count('[launch] respawning filter') == 2
    assert outcome.escalations == {'filter': 'SIGINT'}   # the third run, stopped at the end
    assert "respawns {'filter': 2}; exit code 0" in output


def test_a_child_that_ends_the_launch_is_not_respawned(tmp_path):
    children = [launch_local.ChildSpec('sim', _python('import sys; sys.exit(0)'),
                                       ends_launch=True, respawn=True)]
    outcome, output = _run(children)
    assert outcome.reason == 'sim exited (0)' and outcome.respawns == {}
    assert 'respawning' not in output


def test_a_stop_during_the_respawn_delay_starts_nothing_more(tmp_path):
    stop = threading.Event()
    sink = io.StringIO()
    children = [launch_local.ChildSpec('filter', _python('import sys; sys.exit(3)'),
                                       respawn=True, respawn_delay_s=60.0)]

    def stop_when_waiting():
        while 'respawning in 60 s' not in sink.getvalue():
            import time
            time.sleep(0.01)
        stop.set()

    thread = threading.Thread(target=stop_when_waiting, daemon=True)
    thread.start()
    env = launch_local.child_environment(dict(__import__('os').environ), domain_id=0)
    outcome = launch_local.run_processes(children, env=env, sink=sink, stop_event=stop)
    thread.join(timeout=5)
    assert outcome.reason == 'stop requested' and outcome.respawns == {}
    assert outcome.returncodes == {'filter': 3} and outcome.exit_code == 0
    assert '[launch] respawning filter' not in sink.getvalue()


# --- params file: refused before any node starts -----------------------------------------------

BAD_PARAMS = {
    'missing': (None, 'No such file or directory'),
    'directory': ('', 'not a regular file (a directory)'),
    'not_utf8': (b'\xff\xfe\x00', 'not UTF-8'),
    'not_yaml': ('a: [1\n', 'not valid YAML at line 2'),
    'two_documents': ('a: 1\n---\nb: 2\n', "'a' has no ros__parameters"),
    'a_list': ('- 1\n- 2\n', 'top level must map node names'),
    'no_ros__parameters': ('/simulator:\n  seed: 3\n', 'has no ros__parameters'),
    'ros__parameters_not_a_mapping': ('/simulator:\n  ros__parameters: 3\n', 'must be a mapping'),
    'no_section_for_these_nodes': ('/planner:\n  ros__parameters: {a: 1}\n', 'no section'),
    'empty': ('', 'no section'),
}


def _params_file(tmp_path: Path, kind: str) -> Path:
    content, _ = BAD_PARAMS[kind]
    path = tmp_path / f'{kind}.yaml'
    if kind == 'directory':
        path.mkdir()
    elif isinstance(content, bytes):
        path.write_bytes(content)
    elif content is not None:
        path.write_text(content)
    return path


@pytest.mark.parametrize('kind', sorted(BAD_PARAMS))
def test_a_bad_params_file_is_refused_in_one_line_before_any_node_starts(tmp_path, monkeypatch,
                                                                        capsys, kind):
    def no_process(*args, **kwargs):
        raise AssertionError(f'a process was started: {args[0]}')

    monkeypatch.setattr(launch_local.subprocess, 'Popen', no_process)
    path = _params_file(tmp_path, kind)
    for extra in ([], ['--print']):
        assert launch_local.main(['unicycle_filter', '--params-file', str(path), *extra]) == 2
        captured = capsys.readouterr()
        assert captured.out == ''
        lines = captured.err.splitlines()
        assert len(lines) == 1, captured.err
        assert lines[0].startswith('rcbf_ros launch: --params-file')
        assert str(path) in lines[0] and BAD_PARAMS[kind][1] in lines[0]


def test_params_files_that_configure_a_node_of_the_launch_are_accepted(tmp_path):
    setup = launch_setup('unicycle_filter')
    launch_local.check_params_file(setup, REPO / 'config' / 'unicycle.yaml')
    for text in ('/**:\n  ros__parameters: {seed: 1}\n',
                 'simulator:\n  ros__parameters: {seed: 1}\n',
                 '/**/recorder:\n  ros__parameters: {output: b}\n'):
        path = tmp_path / 'p.yaml'
        path.write_text(text)
        launch_local.check_params_file(setup, path)


class _ExitsOnSecondPoll:
    """A process stand-in that is running at its first poll and has exited from the second."""

    def __init__(self, code: int) -> None:
        self.pid, self.polls, self.code = 0, 0, code
        self.returncode: int | None = None

    def poll(self) -> int | None:
        self.polls += 1
        if self.polls >= 2:
            self.returncode = self.code
        return self.returncode


def test_stopping_records_every_return_code_even_of_a_process_exiting_meanwhile(monkeypatch):
    # A process that exits between two looks at it must still be in `return codes {...}`.
    monkeypatch.setattr(launch_local, '_signal_group', lambda process, signum: None)
    processes = {'quick': _ExitsOnSecondPoll(0), 'slow': _ExitsOnSecondPoll(-2)}
    processes['slow'].polls = -3  # running for a few more looks
    outcome = launch_local.LaunchOutcome(exit_code=0)
    launch_local._stop_all(processes, outcome, {'quick': 5.0, 'slow': 5.0}, 3.0, 0.0,
                           lambda line: None)
    assert outcome.returncodes == {'quick': 0, 'slow': -2}
    assert outcome.escalations == {'quick': 'SIGINT', 'slow': 'SIGINT'}
