"""The safety filter's path runs without PyTorch: every module but learning's imports, the filter
node starts, and the filter, the simulated systems and the nominal controllers answer on the
three systems exactly as with torch installed; the install's ``filter`` set holds no torch and
brings what these modules import; a user's system that needs torch says how to install it.

torch is made unimportable in a child process (a meta path finder that refuses it, as a robot
computer without the wheel would); the answers there are compared with this process's. The
nodes and commands as processes: test/integration/test_lean_nodes.py.
"""
from __future__ import annotations

import importlib.metadata
import json
import os
from pathlib import Path
import re
import runpy
import subprocess
import sys
import tempfile
import textwrap

import numpy as np

from rcbf_ros.core.config import filter_config_from_params
from rcbf_ros.envs import make_env
from rcbf_ros.node_logic import safety_filter as logic
from rcbf_ros.parameters.rules import find_config, load_params
from sim_nodes.nominal_controller_node import controller_from_params

SYSTEMS = ('unicycle', 'pvtol', 'car_following')
REPO = Path(__file__).resolve().parents[2]

LEARNING_MODULES = ('rcbf_ros.cli.train', 'rcbf_ros.core.diffqp', 'rcbf_ros.experiments',
                    'rcbf_ros.learning', 'rcbf_ros.ros.learner_node', 'rcbf_ros.ros.policy_node',
                    'rcbf_ros.training')
"""The modules that need torch (learning, training, experiments; package.xml's python3-torch):
every other module of the package imports without it."""

_BLOCK_TORCH = textwrap.dedent("""
    import sys

    class _NoTorch:
        def find_spec(self, name, path=None, target=None):
            if name == 'torch' or name.startswith('torch.'):
                raise ModuleNotFoundError(f'No module named {name!r}', name=name)

    sys.meta_path.insert(0, _NoTorch())
""")

_CHILD = _BLOCK_TORCH + textwrap.dedent("""
    import json
    import test_lean_filter as lean
    import rcbf_ros.ros.safety_filter_node  # noqa: F401 - the node's whole import chain
    from rcbf_ros.ros.dds import rclpy_compat as rclpy
    from rcbf_ros.ros.safety_filter_node import SafetyFilterNode
    answers = {system: lean.answers(system) for system in lean.SYSTEMS}
    runs = {system: lean.simulated_run(system) for system in lean.SYSTEMS}
    rclpy.init(args=['--ros-args', '--params-file', str(lean.find_config('pvtol'))],
               domain_id=int(sys.argv[1]))
    node = SafetyFilterNode()
    started = node.filter.n_x
    node.destroy_node()
    rclpy.try_shutdown()
    refused = lean.import_every_module()
    print(json.dumps({'answers': answers, 'started': started, 'runs': runs,
                      'refused': refused, 'third_party': lean.third_party_modules(),
                      'torch': 'torch' in sys.modules}))
""")


def answers(system: str) -> list[list]:
    """The filter of ``system``'s packaged config at 40 seeded states and proposals: each
    answer's command, status and slack."""
    active = logic.build_active_filter(params=load_params(find_config(system), 'safety_filter'))
    safety_filter = active.safety_filter
    rng = np.random.default_rng(7)
    out = []
    for _ in range(40):
        state = rng.uniform(-2.0, 2.0, safety_filter.n_x)
        proposal = rng.uniform(-3.0, 3.0, safety_filter.n_u)
        std = np.abs(rng.normal(0.0, 0.05, safety_filter.n_x))
        result = safety_filter.filter(state, proposal, np.zeros(safety_filter.n_x), std)
        out.append([result.u_safe.tolist(), result.status, float(result.slack)])
    return out


def simulated_run(system: str) -> dict[str, list]:
    """40 seeded steps of ``system``'s simulator driven by its nominal controller through the
    filter (the loop the filter launches run): the states, the proposals, and the barrier
    values of the states as refilter reports them."""
    from rcbf_ros.core.lie_closed_form import state_barrier_values
    config = find_config(system)
    env = make_env(system, load_params(config, 'simulator'))
    controller = controller_from_params(load_params(config, 'nominal_controller'))
    safety_filter = logic.build_active_filter(
        params=load_params(config, 'safety_filter')).safety_filter
    state = env.reset(seed=3)[1]['state']
    states, proposals = [state.tolist()], []
    for _ in range(40):
        proposal = np.asarray(controller(state), dtype=np.float64)
        answer = safety_filter.filter(state, proposal, np.zeros(state.size),
                                      np.zeros(state.size))
        state = env.step(answer.u_safe)[4]['state']
        states.append(state.tolist())
        proposals.append(proposal.tolist())
    h = state_barrier_values(safety_filter.problem, np.array(states))
    return {'states': states, 'proposals': proposals, 'h': h.tolist()}


def import_every_module() -> list[str]:
    """Import every module of rcbf_ros and sim_nodes; the names of those that fail to."""
    import importlib
    import pkgutil
    failed = []
    for package in ('rcbf_ros', 'sim_nodes'):
        path = importlib.import_module(package).__path__
        for info in pkgutil.walk_packages(path, f'{package}.'):
            if info.name.endswith('.__main__'):  # it runs the command
                continue
            try:
                importlib.import_module(info.name)
            except ImportError:
                failed.append(info.name)
    return sorted(failed)


def third_party_modules() -> list[str]:
    """The top-level modules loaded now from files that are neither the standard library's nor
    ours (not the names an extension makes up, e.g. Cython's ``cython_runtime``)."""
    ours = {'rcbf_ros', 'sim_nodes', 'test_lean_filter'}
    loaded = {name for name, module in list(sys.modules.items())
              if '.' not in name and not name.startswith('_')
              and getattr(module, '__file__', None)}
    return sorted(loaded - set(sys.stdlib_module_names) - ours)


_REPORTS: dict[str, dict] = {}


def _lean_report(domain_id: int) -> dict:
    """What the child without torch reports (run once per test process)."""
    if 'report' not in _REPORTS:
        with tempfile.TemporaryDirectory() as cwd:
            child = subprocess.run([sys.executable, '-c', _CHILD, str(domain_id)],
                                   capture_output=True, text=True, timeout=300, cwd=cwd,
                                   env=_env_with_tests())
        assert child.returncode == 0, child.stderr[-3000:]
        _REPORTS['report'] = json.loads(child.stdout.strip().splitlines()[-1])
    return _REPORTS['report']


def test_the_filter_runs_without_torch_and_answers_as_with_it(ros_domain_id):
    report = _lean_report(ros_domain_id)
    assert report['torch'] is False
    assert report['started'] == 7  # PVTOL with its operator
    for system in SYSTEMS:
        ours = answers(system)
        theirs = report['answers'][system]
        used_fallback = [i for i, (_, status, _) in enumerate(ours)
                         if status == 'solved_interior_point']
        assert len(used_fallback) <= 2, used_fallback  # the comparison covers the usual path
        for index, (mine, other) in enumerate(zip(ours, theirs)):
            if index in used_fallback:  # no torch: no interior point, the fail-safe instead
                assert other[1] == 'unverified', other
                continue
            assert mine[1] == other[1], (system, index)
            np.testing.assert_array_equal(mine[0], other[0])
        assert {status for _, status, _ in ours} - {'slack_exceeded'}, system  # not all refused


def test_every_module_but_learning_imports_without_torch(ros_domain_id):
    refused = _lean_report(ros_domain_id)['refused']
    assert refused, 'the learning modules imported without torch: is torch refused at all?'
    assert [name for name in refused if not name.startswith(LEARNING_MODULES)] == []


def test_simulators_and_controllers_run_without_torch_as_with_it(ros_domain_id):
    import torch  # here, not at the top: the child without torch imports this module
    runs = _lean_report(ros_domain_id)['runs']
    for system in SYSTEMS:
        ours = simulated_run(system)
        assert ours['states'] == runs[system]['states'], system  # bit for bit
        assert ours['proposals'] == runs[system]['proposals'], system
        # refilter's barrier values (closed form there) are state_h of the autograd path
        problem = filter_config_from_params(
            load_params(find_config(system), 'safety_filter')).problem
        state_h = problem.state_h(torch.tensor(ours['states'], dtype=torch.float64))
        np.testing.assert_allclose(runs[system]['h'], state_h.detach().numpy(),
                                   rtol=1e-12, atol=1e-12)


def _setup_keywords() -> dict:
    """The keyword arguments setup.py gives ``setuptools.setup`` (setup.py run, setup()
    caught)."""
    import setuptools
    caught: dict = {}
    original, here = setuptools.setup, os.getcwd()
    setuptools.setup = lambda **keywords: caught.update(keywords)
    os.chdir(REPO)  # its data_files glob relative paths
    try:
        runpy.run_path(str(REPO / 'setup.py'))
    finally:
        setuptools.setup = original
        os.chdir(here)
    return caught


def _name(requirement: str) -> str:
    """A requirement's distribution name, normalized (PEP 503)."""
    name = re.match(r'[A-Za-z0-9._-]+', requirement).group()
    return re.sub(r'[-_.]+', '-', name).lower()


def _with_dependencies(names: set[str]) -> set[str]:
    """``names`` and everything they require, as installed here (extras left out)."""
    todo, found = list(names), set()
    while todo:
        name = todo.pop()
        if name in found:
            continue
        found.add(name)
        try:
            requires = importlib.metadata.requires(name) or []
        except importlib.metadata.PackageNotFoundError:
            continue
        todo += [_name(r) for r in requires if 'extra ==' not in r]
    return found


def test_the_filter_install_holds_no_torch_and_what_the_filter_path_imports(ros_domain_id):
    keywords = _setup_keywords()
    extras = keywords['extras_require']
    base = {_name(r) for r in [*keywords['install_requires'], *extras['filter']]}
    assert not base & {'torch', 'gpytorch'}, base
    base_and = {extra: {_name(r) for r in [*keywords['install_requires'], *extras[extra]]}
                for extra in ('learning', 'standalone')}
    learning = base_and['learning']
    assert {'torch', 'gpytorch'} <= learning and base <= learning  # learning: filter and more
    assert learning <= base_and['standalone']
    # What the modules imported without torch (the child) comes with the filter set.
    provided = _with_dependencies(base)
    distributions = importlib.metadata.packages_distributions()
    at_start = set(json.loads(subprocess.run(  # .pth files import some at interpreter start
        [sys.executable, '-c', 'import json, sys; print(json.dumps(list(sys.modules)))'],
        capture_output=True, text=True, check=True).stdout))
    missing = {module: distributions.get(module)
               for module in _lean_report(ros_domain_id)['third_party']
               if module not in at_start
               and not any(_name(d) in provided for d in distributions.get(module, []))}
    assert not missing, f'imported without torch, not in the filter set: {missing}'


def test_what_needs_torch_says_how_to_install_it(tmp_path):
    child = subprocess.run(
        [sys.executable, '-c', _BLOCK_TORCH + textwrap.dedent("""
            from rcbf_ros.core import rcbf
            try:
                rcbf.torch.zeros(1)
            except ImportError as exc:
                print(exc)
            """)], capture_output=True, text=True, timeout=120, env=_env_with_tests())
    assert child.returncode == 0, child.stderr[-2000:]
    line = child.stdout.strip()
    assert '\n' not in line and line.startswith('PyTorch is needed here') and (
        'pip install torch' in line), line


USER_SYSTEMS = {
    # Not a built-in type: no closed form, so the filter assembles through autograd.
    'my_system.py': textwrap.dedent('''
        from dataclasses import dataclass

        from rcbf_ros.core.dynamics import Unicycle


        @dataclass(frozen=True)
        class MyUnicycle(Unicycle):
            """A user's system."""
        '''),
    # A user's module that imports torch itself.
    'torch_system.py': 'import torch  # noqa: F401\nfrom my_system import MyUnicycle\n',
}

_USER_CHILD = _BLOCK_TORCH + textwrap.dedent("""
    import json
    from rcbf_ros.envs import env_class
    from rcbf_ros.node_logic import safety_filter as logic
    from rcbf_ros.parameters.rules import find_config, load_params
    errors = []
    for system in ('my_system.MyUnicycle', 'torch_system.MyUnicycle'):
        params = dict(load_params(find_config('unicycle'), 'safety_filter'), system=system)
        try:
            logic.build_active_filter(params=params)
            errors.append(None)
        except (ImportError, ValueError) as exc:
            errors.append(str(exc))
    try:
        env_class('torch_system.MyUnicycle')
        errors.append(None)
    except ValueError as exc:
        errors.append(str(exc))
    print(json.dumps({'errors': errors, 'torch': 'torch' in sys.modules}))
""")


def test_a_user_system_that_needs_torch_is_refused_in_one_line_without_it(tmp_path):
    """Without torch such a filter is refused when it is built (the node and refilter stop
    with this line, exit status 2), and so is a user's module that imports torch."""
    for name, text in USER_SYSTEMS.items():
        (tmp_path / name).write_text(text)
    child = subprocess.run([sys.executable, '-c', _USER_CHILD], capture_output=True,
                           text=True, timeout=120, cwd=str(tmp_path),
                           env=_env_with_tests(str(tmp_path)))
    assert child.returncode == 0, child.stderr[-2000:]
    report = json.loads(child.stdout.strip().splitlines()[-1])
    assert report['torch'] is False
    assert None not in report['errors'], report
    for line in report['errors']:
        assert '\n' not in line and 'PyTorch is needed here' in line, line
        assert 'pip install torch' in line and 'python3-torch' in line, line
    assert report['errors'][1].startswith("system: cannot import 'torch_system.MyUnicycle'")
    # With torch, the same user system builds and filters (the autograd assembly).
    sys.path.insert(0, str(tmp_path))
    try:
        params = dict(load_params(find_config('unicycle'), 'safety_filter'),
                      system='my_system.MyUnicycle')
        active = logic.build_active_filter(params=params)
    finally:
        sys.path.remove(str(tmp_path))
        sys.modules.pop('my_system', None)
    assert active.safety_filter.assembly == 'autograd'


def _env_with_tests(*more: str) -> dict[str, str]:
    """This environment, with this directory (the child imports this module), the repository
    and ``more`` importable."""
    here = str(Path(__file__).resolve().parent)
    path = os.pathsep.join(p for p in (here, str(REPO), *more, os.environ.get('PYTHONPATH', ''))
                           if p)
    return {**os.environ, 'PYTHONPATH': path}
