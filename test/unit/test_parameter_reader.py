"""The typed parameter reader: every field type, defaults from the dataclass, errors naming the
key, nested and optional groups."""
from __future__ import annotations

from dataclasses import dataclass, field
import subprocess
import sys

from hypothesis import given
from hypothesis import strategies as st
import numpy as np
import pytest

from rcbf_ros.parameters.reader import (
    defaults_of,
    parameter_keys,
    ParameterError,
    parameters_of,
    read_parameters,
    setting,
)


@dataclass(frozen=True)
class Limits:
    """A nested group."""

    state: float = setting(1e6, positive=True, description='largest |x|')
    depth: int = setting(10, minimum=1, strict=True)


@dataclass(frozen=True)
class Extra:
    """An optional group, read when ``extra.x`` is set."""

    x: tuple[float, ...] = ()
    margin: float = setting(0.0, minimum=0)


@dataclass(frozen=True)
class Settings:
    """One field of every supported type."""

    name: str
    rate: float = setting(50.0, positive=True)
    count: int = setting(3, minimum=0)
    enabled: bool = False
    word: bool = setting(True, text_bool=True)
    mode: str = setting('fast', choices=('fast', 'slow'))
    goal: tuple[float, ...] = setting((1.0, 2.0), length=2)
    indices: tuple[int, ...] = (0, 1)
    fields: tuple[str, ...] = setting(('a',), choices=('a', 'b', 'c'), nonempty=True,
                                      distinct=True)
    weights: tuple[float, ...] | None = None
    frame: str = setting('map', key='frame.id')
    limits: Limits = field(default_factory=Limits)
    extra: Extra | None = setting(None, when='x')


def test_defaults_come_from_the_dataclass() -> None:
    settings = read_parameters(Settings, {'name': 'n'})
    assert settings == Settings(name='n')
    assert defaults_of(Settings)['rate'] == 50.0
    assert defaults_of(Settings)['limits.depth'] == 10
    assert 'name' not in defaults_of(Settings)  # required: no default


def test_every_type_is_read() -> None:
    settings = read_parameters(Settings, {
        'name': 'n', 'rate': '2.5', 'count': 4.0, 'enabled': True, 'word': 'FALSE',
        'mode': 'slow', 'goal': [3, 4], 'indices': np.array([2, 3]), 'fields': ['b', 'c'],
        'weights': [1.0], 'frame.id': 'odom', 'limits.state': 7, 'limits.depth': 2,
        'extra.x': [1.0], 'extra.margin': 0.5, 'unrelated.key': object()})
    assert settings.rate == 2.5 and settings.count == 4 and isinstance(settings.count, int)
    assert settings.enabled is True and settings.word is False and settings.mode == 'slow'
    assert settings.goal == (3.0, 4.0) and settings.indices == (2, 3)
    assert settings.fields == ('b', 'c') and settings.weights == (1.0,)
    assert settings.frame == 'odom'
    assert settings.limits == Limits(state=7.0, depth=2)
    assert settings.extra == Extra(x=(1.0,), margin=0.5)


def test_optional_group_is_read_only_when_its_key_is_set() -> None:
    assert read_parameters(Settings, {'name': 'n', 'extra.margin': 'junk'}).extra is None
    assert read_parameters(Settings, {'name': 'n', 'extra.x': []}).extra is None
    with pytest.raises(ParameterError, match=r'^extra\.margin: must be >= 0, got -1'):
        read_parameters(Settings, {'name': 'n', 'extra.x': [1.0], 'extra.margin': -1.0})


def test_none_keeps_an_optional_field_unset() -> None:
    assert read_parameters(Settings, {'name': 'n', 'weights': None}).weights is None


@pytest.mark.parametrize('key, value, why', [
    ('name', 3, 'expected a string, got 3'),
    ('rate', True, 'expected a number, got True'),
    ('rate', 'fast', "expected a number, got 'fast'"),
    ('rate', float('nan'), 'must be finite'),
    ('rate', 0.0, 'must be > 0, got 0.0'),
    ('count', 1.5, 'expected an integer, got 1.5'),
    ('count', True, 'expected an integer, got True'),
    ('count', -1, 'must be >= 0, got -1'),
    ('enabled', 'true', "expected true or false, got 'true'"),
    ('enabled', 1, 'expected true or false, got 1'),
    ('word', 'yes', "expected true or false, got 'yes'"),
    ('mode', 'medium', "expected one of ['fast', 'slow'], got 'medium'"),
    ('goal', [1.0], 'expected 2 values, got 1'),
    ('goal', [1.0, float('inf')], 'contains NaN or inf'),
    ('goal', 'ab', "expected a list of numbers, got 'ab'"),
    ('goal', [True, 1.0], 'expected a list of numbers'),
    ('indices', [0.5], 'expected an integer, got 0.5'),
    ('fields', 'a', "expected a list of strings, got 'a'"),
    ('fields', ['a', 'z'], "['z'] not in ['a', 'b', 'c']"),
    ('fields', ['a', 'a'], "repeated value in ['a', 'a']"),
    ('fields', [], 'must not be empty'),
    ('frame.id', 1.0, 'expected a string, got 1.0'),
    ('limits.state', -2, 'must be > 0, got -2'),
    ('limits.depth', 2.0, 'expected an integer, got 2.0'),
    ('limits.depth', 0, 'must be >= 1, got 0'),
])
def test_errors_are_one_line_naming_the_key(key: str, value: object, why: str) -> None:
    with pytest.raises(ParameterError) as info:
        read_parameters(Settings, {'name': 'n', key: value})
    message = str(info.value)
    assert message == f'{key}: {why}' or message.startswith(f'{key}: {why}'), message
    assert '\n' not in message
    assert isinstance(info.value, ValueError)  # what the nodes turn into "exit 2"


def test_a_required_key_missing_is_named() -> None:
    with pytest.raises(ParameterError, match=r'^name: required$'):
        read_parameters(Settings, {})


def test_prefix_names_the_full_key() -> None:
    with pytest.raises(ParameterError, match=r'^input_bounds\.state: must be > 0'):
        read_parameters(Limits, {'input_bounds.state': 0.0}, prefix='input_bounds.')


def test_parameters_are_listed_with_their_full_keys_in_field_order() -> None:
    keys = parameter_keys(Settings)
    assert keys[:3] == ('name', 'rate', 'count')
    assert 'frame.id' in keys and 'limits.state' in keys and 'extra.margin' in keys
    by_key = {p.key: p for p in parameters_of(Settings)}
    assert by_key['name'].required and not by_key['rate'].required
    assert by_key['limits.state'].rule.description == 'largest |x|'


def test_the_reader_is_a_leaf() -> None:
    """rcbf_ros.parameters imports nothing else of rcbf_ros (any layer may use it)."""
    code = ('import sys, rcbf_ros.parameters.reader, rcbf_ros.parameters.rules; '
            "print(sorted(m for m in sys.modules if m.startswith('rcbf_ros') "
            "and not m.startswith('rcbf_ros.parameters')))")
    out = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True,
                         check=True).stdout.strip()
    assert out == "['rcbf_ros']"


# --- the readers built on it ------------------------------------------------------------------

def _every_group(unicycle: dict) -> dict:
    """A unicycle configuration with every barrier group set (each group's keys are read)."""
    return {**unicycle, 'gaps.a': [0], 'gaps.b': [1], 'gaps.delta': 0.1,
            'walls.nx': [1.0], 'walls.ny': [0.0], 'walls.offset': [-10.0]}


def test_every_filter_key_is_read_and_named_when_bad() -> None:
    """FILTER_PARAMETER_KEYS is derived from FilterParameters; each key is really read by
    filter_config_from_params (a wrong type there is refused naming exactly that key)."""
    from rcbf_ros.core.config import filter_config_from_params
    from rcbf_ros.node_logic.safety_filter import FILTER_PARAMETER_KEYS
    from rcbf_ros.parameters.rules import find_config, load_params
    params = _every_group(load_params(find_config('unicycle'), 'safety_filter'))
    filter_config_from_params(params)  # valid as it is
    for key in FILTER_PARAMETER_KEYS:
        bad = {'system': 'submarine', 'observation_sources': ['1junk']}.get(key, ['junk'])
        with pytest.raises(ValueError, match=f'^{key.replace(".", "[.]")}[:/]'):
            filter_config_from_params({**params, key: bad})


def test_k_c_keeps_the_refusal_text_ros2_param_set_reports() -> None:
    from rcbf_ros.core.config import filter_config_from_params
    from rcbf_ros.parameters.rules import find_config, load_params
    params = load_params(find_config('unicycle'), 'safety_filter')
    with pytest.raises(ValueError) as info:
        filter_config_from_params({**params, 'k_c': -1.0})
    assert str(info.value) == 'k_c: must be >= 0, got -1.0'  # the rule that declares its range


def test_node_specs_and_defaults_come_from_the_dataclasses() -> None:
    from rcbf_ros.envs.base import EnvSettings
    from rcbf_ros.node_logic import safety_filter as fl
    from rcbf_ros.ros.learner_node import NODE_DEFAULTS, NODE_SETTINGS, PARAMETERS
    from rcbf_ros.training.agent import LearnerConfig
    from rcbf_ros.training.settings import TrainingSettings
    assert fl.NODE_PARAMETER_DEFAULTS == defaults_of(fl.NodeSettings)
    assert [s.name for s in fl.NODE_PARAMETERS] == list(parameter_keys(fl.NodeSettings))
    assert fl.READ_ONLY_PARAMETERS == (
        'state_type', 'command_type', 'twist_fields', 'qos.reliable', 'qos.depth', 'system',
        'observation_sources', 'odom_frame_id', 'base_frame_id', 'transform_tolerance')
    for name in ('mode', 'seed', 'batch_size', 'start_steps', 'update_after',
                 'gp_refit_interval', 'k_c', 'model_based'):
        assert PARAMETERS[name] == getattr(LearnerConfig, name), name
    assert PARAMETERS['dt'] == EnvSettings.dt
    assert list(PARAMETERS) == list(NODE_SETTINGS)
    for name in set(NODE_SETTINGS) - {'dt'} - set(NODE_DEFAULTS):  # one default for both
        assert PARAMETERS[name] == getattr(TrainingSettings, name), name


@pytest.mark.parametrize('key, value, why', [
    ('threads', 0, 'must be >= 1, got 0'),
    ('checkpoint_every', 2.0, 'expected an integer, got 2.0'),
    ('initial_alpha', -1.0, 'must be > 0, got -1.0'),
    ('seed', 1.5, 'expected an integer, got 1.5'),
    ('resume', 'yes', "expected true or false, got 'yes'"),
])
def test_learner_settings_errors_name_the_key(key: str, value: object, why: str) -> None:
    from rcbf_ros.ros.learner_node import node_settings
    with pytest.raises(ParameterError) as info:
        node_settings({key: value})
    assert str(info.value) == f'{key}: {why}'



@pytest.mark.parametrize('system, key, value, why', [
    ('unicycle', 'goal', [1.0], 'expected 2 values, got 1'),
    ('unicycle', 'max_steps', 0, 'must be >= 1, got 0'),
    ('unicycle', 'layout', 'maze', "expected one of ['fixed', 'random'], got 'maze'"),
    ('pvtol', 'system_params.with_operator', 'maybe', "expected true or false, got 'maybe'"),
    ('pvtol', 'operator_noise', -0.1, 'must be >= 0, got -0.1'),
    ('car_following', 'collision_gap', 0.0, 'must be > 0, got 0.0'),
    ('car_following', 'initial_positions', [1.0, 2.0], 'expected 5 values, got 2'),
])
def test_env_settings_errors_name_the_key(system: str, key: str, value: object,
                                          why: str) -> None:
    from rcbf_ros.envs import make_env
    with pytest.raises(ParameterError) as info:
        make_env(system, {key: value})
    assert str(info.value) == f'{key}: {why}'



def test_env_text_booleans_are_still_taken() -> None:
    from rcbf_ros.envs import make_env
    assert make_env('unicycle', {'random_start': 'True'}).settings.random_start is True
    assert make_env('pvtol', {'system_params.with_operator': np.bool_(False)}
                    ).settings.with_operator is False


def test_env_hands_on_every_filter_key() -> None:
    """env.filter_params() keeps every key of FilterParameters (compile_assembly included) and
    drops the env's own (obstacles.shape)."""
    from rcbf_ros.envs import make_env
    params = make_env('unicycle', compile_assembly=True, k_c=1.5).filter_params()
    assert params['compile_assembly'] is True and params['k_c'] == 1.5
    assert 'obstacles.shape' not in params and 'goal' not in params


@dataclass(frozen=True)
class Names:
    """A string and a list of strings, without choices."""

    frame: str = setting('map', key='frame.id')
    topics: tuple[str, ...] = ()


@given(st.text(max_size=12), st.integers(0, 1))
def test_a_string_is_refused_exactly_when_it_holds_a_c0_control_character(text, as_list):
    """Oracle: a code point below U+0020 anywhere in the string."""
    control = [i for i, char in enumerate(text) if ord(char) < 0x20]
    params = {'topics': ['ok', text]} if as_list else {'frame.id': text}
    if not control:
        read_parameters(Names, params)
        return
    with pytest.raises(ParameterError) as refused:
        read_parameters(Names, params)
    line = str(refused.value)
    assert '\n' not in line
    where = 'topics: value 1: ' if as_list else 'frame.id: '
    assert line == (f'{where}contains the control character U+{ord(text[control[0]]):04X} at '
                    f'position {control[0]} (no string parameter holds one)')
