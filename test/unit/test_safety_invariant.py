"""The safety invariant under hostile inputs, as property-based tests (Hypothesis).

The invariant: what the filter returns is either
(a) within the actuator limits and meets every RCBF row with a slack of at most the tolerance, or
(b) exactly the configured fail-safe action, flagged, with a reason.

It is checked in the three places a command can come from: the core filter
(:class:`SafetyFilter`), the node's decision logic
(:func:`rcbf_ros.node_logic.safety_filter.decide`, from raw message sections) and the offline
re-filter (:func:`refilter_bag`, read back from its output bag). The oracle evaluates the rows
itself: h, grad h, f and g at the state from the barrier and system definitions, the robust
margin grad h^T mean - k_c |grad h|^T std written out here in numpy, then L_f h + L_g h u +
alpha h + rho at the returned command. It never looks at the filter's QP data or the solver's
answer.

Inputs: all three systems; configs drawn at random within their valid ranges (obstacle layouts,
gains, input weights, limits, fail-safe actions); states inside, on and outside the safe set and
absurd ones; proposals and disturbance boxes of any magnitude, from 1e-300 to 1e300, +-inf and
NaN. The search is derandomised (fixed seed) and bounded for CI.
"""
from __future__ import annotations

import math
from pathlib import Path
import tempfile

from hypothesis import assume, given, HealthCheck, settings
from hypothesis import strategies as st
import numpy as np
import pytest
from rosbags.highlevel import AnyReader
import torch

from rcbf_ros.bag import BagWriter
from rcbf_ros.bag.refilter import refilter_bag
from rcbf_ros.core.config import filter_config_from_params, FilterConfig
from rcbf_ros.core.filter import FilterResult, SafetyFilter
from rcbf_ros.messages.typestore import jazzy_typestore
from rcbf_ros.node_logic import safety_filter as fl
from rcbf_ros.parameters.rules import find_config, load_params

SLACK_TOLERANCE = 1e-4
SYSTEMS = ('unicycle', 'pvtol', 'car_following')
PROPERTY = settings(max_examples=60, derandomize=True, deadline=None, database=None,
                    suppress_health_check=[HealthCheck.too_slow,
                                           HealthCheck.filter_too_much])

# Any float a hostile client can put in a message, weighted toward the interesting ones.
HOSTILE = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True),
    st.sampled_from([0.0, -0.0, 1e-300, -1e-300, 5e-324, 2.5, -2.5, 2.5000001, 1e6, -1e6,
                     1.0000001e6, 1e7, -1e7, 1e10, 1e30, 1e300, -1e300, math.inf, -math.inf,
                     math.nan]),
    st.floats(min_value=-10.0, max_value=10.0),
)


def _vector(n: int, plain: st.SearchStrategy[float]) -> st.SearchStrategy[np.ndarray]:
    """n floats, mostly ``plain``, sometimes hostile in any entry."""
    entry = st.one_of(plain, plain, plain, HOSTILE)
    return st.lists(entry, min_size=n, max_size=n).map(lambda v: np.array(v, dtype=np.float64))


@st.composite
def unicycle_params(draw: st.DrawFn) -> dict:
    """A valid random unicycle config: 1-5 obstacles, look-ahead on or off, gains, limits."""
    k = draw(st.integers(1, 5))
    coordinate = st.floats(-3.0, 3.0)
    lookahead = draw(st.sampled_from([0.0, 0.03, 0.1]))
    limit = draw(st.floats(0.5, 5.0))
    params = {
        'system': 'unicycle',
        'obstacles.x': draw(st.lists(coordinate, min_size=k, max_size=k)),
        'obstacles.y': draw(st.lists(coordinate, min_size=k, max_size=k)),
        'obstacles.radius': draw(st.lists(st.floats(0.05, 1.0), min_size=k, max_size=k)),
        # the robot's centre stays outside the true radius only with margin >= lookahead
        'obstacles.margin': draw(st.floats(lookahead, lookahead + 0.3)),
        'input_limits.min': [-limit, -limit], 'input_limits.max': [limit, limit],
    }
    if lookahead > 0:
        speed_input = draw(st.sampled_from([-1, 0]))
        params.update({'obstacles.lookahead': lookahead, 'obstacles.heading_index': 2,
                       'obstacles.speed_input': speed_input})
        if speed_input >= 0:  # the point may switch behind: margin >= 3 lookahead
            params['obstacles.margin'] = max(params['obstacles.margin'], 3.0 * lookahead)
    return params


def _packaged(system: str) -> dict:
    return load_params(find_config(system), 'safety_filter')


@st.composite
def configs(draw: st.DrawFn, system: str) -> dict:
    """Flat filter parameters of ``system`` with random valid gains, weights and fail-safe."""
    params = draw(unicycle_params()) if system == 'unicycle' else _packaged(system)
    n_u = 1 if system == 'car_following' else 2
    params.update({
        'alpha': draw(st.floats(0.1, 10.0)),
        'k_c': draw(st.floats(0.0, 5.0)),
        'slack_weight': draw(st.sampled_from([1e3, 1e6, 1e8])),
        'input_weight': draw(st.lists(st.floats(0.01, 10.0), min_size=n_u, max_size=n_u)),
    })
    config = filter_config_from_params(params)
    system_ = config.problem.system
    lo = np.array(system_.u_min) if system_.u_min is not None else np.full(n_u, -1.0)
    hi = np.array(system_.u_max) if system_.u_max is not None else np.full(n_u, 1.0)
    share = draw(st.lists(st.floats(0.0, 1.0), min_size=n_u, max_size=n_u))
    params['fail_safe_action'] = (lo + np.array(share) * (hi - lo)).tolist()
    return params


@st.composite
def states(draw: st.DrawFn, system: str, params: dict) -> np.ndarray:
    """Inside, on and outside the safe set, and hostile values."""
    if system == 'unicycle':
        k = draw(st.integers(0, len(params['obstacles.x']) - 1))
        centre = np.array([params['obstacles.x'][k], params['obstacles.y'][k]])
        reach = params['obstacles.radius'][k] + params['obstacles.margin']
        distance = draw(st.sampled_from([0.0, 0.5, 0.99, 1.0, 1.01, 1.5, 3.0])) * reach
        angle, heading = draw(st.floats(-math.pi, math.pi)), draw(st.floats(-4.0, 4.0))
        base = np.array([*(centre + distance * np.array([math.cos(angle), math.sin(angle)])),
                         heading])
        plain = st.floats(-4.0, 4.0)
    elif system == 'pvtol':
        x1 = draw(st.floats(-6.0, 6.0))
        base = np.array([x1, draw(st.floats(-3.0, 3.0)), *draw(st.lists(
            st.floats(-1.5, 1.5), min_size=2, max_size=2)), draw(st.floats(-1.2, 1.2)),
            draw(st.floats(0.3, 1.7)), x1 + draw(st.floats(-1.0, 1.0))])
        plain = st.floats(-6.0, 6.0)
    else:
        gaps = draw(st.lists(st.floats(2.0, 9.0), min_size=4, max_size=4))
        positions = 34.0 - np.concatenate([[0.0], np.cumsum(gaps)])
        velocities = np.array(draw(st.lists(st.floats(20.0, 40.0), min_size=5, max_size=5)))
        base = np.stack([positions, velocities], axis=1).reshape(-1)
        plain = st.floats(-50.0, 50.0)
    if draw(st.booleans()):
        return base
    hostile = draw(_vector(base.size, plain))
    keep = np.array(draw(st.lists(st.booleans(), min_size=base.size, max_size=base.size)))
    return np.where(keep, base, hostile)


def _boxes(n_x: int) -> st.SearchStrategy[tuple[np.ndarray | None, np.ndarray | None]]:
    small = st.floats(-0.5, 0.5)
    return st.tuples(st.one_of(st.none(), _vector(n_x, small)),
                     st.one_of(st.none(), _vector(n_x, st.floats(0.0, 0.5))))


def row_values(problem, x: np.ndarray, u_rows: np.ndarray, u: np.ndarray,
               mean: np.ndarray | None, std: np.ndarray | None) -> np.ndarray:
    """L_f h + L_g h u + alpha h + rho per barrier at state x, with the rows chosen for the
    proposal ``u_rows`` (it picks the unicycle's look-ahead point), evaluated here."""
    xt = torch.from_numpy(x).unsqueeze(0)
    terms = problem.terms(xt, torch.from_numpy(u_rows).unsqueeze(0))
    h, grad = terms.h[0].numpy(), terms.grad_h[0].numpy()
    f = problem.system.f(xt)[0].numpy()
    g = problem.system.g(xt)[0].numpy().reshape(x.size, -1)
    mean = np.zeros(x.size) if mean is None else mean
    std = np.zeros(x.size) if std is None else std
    rho = grad @ mean - problem.k_c * np.abs(grad) @ std
    return grad @ f + (grad @ g) @ u + problem.alpha * h + rho


def assert_invariant(*, config: FilterConfig, fail_safe: np.ndarray, x: np.ndarray,
                     u_rl: np.ndarray, mean: np.ndarray | None, std: np.ndarray | None,
                     command: np.ndarray, flagged: bool, reason: str) -> None:
    """(a) within the limits and the rows hold within the tolerance, or (b) the fail-safe."""
    assert command.shape == fail_safe.shape and np.all(np.isfinite(command))
    if flagged:
        np.testing.assert_array_equal(command, fail_safe)
        assert reason, 'a fail-safe without a reason'
        return
    problem = config.problem
    system = problem.system
    if system.u_min is not None:
        assert np.all(command >= np.array(system.u_min)), (command, system.u_min)
        assert np.all(command <= np.array(system.u_max)), (command, system.u_max)
    # Everything that passed was finite and within the bounds, so the oracle can evaluate it.
    for value in (x, u_rl, mean, std):
        assert value is None or np.all(np.isfinite(value))
    u_rows = np.clip(u_rl, system.u_min, system.u_max) if system.u_min is not None else u_rl
    values = row_values(problem, x, u_rows, command, mean, std)
    scale = 1.0 + np.abs(values).max(initial=0.0)
    assert np.all(values >= -SLACK_TOLERANCE - 1e-9 * scale), (values, x, u_rl, command)


@pytest.mark.parametrize('system', SYSTEMS)
def test_core_filter_keeps_the_invariant(system: str) -> None:
    """SafetyFilter on drawn configs: three calls on one filter, each at a drawn state with a
    drawn proposal and disturbance box (no answer may depend on the one before)."""
    @PROPERTY
    @given(data=st.data())
    def check(data: st.DataObject) -> None:
        params = data.draw(configs(system))
        config = filter_config_from_params(params)
        safety_filter = SafetyFilter(config.problem, fail_safe_action=config.fail_safe_action,
                                     slack_tolerance=SLACK_TOLERANCE)
        n_x, n_u = safety_filter.n_x, safety_filter.n_u
        for _ in range(3):  # a few calls on one filter: no answer may depend on the last
            x = data.draw(states(system, params))
            u_rl = data.draw(_vector(n_u, st.floats(-5.0, 5.0)))
            mean, std = data.draw(_boxes(n_x))
            result = safety_filter.filter(x, u_rl, mean, std)
            assert isinstance(result, FilterResult)
            assert_invariant(config=config, fail_safe=safety_filter.fail_safe_action, x=x,
                             u_rl=u_rl, mean=mean, std=std, command=result.u_safe,
                             flagged=result.fail_safe, reason=result.reason)

    check()


def _sections(draw: st.DrawFn, n_x: int, n_u: int, x: np.ndarray) -> dict[str, np.ndarray]:
    """Proposal sections as a hostile client could send them: lengths and labels vary."""
    sections: dict[str, np.ndarray] = {}
    size = draw(st.sampled_from([n_u, n_u, n_u, 0, n_u + 1]))
    sections['u'] = draw(_vector(size, st.floats(-5.0, 5.0))) if size else np.zeros(0)
    if draw(st.booleans()):
        sections['state'] = x
    mean, std = draw(_boxes(n_x))
    if mean is not None:
        sections['disturbance_mean'] = mean
    if std is not None:
        sections['disturbance_std'] = std
    if draw(st.integers(0, 9)) == 0:
        sections['unexpected'] = np.zeros(1)
    return sections


@pytest.mark.parametrize('system', SYSTEMS)
def test_node_decisions_keep_the_invariant(system: str) -> None:
    """The node's decision logic from raw message sections: proposals of any length and labels,
    with or without their state, and a latest state sample that is valid, malformed or absent,
    at any age."""
    @PROPERTY
    @given(data=st.data())
    def check(data: st.DataObject) -> None:
        params = data.draw(configs(system))
        params.update({'slack_tolerance': SLACK_TOLERANCE})
        settings_ = fl.node_settings_from_params(params)
        config = filter_config_from_params(params)
        safety_filter = fl.build_safety_filter(config=config, settings=settings_)
        n_x, n_u = safety_filter.n_x, safety_filter.n_u
        topic_state = data.draw(states(system, params))
        latest = None
        if data.draw(st.booleans()):
            try:
                latest = fl.StateSample(received_ns=0, state=fl.state_from_sections(
                    sections={'state': topic_state}, n_x=n_x))
            except ValueError as exc:
                latest = fl.StateSample(received_ns=0, state=None, error=str(exc))
        sections = _sections(data.draw, n_x, n_u, data.draw(states(system, params)))
        proposal, error = None, ''
        try:
            proposal = fl.proposal_from_sections(sections=sections, n_u=n_u, n_x=n_x)
        except ValueError as exc:
            error = str(exc)
        decision = fl.decide(
            safety_filter=safety_filter, proposal=proposal, proposal_error=error,
            latest_state=latest, now_ns=data.draw(st.sampled_from([0, 10**8, 10**9])),
            max_state_age_s=settings_.max_state_age_s, static_mean=config.static_mean,
            static_std=config.static_std, slack_tolerance=settings_.slack_tolerance)
        assert decision.fail_safe == (decision.level == fl.ERROR)
        if decision.fail_safe:
            assert_invariant(config=config, fail_safe=safety_filter.fail_safe_action,
                             x=topic_state, u_rl=np.zeros(n_u), mean=None, std=None,
                             command=decision.u_safe, flagged=True, reason=decision.reason)
            return
        assert proposal is not None
        x = proposal.state if proposal.state is not None else latest.state
        assert_invariant(config=config, fail_safe=safety_filter.fail_safe_action, x=x,
                         u_rl=proposal.u, mean=proposal.disturbance_mean,
                         std=proposal.disturbance_std, command=decision.u_safe,
                         flagged=False, reason=decision.reason)

    check()


def _message(sections: dict[str, np.ndarray]) -> dict:
    dims = [{'label': k, 'size': int(v.size), 'stride': int(v.size)} for k, v in sections.items()]
    data = np.concatenate([v for v in sections.values()]) if sections else np.zeros(0)
    return {'layout': {'dim': dims, 'data_offset': 0}, 'data': data}


@pytest.mark.parametrize('system', SYSTEMS)
def test_refilter_keeps_the_invariant(system: str) -> None:
    """Whole recorded runs of hostile proposals, each carrying its state, re-filtered offline:
    every command in the output bag is read back and checked."""
    @settings(PROPERTY, max_examples=8)
    @given(data=st.data())
    def check(data: st.DataObject) -> None:
        params = data.draw(configs(system))
        config = filter_config_from_params(params)
        n_x = config.problem.system.n_x
        n_u = config.problem.system.n_u
        proposals = []
        for _ in range(6):
            x = data.draw(states(system, params))
            assume(np.all(np.isfinite(x)))  # a recorded state of the wrong kind stops refilter
            u = data.draw(_vector(n_u, st.floats(-5.0, 5.0)))
            mean, std = data.draw(_boxes(n_x))
            sections = {'u': u, 'state': x}
            if mean is not None:
                sections['disturbance_mean'] = mean
            if std is not None:
                sections['disturbance_std'] = std
            proposals.append(sections)
        with tempfile.TemporaryDirectory() as tmp:
            source, output = Path(tmp) / 'source', Path(tmp) / 'output'
            with BagWriter(source) as bag:
                bag.add_topic('/cmd_proposed', 'std_msgs/msg/Float64MultiArray')
                for k, sections in enumerate(proposals):
                    bag.write_message('/cmd_proposed', _message(sections), 1_000 + k)
            refilter_bag(source, output, dict(params, slack_tolerance=SLACK_TOLERANCE))
            with AnyReader([output], default_typestore=jazzy_typestore()) as reader:
                connections = [c for c in reader.connections
                               if c.topic == '/refilter/cmd_safe']
                commands = [np.asarray(reader.deserialize(raw, c.msgtype).data)[:n_u]
                            for c, _, raw in reader.messages(connections=connections)]
        # Every proposal is answered, one that fails validation with the fail-safe.
        assert len(commands) == len(proposals)
        fail_safe = np.array(params['fail_safe_action'], dtype=np.float64)
        for sections, command in zip(proposals, commands):
            try:
                fl.proposal_from_sections(sections=sections, n_u=n_u, n_x=n_x)
            except ValueError:
                np.testing.assert_array_equal(command, fail_safe)
                continue
            refused = not all(np.all(np.abs(v) <= 1e6) for v in sections.values())
            flagged = refused or np.array_equal(command, fail_safe)
            assert_invariant(config=config, fail_safe=fail_safe, x=sections['state'],
                             u_rl=sections['u'], mean=sections.get('disturbance_mean'),
                             std=sections.get('disturbance_std'), command=command,
                             flagged=flagged, reason='fail-safe in the output bag')

    check()


@pytest.mark.parametrize('system', SYSTEMS)
def test_the_filter_does_not_hide_behind_the_fail_safe(system: str) -> None:
    """The invariant alone holds for a filter that always returns the fail-safe: at ordinary
    states inside the safe set with ordinary proposals, it must filter instead."""
    rng = np.random.default_rng(3)
    config = filter_config_from_params(_packaged(system))
    safety_filter = SafetyFilter(config.problem, fail_safe_action=config.fail_safe_action,
                                 slack_tolerance=SLACK_TOLERANCE)
    problem = config.problem
    filtered = tried = 0
    while tried < 40:
        if system == 'unicycle':
            x = np.array([*rng.uniform(-3.0, 3.0, 2), rng.uniform(-np.pi, np.pi)])
        elif system == 'pvtol':
            x1 = rng.uniform(-5.0, 5.0)
            x = np.array([x1, rng.uniform(-2.0, 2.0), *rng.uniform(-0.5, 0.5, 2),
                          rng.uniform(-0.3, 0.3), rng.uniform(0.8, 1.2),
                          x1 + rng.uniform(-0.3, 0.3)])
        else:
            positions = np.array([34.0, 28.0, 22.0, 16.0, 10.0]) + rng.normal(0.0, 0.5, 5)
            x = np.stack([positions, 30.0 + rng.normal(0.0, 1.0, 5)], axis=1).reshape(-1)
        h = problem.state_h(torch.from_numpy(x).unsqueeze(0))[0].numpy()
        if np.min(h) <= 0.05:
            continue
        tried += 1
        u_rl = rng.uniform(-2.0, 2.0, safety_filter.n_u)
        filtered += not safety_filter.filter(x, u_rl).fail_safe
    assert filtered >= 36, filtered
