"""refilter's barrier statistics (min h_i, violation counts) are reduced as the states come, a
chunk at a time, and equal what evaluating every state at once gives: with few obstacles
(the generated closed form), with many (the filter's array rows) and with a look-ahead point
that follows the direction of travel."""
from __future__ import annotations

from pathlib import Path

from hypothesis import given, settings
from hypothesis import strategies as st
import numpy as np
import pytest
from test_refilter import _write_source, INSIDE_B, PARAMS_B, STATES

from rcbf_ros.bag import refilter
from rcbf_ros.bag.refilter import refilter_bag
from rcbf_ros.core.config import filter_config_from_params
from rcbf_ros.core.lie_closed_form import state_barrier_values
from rcbf_ros.core.lie_closed_form_rows import VECTOR_ROWS, VectorAssembly

_RING = 2 * np.pi * np.arange(VECTOR_ROWS + 6) / (VECTOR_ROWS + 6)
PARAMS_MANY = dict(PARAMS_B, obstacles=dict(
    PARAMS_B['obstacles'], x=[-0.5, *(3.0 * np.cos(_RING)).tolist()],
    y=[0.0, *(3.0 * np.sin(_RING)).tolist()], radius=[0.3] + [0.2] * _RING.size))
"""Config B's obstacle in the robot's path and a ring of obstacles: an array-rows family."""
PARAMS_MANY_BEHIND = dict(PARAMS_MANY, obstacles=dict(PARAMS_MANY['obstacles'], speed_input=0))
"""The same with the look-ahead point behind a reversing robot (the larger h of the two)."""
CASES = {'few': PARAMS_B, 'many': PARAMS_MANY, 'many_behind': PARAMS_MANY_BEHIND}


def _expected(params: dict, states: np.ndarray) -> tuple[dict, dict, int]:
    """(min h, violations per barrier, violating states) from every state at once."""
    problem = filter_config_from_params(params).problem
    h = state_barrier_values(problem, states)
    names = problem.barrier_names
    return ({name: float(h[:, i].min()) for i, name in enumerate(names)},
            {name: int((h[:, i] < 0).sum()) for i, name in enumerate(names)},
            int((h < 0).any(axis=1).sum()))


def test_the_cases_take_the_paths_they_name() -> None:
    for name, params in CASES.items():
        rows = VectorAssembly.from_problem(filter_config_from_params(params).problem)
        assert (rows is not None) == name.startswith('many')


@pytest.fixture(scope='module')
def source_bag(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return _write_source(tmp_path_factory.mktemp('stats') / 'src')


@pytest.mark.parametrize('case', sorted(CASES))
def test_a_run_is_reduced_a_chunk_at_a_time_to_the_same_statistics(
        case: str, source_bag: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    chunk = 5
    monkeypatch.setattr(refilter, 'BARRIER_CHUNK', chunk, raising=False)
    batches: list[int] = []
    evaluate_barriers = refilter.state_barrier_values

    def counted(problem: object, states: np.ndarray) -> np.ndarray:
        batches.append(len(states))
        return evaluate_barriers(problem, states)

    monkeypatch.setattr(refilter, 'state_barrier_values', counted)
    evaluate_rows = VectorAssembly.evaluate
    held = []

    def rows_counted(self: VectorAssembly, *args: object) -> object:
        held.append(1)
        return evaluate_rows(self, *args)

    monkeypatch.setattr(VectorAssembly, 'evaluate', rows_counted)
    summary = refilter_bag(source_bag, tmp_path / 'out', CASES[case])
    states = np.stack(STATES + INSIDE_B)
    min_h, violations, violating = _expected(CASES[case], states)
    assert summary.states_evaluated == len(states)
    assert summary.min_h == pytest.approx(min_h, rel=1e-12, abs=1e-12)
    assert summary.violations_per_barrier == violations
    assert summary.states_violating == violating == len(INSIDE_B)
    # Never every state at once: a chunk of states is all the statistics hold.
    assert batches or held
    assert all(n <= chunk for n in batches), batches


@settings(max_examples=60, deadline=None)
@given(case=st.sampled_from(sorted(CASES)), chunk=st.integers(1, 7),
       states=st.lists(st.tuples(st.floats(-3.5, 3.5), st.floats(-3.5, 3.5),
                                 st.floats(-7.0, 7.0)), max_size=20))
def test_the_tally_is_every_state_at_once(case: str, chunk: int,
                                          states: list[tuple[float, float, float]]) -> None:
    problem = filter_config_from_params(CASES[case]).problem
    tally = refilter._BarrierTally(problem)
    summary = refilter.RefilterSummary('s', 'o', 'unicycle', list(problem.barrier_names))
    original = refilter.BARRIER_CHUNK
    refilter.BARRIER_CHUNK = chunk
    try:
        for state in states:
            tally.add(np.array(state))
            assert len(tally._pending) < chunk
        refilter._barrier_statistics(summary, tally)
    finally:
        refilter.BARRIER_CHUNK = original
    assert summary.states_evaluated == len(states)
    if not states:
        assert all(np.isnan(v) for v in summary.min_h.values())
        assert summary.states_violating == 0
        return
    min_h, violations, violating = _expected(CASES[case], np.array(states))
    assert summary.min_h == pytest.approx(min_h, rel=1e-12, abs=1e-12)
    assert summary.violations_per_barrier == violations
    assert summary.states_violating == violating
