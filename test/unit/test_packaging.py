"""The package as installed: configs found in every layout, ROS dependencies declared."""
from __future__ import annotations

import ast
import importlib
from pathlib import Path
import re
import shutil
import subprocess
import sys
import sysconfig
import xml.etree.ElementTree as ET

REPO = Path(__file__).resolve().parents[2]
SOURCES = [*(REPO / 'rcbf_ros').rglob('*.py'), *(REPO / 'sim_nodes').rglob('*.py'),
           *(REPO / 'launch').glob('*.py')]
# Our Cyclone runtime and the middleware-free message classes name messages for themselves
# (e.g. the defaults Jazzy's .msg files declare); on ROS the nodes use rclpy's own classes.
FALLBACK = (REPO / 'rcbf_ros' / 'ros' / 'dds', REPO / 'rcbf_ros' / 'messages' / 'classes.py')
ROS_PYTHON_PACKAGES = {'rclpy', 'rcl_interfaces', 'rosidl_runtime_py', 'ament_index_python',
                       'launch', 'launch_ros', 'launch_testing', 'rosbag2_py', 'ros2cli'}
TYPE_NAME = re.compile(r'^([a-z][a-z0-9_]*(?:_msgs|_interfaces))/(?:msg/)?[A-Z][A-Za-z0-9]*$')


def _run(command: list[str], **kwargs) -> subprocess.CompletedProcess:
    done = subprocess.run(command, capture_output=True, text=True, timeout=300, **kwargs)
    assert done.returncode == 0, done.stdout + done.stderr
    return done


def test_a_wheel_installed_with_pip_finds_its_configs(tmp_path):
    """A real, non-editable pip install into a fresh venv, used from outside the source tree."""
    source = tmp_path / 'source'  # a clean copy: no build/ left over from another build
    source.mkdir()
    for name in ('setup.py', 'setup.cfg', 'package.xml', 'README.md'):
        shutil.copy2(REPO / name, source / name)
    for name in ('rcbf_ros', 'sim_nodes', 'config', 'launch', 'resource'):
        shutil.copytree(REPO / name, source / name,
                        ignore=shutil.ignore_patterns('__pycache__', '*.egg-info'))
    wheels = tmp_path / 'wheels'
    _run([sys.executable, '-m', 'pip', 'wheel', '-q', '--no-deps', '--no-build-isolation',
          '-w', str(wheels), str(source)])
    venv = tmp_path / 'venv'
    _run([getattr(sys, '_base_executable', sys.executable), '-m', 'venv', '--without-pip',
          str(venv)])
    python = venv / 'bin' / 'python'
    _run([sys.executable, '-m', 'pip', '--python', str(python), 'install', '-q', '--no-deps',
          *map(str, wheels.glob('*.whl'))])
    site = Path(_run([str(python), '-c', 'import sysconfig; print(sysconfig.get_path("purelib"))'
                      ]).stdout.strip())
    # Dependencies (PyYAML) from this environment, after the venv's own site-packages.
    (site / 'dependencies.pth').write_text(sysconfig.get_path('purelib') + '\n')
    done = _run([str(python), '-c', 'import rcbf_ros.parameters.rules as p; '
                 'print(p.find_config("pvtol"));'
                 ' print(p.find_config("unicycle.yaml")); print(p.__file__)'],
                cwd=tmp_path, env={'PATH': '/usr/bin:/bin'})
    pvtol, unicycle, module = (Path(line) for line in done.stdout.split())
    assert module.is_relative_to(site), module
    assert pvtol == site / 'rcbf_ros' / 'config' / 'pvtol.yaml'
    assert pvtol.read_bytes() == (REPO / 'config' / 'pvtol.yaml').read_bytes()
    assert unicycle.parent == pvtol.parent


def test_the_source_tree_finds_its_configs():
    from rcbf_ros.parameters.rules import find_config
    assert find_config('car_following') == REPO / 'config' / 'car_following.yaml'


def _ros_names_used() -> dict[str, set[str]]:
    """ROS package -> the files that import it or name one of its message types."""
    used: dict[str, set[str]] = {}
    for path in SOURCES:
        if any(path.is_relative_to(part) for part in FALLBACK):
            continue
        tree = ast.parse(path.read_text(), filename=str(path))
        for node in ast.walk(tree):
            names: list[str] = []
            if isinstance(node, ast.Import):
                names = [alias.name.split('.')[0] for alias in node.names]
            elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                names = [node.module.split('.')[0]]
            elif isinstance(node, ast.Constant) and isinstance(node.value, str):
                match = TYPE_NAME.match(node.value)
                names = [match.group(1)] if match else []
            for name in names:
                if name in ROS_PYTHON_PACKAGES or name.endswith(('_msgs', '_interfaces')):
                    used.setdefault(name, set()).add(str(path.relative_to(REPO)))
    return used


def test_package_xml_declares_every_ros_package_the_code_uses():
    root = ET.parse(REPO / 'package.xml').getroot()
    declared = {e.text for e in root if e.tag in ('depend', 'exec_depend')}
    used = _ros_names_used()
    assert {'rclpy', 'rcl_interfaces', 'rosidl_runtime_py', 'ament_index_python', 'std_msgs',
            'visualization_msgs'} <= set(used)
    missing = {name: sorted(files) for name, files in used.items() if name not in declared}
    assert not missing, f'package.xml lacks {missing}'


def test_package_xml_points_only_at_files_that_exist():
    text = (REPO / 'package.xml').read_text()
    for name in re.findall(r'[\w./-]+\.(?:txt|md|py|cfg|toml)\b', text):
        assert (REPO / name).exists() or name.startswith('test/'), name


def _console_scripts() -> dict[str, str]:
    """setup.py's console_scripts, name -> 'module:function', read without running setup()."""
    tree = ast.parse((REPO / 'setup.py').read_text())
    for node in ast.walk(tree):
        if isinstance(node, ast.Dict):
            for key, value in zip(node.keys, node.values):
                if isinstance(key, ast.Constant) and key.value == 'console_scripts':
                    entries = [ast.literal_eval(item) for item in value.elts]
                    return dict(tuple(part.strip() for part in entry.split('=', 1))
                                for entry in entries)
    raise AssertionError('setup.py declares no console_scripts')


def test_every_console_script_points_at_a_function_that_exists():
    scripts = _console_scripts()
    assert {'rcbf_ros', 'rcbf_ros_launch', 'rcbf_ros_refilter', 'safety_filter'} <= set(scripts)
    for name, target in scripts.items():
        module_name, _, function = target.partition(':')
        module = importlib.import_module(module_name)
        assert callable(getattr(module, function, None)), f'{name} = {target}'


def test_the_old_console_scripts_are_the_rcbf_ros_subcommands(monkeypatch):
    """rcbf_ros_launch and rcbf_ros_refilter run what rcbf_ros launch / refilter run, through
    rcbf_ros's own entry (its stdout guard included)."""
    from rcbf_ros.cli import main as cli
    scripts = _console_scripts()
    assert scripts['rcbf_ros'] == 'rcbf_ros.cli.main:main'
    for alias, subcommand in (('rcbf_ros_launch', 'launch'), ('rcbf_ros_refilter', 'refilter')):
        module_name, _, function = scripts[alias].partition(':')
        assert module_name == 'rcbf_ros.cli.main'
        ran: list = []
        monkeypatch.setattr(cli, '_run', ran.append)  # returns None: exit status 0
        monkeypatch.setattr(sys, 'argv', [alias, '--x', 'y'])
        assert not getattr(cli, function)()
        assert ran == [[subcommand, '--x', 'y']]
