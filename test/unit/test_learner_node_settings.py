"""The learner node's parameters -> its SafeLearner (no DDS: the pure construction)."""
from __future__ import annotations

import numpy as np
import pytest

from rcbf_ros.envs import make_env
from rcbf_ros.parameters.rules import find_config, load_params
from rcbf_ros.ros.learner_node import learner_from_settings, node_settings


@pytest.fixture(scope='module')
def pvtol() -> tuple[dict, int]:
    params = load_params(find_config('pvtol'), 'learner')
    obs, _ = make_env('pvtol', load_params(find_config('pvtol'), 'simulator')).reset(seed=0)
    return params, int(np.asarray(obs).size)


@pytest.mark.parametrize('mode, envelope, expect_layer', [
    ('modular', True, True), ('modular', False, False), ('diff', True, False)])
def test_modular_envelope_parameter_reaches_the_losses(pvtol, mode, envelope, expect_layer):
    params, obs_dim = pvtol
    settings = node_settings({'system': 'pvtol', 'mode': mode, 'modular_envelope': envelope})
    learner = learner_from_settings(settings, params, obs_dim)
    assert learner.config.mode == mode and learner.config.modular_envelope is envelope
    assert (learner.envelope_layer is not None) is expect_layer
    # The losses' layer: the full problem in diff, the envelope (or none) in modular.
    expected = {'diff': learner.safety_layer, 'modular': learner.envelope_layer}[mode]
    assert learner.sac.safety_layer is expected
    if expect_layer:
        names = learner.envelope_layer.problem.barrier_names
        assert names and not any('obstacle' in n or 'operator' in n for n in names)
        assert any('operator' in n for n in learner.problem.barrier_names)
        assert learner.envelope_layer.problem.n_barriers < learner.problem.n_barriers


def test_the_nodes_learner_takes_the_policy_box_of_the_params_file():
    """As the in-process trainer (resolve_run): config/unicycle.yaml's /learner
    policy_limits reach the node's SAC; PVTOL's file has none, so its input limits apply."""
    path = find_config('unicycle')
    params = {**load_params(path, 'safety_filter'), **load_params(path, 'learner')}
    learner = learner_from_settings(node_settings({'system': 'unicycle'}), params,
                                    obs_dim=7)
    np.testing.assert_array_equal(learner.u_low, [0.0, -2.5])
    np.testing.assert_array_equal(learner.u_high, [2.5, 2.5])
    path = find_config('pvtol')
    params = {**load_params(path, 'safety_filter'), **load_params(path, 'learner')}
    learner = learner_from_settings(node_settings({'system': 'pvtol'}), params, obs_dim=12)
    np.testing.assert_array_equal(learner.u_low, learner.system.u_min)
