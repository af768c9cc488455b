"""One table of systems: every consumer draws its list of systems, and every fact of a system,
from :mod:`rcbf_ros.messages.systems`; no other module keeps a table keyed by system names.

A fourth system registered here (its entry, a dynamics class and an env class that declare its
name, nothing else) must show in the CLI's choices, the dynamics loader, the env factory, the
config lookup, the message layouts and the nominal controller.
"""
from __future__ import annotations

import argparse
import ast
from pathlib import Path
from typing import Iterator

import numpy as np
import pytest

from rcbf_ros.core.config import build_system
from rcbf_ros.core.dynamics import load_system, Unicycle
from rcbf_ros.envs import env_class, make_env, UnicycleEnv
from rcbf_ros.messages import conversions, systems
from rcbf_ros.parameters.rules import find_config, load_params

ROOT = Path(__file__).resolve().parents[2]
TABLE = ROOT / 'rcbf_ros' / 'messages' / 'systems.py'
FAKE = 'fourth_system'

NOT_SYSTEM_FACTS = {
    'rcbf_ros/experiments/definitions.py': "the paper's experiment matrix (methods per system)",
    'rcbf_ros/experiments/report.py': "the paper's published figures per system",
    'rcbf_ros/experiments/command.py': "the experiments' --systems: the paper's systems",
    'rcbf_ros/node_logic/scene.py': 'a marker drawing per shipped system; another system gets '
                                    'the default drawing (a sphere at its position)',
}
"""Modules allowed to key by system names, and why: what they hold is not a fact a new system
must give (the drift a new system would meet here is a missing picture, not a missing path)."""


@pytest.fixture
def fourth_system() -> Iterator[tuple[type, type]]:
    """A system the package does not ship: an entry, and a dynamics and an env class that
    declare its name (the unicycle's maths, the unicycle's params file)."""
    systems.register(systems.System(
        FAKE, state=(('x', 'm'), ('y', 'm'), ('theta', 'rad')), command=(('v', 'm/s'),
                                                                         ('omega', 'rad/s')),
        odometry='[x, y, yaw]', config='unicycle.yaml'))
    try:
        class FourthDynamics(Unicycle):
            system_name = FAKE

        class FourthEnv(UnicycleEnv):
            system_name = FAKE

        yield FourthDynamics, FourthEnv
    finally:
        systems.unregister(FAKE)


def _fake_params(section: str) -> dict:
    params = load_params(find_config('unicycle'), section)
    params['system'] = FAKE
    return params


def test_a_registered_system_reaches_every_consumer(fourth_system):
    dynamics, env = fourth_system
    from rcbf_ros.cli.train import add_train_arguments
    parser = argparse.ArgumentParser()
    add_train_arguments(parser)
    assert parser.parse_args(['--system', FAKE]).system == FAKE
    assert type(load_system(FAKE)) is dynamics
    assert type(build_system({'system': FAKE})) is dynamics
    assert env_class(FAKE) is env
    assert type(make_env(FAKE, _fake_params('simulator'))) is env
    assert systems.lookup(FAKE).config_path() == find_config('unicycle')
    assert conversions.STATE_LAYOUTS[FAKE][2] == ('theta', 'rad')
    assert conversions.COMMAND_LAYOUTS[FAKE] == (('v', 'm/s'), ('omega', 'rad/s'))
    conversions.check_odometry_support(FAKE)
    controller = env.nominal_controller(_fake_params('nominal_controller'))
    assert controller(np.zeros(3)).shape == (2,)
    from sim_nodes.packaged import packaged_parameters, system_from_argv
    assert packaged_parameters(FAKE, 'simulator') == packaged_parameters('unicycle', 'simulator')
    assert system_from_argv(['--ros-args', '-p', f'system:={FAKE}']) == FAKE


def test_a_system_leaves_no_trace_once_unregistered(fourth_system):
    systems.unregister(FAKE)
    from rcbf_ros.cli.train import add_train_arguments
    parser = argparse.ArgumentParser()
    add_train_arguments(parser)
    with pytest.raises(SystemExit):
        parser.parse_args(['--system', FAKE])
    with pytest.raises(ValueError, match=f"^system: unknown system '{FAKE}'"):
        load_system(FAKE)
    with pytest.raises(ValueError, match=f"^system: no simulator for '{FAKE}'"):
        env_class(FAKE)
    assert FAKE not in conversions.STATE_LAYOUTS


@pytest.mark.parametrize('name', systems.system_names())
def test_every_shipped_system_has_all_its_parts(name):
    entry = systems.lookup(name)
    dynamics, env = entry.part('dynamics'), entry.part('env')
    assert dynamics.system_name == env.system_name == name
    assert entry.config_path().is_file()
    params = load_params(entry.config_path(), 'simulator')
    assert params['system'] == name  # the file's own name for the system
    sim = make_env(name, params)
    system = load_system(name, {})
    assert len(entry.state) >= system.n_x == sim.nominal_system.n_x  # PVTOL: x_h optional
    assert len(entry.command) == system.n_u
    controller = env.nominal_controller(load_params(entry.config_path(), 'nominal_controller'))
    assert controller(sim.reset(seed=0)[1]['state']).shape == (system.n_u,)
    assert (sim.torch_models() is None) == (name == 'car_following')  # no state-only obs


def test_a_name_is_registered_once_and_a_part_must_exist():
    with pytest.raises(ValueError, match="^system: 'unicycle' is in the table already"):
        systems.register(systems.System('unicycle', state=(), command=()))
    with pytest.raises(ValueError, match='^system: a table name is an identifier'):
        systems.System('a.b', state=(), command=())
    entry = systems.System('bare', state=(), command=())
    with pytest.raises(ValueError, match="^system: no env declares system_name 'bare'"):
        entry.part('env')


def test_a_subclass_that_keeps_its_parents_name_does_not_take_its_place():
    class Tweaked(Unicycle):
        pass

    assert systems.lookup('unicycle').part('dynamics') is Unicycle
    assert type(load_system('unicycle')) is Unicycle is not Tweaked


def _sources() -> list[Path]:
    return sorted([*ROOT.glob('rcbf_ros/**/*.py'), *ROOT.glob('sim_nodes/*.py')])


def _names(node: ast.AST) -> set[str]:
    return {n.value for n in getattr(node, 'keys', getattr(node, 'elts', []))
            if isinstance(n, ast.Constant) and isinstance(n.value, str)}


def _tables_of_systems(path: Path) -> list[str]:
    """Dict literals keyed by two system names, and list / tuple / set literals that hold
    every shipped name (a hand-kept list of systems)."""
    shipped = {'unicycle', 'pvtol', 'car_following'}
    found = []
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        names = _names(node) if isinstance(node, (ast.Dict, ast.List, ast.Tuple, ast.Set)) \
            else set()
        if (isinstance(node, ast.Dict) and {'unicycle', 'pvtol'} <= names) or shipped <= names:
            found.append(f'line {node.lineno}: {type(node).__name__.lower()} of '
                         f'{sorted(names & shipped)}')
    return found


def test_the_oracle_finds_a_table_keyed_by_system_names(tmp_path):
    sample = tmp_path / 'sample.py'
    sample.write_text("A = {'unicycle': 1, 'pvtol': 2}\nB = ['unicycle', 'pvtol', "
                      "'car_following']\nC = {'unicycle': 1}\nD = ('unicycle', 'pvtol')\n")
    assert [line.split(':')[0] for line in _tables_of_systems(sample)] == ['line 1', 'line 2']


@pytest.mark.parametrize('path', _sources(), ids=lambda p: str(p.relative_to(ROOT)))
def test_no_other_module_keeps_a_table_of_systems(path):
    relative = str(path.relative_to(ROOT))
    if path == TABLE or relative in NOT_SYSTEM_FACTS:
        return
    assert _tables_of_systems(path) == [], (
        f'{relative} keys by system names: draw from rcbf_ros.messages.systems instead')


def test_the_allowed_modules_still_exist_and_still_need_it():
    for relative in NOT_SYSTEM_FACTS:
        assert _tables_of_systems(ROOT / relative), f'{relative}: drop it from NOT_SYSTEM_FACTS'
