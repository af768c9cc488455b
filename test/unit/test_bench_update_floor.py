"""The training benchmark's own floor: the update it times is SAC.update's, and the floor's
table arithmetic."""
from __future__ import annotations

from benchmark_modules import load_benchmark
import numpy as np
import pytest
from sac_batches import N_U, OBS, random_batches
import torch

from rcbf_ros.learning.sac import SAC, SACConfig

floor_module = load_benchmark('_update_floor')
bench = load_benchmark('bench_training')


def _agent(mode: str = 'baseline', **config) -> SAC:
    layer = (lambda state, u, estimate=None: u) if mode == 'diff' else None
    return SAC(OBS, N_U, -np.ones(N_U), np.ones(N_U),
               SACConfig(mode=mode, hidden_sizes=(16, 16), **config), safety_layer=layer,
               seed=3)


def test_baseline_twin_carries_the_state_of_an_agent_with_a_safety_layer():
    sac = _agent('diff')
    sac.update(random_batches(1)[0])
    twin = floor_module.baseline_twin(sac)
    assert twin.config.mode == 'baseline' and twin.num_updates == 1
    assert floor_module.difference(twin, sac) == 0.0
    twin.update(random_batches(1)[0])
    assert floor_module.difference(twin, sac) > 0.0


def test_best_update_times_the_eager_update_without_compile_modes():
    sac = _agent()
    out = floor_module.best_update(sac, random_batches(2), modes=[], calls=3)
    assert list(out['variants']) == ['eager'] and out['compile_s'] == {}
    best, median = out['variants']['eager']
    assert 0.0 < best <= median
    assert sac.num_updates == 0  # timed on a twin


def test_best_update_checks_each_compile_mode_against_sac_update(monkeypatch):
    monkeypatch.setattr(torch, 'compile', lambda function, **_: function)
    sac = _agent()
    sac.update(random_batches(1)[0])
    out = floor_module.best_update(sac, random_batches(2), modes=['default'], calls=2)
    assert list(out['variants']) == ['eager', 'default']
    assert out['compile_s']['default'] > 0.0 and out['agreement']['default'] < 1e-6
    assert sac.num_updates == 1


def _run(steps_per_s: float, *, qp: float = 0.0) -> dict:
    floor = {'variants': {'eager': (9.0, 9.5), 'default': (6.0, 6.5),
                          'max-autotune-no-cudagraphs': (5.0, 7.0)},
             'compile_s': {'default': 40.0, 'max-autotune-no-cudagraphs': 60.0},
             'agreement': {'default': 1e-6, 'max-autotune-no-cudagraphs': 2e-6}}
    return {'floor': floor, 'qp_ms': qp, 'action_ms': 1.0, 'env_ms': 0.5,
            'steps_per_s': steps_per_s}


def test_floor_takes_the_fastest_way_of_updating_and_judges_the_step_against_it():
    assert bench.best_update_ms(_run(1.0)['floor']) == ('max-autotune-no-cudagraphs', 5.0)
    faster_eager = _run(1.0)['floor']
    faster_eager['variants']['eager'] = (4.0, 4.5)
    assert bench.best_update_ms(faster_eager) == ('eager', 4.0)
    # floor 5 + 2 + 1 + 0.5 = 8.5 ms; a 10 ms step is 1.18x, a 12.5 ms step 1.47x.
    met = bench.floor_row('unicycle', 'diff', [_run(100.0, qp=2.0)]).split(' | ')
    assert met[3:5] == ['8.50', '5.00'] and met[-3:] == ['1.18x', '<= 1.25x', 'met |']
    missed = bench.floor_row('unicycle', 'diff', [_run(80.0, qp=2.0)])
    assert missed.endswith('| 1.47x | <= 1.25x | not met |')


def test_each_run_is_held_against_the_floor_measured_after_it():
    # Run 1: floor 5 + 2 + 1 + 0.5 = 8.5 ms, step 10 ms: 1.18x. Run 2, its update timed 1.5x
    # slower (the host's speed moved): best call 7.5 ms, floor 11 ms, step 13.3 ms: 1.21x.
    # Against run 1's floor, run 2's step would be 1.57x.
    slow = _run(75.0, qp=2.0)
    slow['floor']['variants'] = {name: (1.5 * best, 1.5 * median) for name, (best, median)
                                 in slow['floor']['variants'].items()}
    cells = bench.floor_row('pvtol', 'diff', [_run(100.0, qp=2.0), slow]).split(' | ')
    assert cells[3:5] == ['9.75', '6.25']          # medians of the floors and update parts
    assert cells[-3:] == ['1.19x (1.18, 1.21)', '<= 1.25x', 'met |']


def test_floor_reading_names_compile_cost_and_agreement():
    second = _run(1.0)['floor']
    second['variants']['eager'] = (11.0, 12.5)
    second['compile_s']['default'] = 2.0
    text = bench.floor_reading({'unicycle/1': [_run(1.0)['floor'], second]}, 200)
    assert 'one-off compile, longest: default 40 s, max-autotune-no-cudagraphs 60 s' in text
    assert 'after one step 2.0e-06' in text
    assert 'best of 200 calls, median over 2 measurements: eager 10.00 (median 11.00)' in text


def test_compile_update_needs_a_warm_up_longer_than_the_batch(monkeypatch, capsys):
    monkeypatch.setattr('sys.argv', ['bench_training.py', '--compile-update', '--warmup', '256'])
    with pytest.raises(SystemExit) as exit_info:
        bench.main()
    assert exit_info.value.code == 2
    assert '--compile-update: --warmup must exceed the batch size' in capsys.readouterr().err


def test_best_update_times_each_way_in_blocks_of_consecutive_calls(monkeypatch):
    """Each variant's calls run in blocks (one untimed call, then ``block`` timed ones), the
    blocks alternating: the best call is one a variant reaches with its working set in the
    caches, not right after another variant's products."""
    from rcbf_ros.learning.compiled_update import FunctionalUpdate

    monkeypatch.setattr(torch, 'compile', lambda function, **_: function)
    order: list[str] = []
    eager_update, compiled_step = SAC.update, FunctionalUpdate.step

    def eager(self, *args, **kwargs):
        order.append('eager')
        return eager_update(self, *args, **kwargs)

    def compiled(self, *args, **kwargs):
        order.append('default')
        return compiled_step(self, *args, **kwargs)

    monkeypatch.setattr(SAC, 'update', eager)
    monkeypatch.setattr(FunctionalUpdate, 'step', compiled)
    out = floor_module.best_update(_agent(), random_batches(2), modes=['default'], calls=5,
                                   block=2)
    # Blocks of 1 untimed + 2 timed calls; the last block holds the 5th timed call.
    timed = (['eager'] * 3 + ['default'] * 3) * 2 + ['eager'] * 2 + ['default'] * 2
    assert order[-len(timed):] == timed
    assert order[-len(timed) - 10:-len(timed)] == ['eager'] * 5 + ['default'] * 5
    assert all(0.0 < best <= median for best, median in out['variants'].values())


def test_the_qp_floor_is_the_typical_minibatch_at_its_best_speed():
    """The QP's part of the floor: each minibatch's best call (its speed floor), the median
    over minibatches (its work): one minibatch with almost nothing to correct does not set
    it, nor do one minibatch's slow repeats."""
    per_batch = [[1.6, 1.9, 1.7], [1.0, 1.1, 1.05], [1.5, 3.0, 1.55], [1.7, 1.65, 2.5],
                 [1.62, 1.62, 1.62]]
    assert bench.typical_best(per_batch) == 1.6
