"""The closed-form single-state assembly (rcbf_ros.core.lie_closed_form) against autograd.

References, none of them the code under test: the batched torch path (RCBFProblem.terms / qp,
autograd through every barrier and cascade), torch.autograd.functional for the systems'
Jacobians and Hessians, the families' own torch ``value`` and build_rcbf_qp. Problems: the
shipped config files and random variations of them (obstacle layouts, cascade depths 0-2, band
forms, moving and constant centres, walls, gaps, gains, the look-ahead point's direction
switch), at random states, proposals and disturbance boxes.
"""
from __future__ import annotations

from dataclasses import dataclass, field
import warnings

from hypothesis import given, HealthCheck, settings
from hypothesis import strategies as st
import numpy as np
import pytest
import torch

from rcbf_ros.core import barriers
from rcbf_ros.core.barriers import BandBarrier, cascade, CircleObstacles, HalfPlane, PairGap
from rcbf_ros.core.config import filter_config_from_params
from rcbf_ros.core.dynamics import CarFollowing, PVTOL, Unicycle
import rcbf_ros.core.filter as filter_module
from rcbf_ros.core.filter import InputBounds, SafetyFilter, select_assembly
from rcbf_ros.core.lie_closed_form import ClosedFormAssembly, ClosedFormTerms, has_closed_form
from rcbf_ros.core.lie_closed_form_batch import BatchClosedForm
from rcbf_ros.core.rcbf import RCBFProblem
from rcbf_ros.parameters.rules import find_config, load_params

SYSTEMS = ('unicycle', 'car_following', 'pvtol')
TOLERANCE = 1e-10
"""Closed form vs autograd, relative to the scale of the compared array (round-off differs:
the closed form expands the quadratics, autograd differentiates the centred form)."""


def assert_close(got: np.ndarray, want: np.ndarray, what: str) -> None:
    scale = max(1.0, float(np.max(np.abs(want), initial=0.0)))
    np.testing.assert_allclose(got, want, rtol=TOLERANCE, atol=TOLERANCE * scale, err_msg=what)


def shipped(system: str) -> dict:
    return load_params(find_config(system), 'safety_filter')


def random_state(system: str, rng: np.random.Generator, n_x: int) -> np.ndarray:
    if system == 'unicycle':
        return np.array([*rng.uniform(-3.0, 3.0, 2), rng.uniform(-np.pi, np.pi)])
    if system == 'pvtol':
        x = np.array([rng.uniform(-5.5, 5.5), rng.uniform(-2.5, 2.5), *rng.normal(0, 1.0, 2),
                      rng.uniform(-1.0, 1.0), rng.uniform(0.3, 1.7)])
        return np.append(x, x[0] + rng.uniform(-1.0, 1.0)) if n_x == 7 else x
    positions = np.array([34.0, 28.0, 22.0, 16.0, 10.0]) + rng.normal(0.0, 4.0, 5)
    velocities = 30.0 + rng.normal(0.0, 3.0, 5)
    return np.stack([positions, velocities], axis=1).reshape(-1)


def _gammas(rng: np.random.Generator, most: int = 2) -> list[float]:
    return [float(g) for g in rng.uniform(0.5, 4.0, rng.integers(0, most + 1))]


def variation(system: str, rng: np.random.Generator) -> dict:
    """The shipped config of ``system`` with random changes to every barrier family."""
    params = shipped(system)
    k = int(rng.integers(1, 7))
    if system == 'unicycle':
        x, y = rng.uniform(-2.5, 2.5, k).tolist(), rng.uniform(-2.5, 2.5, k).tolist()
        radius = rng.uniform(0.2, 0.7, k).tolist()
        lookahead, extra = float(rng.uniform(0.01, 0.3)), float(rng.uniform(0.0, 0.2))
        speed_input = int(rng.choice([-1, 0, 1]))
        params.update({'obstacles.x': x, 'obstacles.y': y, 'obstacles.radius': radius,
                       'obstacles.lookahead': lookahead,
                       # the robot's centre outside the true radius: margin >= lookahead, and
                       # 3 lookaheads where the point may switch behind (speed_input)
                       'obstacles.margin': (3.0 if speed_input >= 0 else 1.0) * lookahead + extra,
                       'obstacles.speed_input': speed_input,
                       'alpha': float(rng.uniform(0.5, 5.0)),
                       'walls.nx': [1.0, -0.6], 'walls.ny': [0.0, 0.8],
                       'walls.offset': rng.uniform(-4.0, -2.0, 2).tolist()})
        if rng.random() < 0.3:  # no look-ahead point: a quadratic, cascaded like any other
            params.update({'obstacles.lookahead': 0.0, 'obstacles.speed_input': -1,
                           'obstacles.gammas': _gammas(rng)})
    elif system == 'car_following':
        pairs = [(4, 6), (8, 6), (2, 4), (6, 8)][:int(rng.integers(1, 5))]
        params.update({'gaps.a': [a for a, _ in pairs], 'gaps.b': [b for _, b in pairs],
                       'gaps.delta': float(rng.uniform(2.0, 5.0)), 'gaps.gammas': _gammas(rng),
                       'alpha': float(rng.uniform(0.5, 8.0)),
                       'system_params.k_v': float(rng.uniform(1.0, 6.0)),
                       'system_params.k_b': float(rng.uniform(5.0, 30.0)),
                       'system_params.brake_gap': float(rng.uniform(4.0, 9.0)),
                       'system_params.rear_brake_gap': float(rng.uniform(8.0, 14.0)),
                       'bands.speed.index': 7, 'bands.speed.center': 30.0,
                       'bands.speed.half_width': 10.0, 'bands.speed.gammas': [],
                       'bands.speed.form': str(rng.choice(['quadratic', 'sides']))})
    else:
        with_operator = bool(rng.random() < 0.7)
        params = {key: value for key, value in params.items()
                  if with_operator or not key.startswith('bands.operator.')}
        params.update({'system_params.with_operator': with_operator,
                       'obstacles.x': rng.uniform(-4.0, 4.0, k).tolist(),
                       'obstacles.y': rng.uniform(-2.0, 2.0, k).tolist(),
                       'obstacles.radius': rng.uniform(0.2, 0.5, k).tolist(),
                       'obstacles.gammas': _gammas(rng),
                       'alpha': float(rng.uniform(0.5, 3.0)),
                       'walls.nx': [0.3], 'walls.ny': [1.0], 'walls.offset': [-2.8],
                       'walls.gammas': _gammas(rng)})
        for band in ('tilt', 'thrust', 'arena_x', 'arena_y') + (
                ('operator',) if with_operator else ()):
            params[f'bands.{band}.gammas'] = _gammas(rng)
            params[f'bands.{band}.form'] = str(rng.choice(['quadratic', 'sides']))
        if with_operator:
            params['system_params.operator_gain'] = float(rng.uniform(0.5, 4.0))
    return params


def problems(system: str, count: int, seed: int) -> list[RCBFProblem]:
    rng = np.random.default_rng(seed)
    return [filter_config_from_params(shipped(system)).problem] + [
        filter_config_from_params(variation(system, rng)).problem for _ in range(count)]


# --- the systems' closed forms -------------------------------------------------------------

@pytest.mark.parametrize('system', [Unicycle(), CarFollowing(), PVTOL(),
                                    PVTOL(with_operator=False),
                                    CarFollowing(k_v=2.5, k_b=7.0, brake_gap=9.0)],
                         ids=['unicycle', 'cars', 'pvtol', 'pvtol-6', 'cars-gains'])
def test_drift_jet_matches_autograd(system):
    rng = np.random.default_rng(0)
    jet_of = system.closed_form_source().function()
    name = type(system).__name__
    n_x = system.n_x
    for _ in range(30):
        x = random_state({'Unicycle': 'unicycle', 'PVTOL': 'pvtol'}.get(name, 'car_following'),
                         rng, n_x)
        if isinstance(system, CarFollowing):  # some cars inside their braking gaps
            x[2] = x[0] - rng.uniform(2.0, 12.0)
        xt = torch.from_numpy(x)
        jet = jet_of(x)
        for mine, listed in zip(jet, jet_of(x.tolist())):  # a list of floats: the same jet
            assert mine.dtype == listed.dtype and mine.tobytes() == listed.tobytes()

        def drift(z):
            return system.f(z[None])[0]

        np.testing.assert_allclose(jet.f, drift(xt).numpy(), rtol=1e-14, atol=1e-14)
        np.testing.assert_allclose(jet.g, system.g(xt[None])[0].numpy(), rtol=1e-14, atol=1e-14)
        jacobian = torch.autograd.functional.jacobian(drift, xt).numpy()
        np.testing.assert_allclose(jet.jacobian, jacobian, rtol=1e-14, atol=1e-14)
        # The closed-form cascades leave out the rate of J along f,
        # R[m, j] = sum_k f_k d^2 f_m / dx_j dx_k: it must vanish.
        hessians = np.stack([torch.autograd.functional.hessian(
            lambda z, m=m: drift(z)[m], xt).numpy() for m in range(n_x)])
        np.testing.assert_allclose(hessians @ jet.f, 0.0, rtol=0, atol=1e-14)


# --- the families' quadratic coefficients ---------------------------------------------------

FAMILIES = [
    CircleObstacles(centers=((0.5, -1.0), (2.0, 3.0)), radii=(0.4, 0.7), margin=0.1),
    CircleObstacles(centers=((0.5, -1.0),), radii=(0.4,), position_indices=(1, 3)),
    CircleObstacles(centers=((0.5, -1.0),), radii=(0.4,), position_indices=(2, 2)),
    BandBarrier(index=0, half_width=0.6, center_index=6),
    BandBarrier(index=0, half_width=0.6, center_index=6, form='sides'),
    BandBarrier(index=5, half_width=0.5, center=1.0),
    BandBarrier(index=5, half_width=0.5, center=1.0, form='sides'),
    BandBarrier(index=3, half_width=0.5, center_index=3),
    PairGap(pairs=((4, 6), (6, 4), (0, 1)), delta=3.5),
    HalfPlane(normals=((1.0, 0.0), (-0.6, 0.8)), offsets=(-3.0, -2.0)),
    HalfPlane(normals=((1.0, 2.0, -1.0),), offsets=(0.5,), indices=(0, 0, 4)),
]


@pytest.mark.parametrize('family', FAMILIES, ids=[f'{type(f).__name__}-{i}'
                                                   for i, f in enumerate(FAMILIES)])
def test_quadratic_rows_reproduce_the_family(family):
    n_x = 7
    rows = family.quadratic_rows(n_x)
    np.testing.assert_array_equal(rows.hessian, np.swapaxes(rows.hessian, 1, 2))
    x = torch.from_numpy(np.random.default_rng(1).normal(0.0, 3.0, (20, n_x)))
    want = barriers.evaluate(family, x).numpy()  # the family's torch values
    for state, h in zip(x.numpy(), want):
        got = rows.constant + rows.linear @ state + 0.5 * (rows.hessian @ state) @ state
        np.testing.assert_allclose(got, h, rtol=1e-12, atol=1e-12)


def test_a_lookahead_circle_is_not_quadratic():
    assert CircleObstacles(centers=((0.0, 0.0),), radii=(0.5,), heading_index=2,
                           lookahead=0.03).quadratic_rows(3) is None


# --- barrier terms and QP data against autograd ---------------------------------------------

@pytest.mark.parametrize('system', SYSTEMS)
def test_terms_match_autograd_on_shipped_and_varied_configs(system):
    rng = np.random.default_rng(2)
    for problem in problems(system, 12, seed=SYSTEMS.index(system)):
        closed = ClosedFormTerms.from_problem(problem)
        assert closed is not None
        n_x, n_u = problem.system.n_x, problem.system.n_u
        for _ in range(15):
            x = random_state(system, rng, n_x)
            for u in (rng.uniform(-3.0, 3.0, n_u), None):
                got = closed.terms(x, u)
                want = problem.terms(torch.from_numpy(x)[None],
                                     None if u is None else torch.from_numpy(u)[None])
                for name, a, b in zip(got._fields, got, want):
                    assert_close(a, b[0].numpy(), f'{system} {name}')


def test_the_lookahead_point_follows_the_direction_of_travel_as_autograd_does():
    # On the rims of the obstacles the two points disagree: every case of the switch occurs.
    rng = np.random.default_rng(4)
    params = shipped('unicycle')
    problem = filter_config_from_params(params).problem
    closed = ClosedFormTerms.from_problem(problem)
    centers = np.stack([params['obstacles.x'], params['obstacles.y']], axis=1)
    delta = np.array(params['obstacles.radius']) + params['obstacles.margin']
    lookahead = params['obstacles.lookahead']
    seen = {'ahead': 0, 'behind': 0, 'behind blocked': 0}
    for _ in range(300):
        o = rng.integers(len(centers))
        angle = rng.uniform(-np.pi, np.pi)
        p = centers[o] + (delta[o] + rng.uniform(-0.04, 0.04)) * np.array(
            [np.cos(angle), np.sin(angle)])
        x = np.array([*p, rng.uniform(-np.pi, np.pi)])
        u = rng.uniform(-2.5, 2.5, 2)
        got = closed.terms(x, u)
        want = problem.terms(torch.from_numpy(x)[None], torch.from_numpy(u)[None])
        for name, a, b in zip(got._fields, got, want):
            assert_close(a, b[0].numpy(), name)
        behind = x[:2] - lookahead * np.array([np.cos(x[2]), np.sin(x[2])])
        clear = np.all(((behind - centers) ** 2).sum(1) >= delta ** 2)
        seen['ahead' if u[0] >= 0 else 'behind' if clear else 'behind blocked'] += 1
    assert min(seen.values()) >= 20, seen


@pytest.mark.parametrize('system', SYSTEMS)
def test_assembly_matches_the_problems_qp(system):
    rng = np.random.default_rng(5)
    for problem in problems(system, 6, seed=17):
        assembly = ClosedFormAssembly.from_problem(problem)
        n_x, n_u = problem.system.n_x, problem.system.n_u
        for _ in range(10):
            x = random_state(system, rng, n_x)
            u = rng.uniform(-3.0, 3.0, n_u)
            mean, std = rng.normal(0.0, 0.1, n_x), rng.uniform(0.0, 0.2, n_x)
            h, rows, upper, size = assembly.evaluate(*(a.tolist() for a in (x, u, mean, std)))
            want = problem.qp(*(torch.from_numpy(a)[None] for a in (x, u, mean, std)))
            want_h = problem.terms(torch.from_numpy(x)[None], torch.from_numpy(u)[None]).h
            assert_close(np.array(h), want_h[0].numpy(), 'h')
            assert_close(np.array(rows), want.G[0].numpy(), 'G')
            assert_close(np.array(upper), want.h[0].numpy(), 'h_qp')
            squares = sum(float(np.square(a).sum()) for a in (h, rows, upper))
            assert size == pytest.approx(squares, rel=1e-12)


# Hostile but valid: anything the filter's input checks let through (finite, within the default
# bounds of 1e6, std >= 0), weighted toward exact zeros of either sign, subnormals, the bounds
# themselves, the cars' braking gaps and headings far from 0.
EDGES = [0.0, -0.0, 5e-324, -5e-324, 1e-300, 1e6, -1e6, 6.0, -6.0, 12.0, -12.0, 1e5, -1e5,
         np.pi, -np.pi, 2.5, -2.5]
ENTRY = st.one_of(st.floats(-1e6, 1e6), st.sampled_from(EDGES), st.floats(-10.0, 10.0))
SPREAD = st.one_of(st.floats(0.0, 1e6), st.sampled_from([0.0, 5e-324, 1e-300, 1e6]),
                   st.floats(0.0, 1.0))
HOSTILE = settings(max_examples=80, derandomize=True, deadline=None, database=None,
                   suppress_health_check=[HealthCheck.too_slow])
ASSEMBLIES = {system: [(problem, ClosedFormAssembly.from_problem(problem))
                       for problem in problems(system, 3, seed=40 + i)]
              for i, system in enumerate(SYSTEMS)}


@st.composite
def hostile_call(draw: st.DrawFn, system: str, n_x: int, n_u: int):
    """A state near the system's operating point, some entries hostile (for the cars, some
    gaps exactly at a braking switch), a proposal and a disturbance box of any valid size."""
    rng = np.random.default_rng(draw(st.integers(0, 2 ** 32 - 1)))
    x = random_state(system, rng, n_x)
    hostile = np.array(draw(st.lists(ENTRY, min_size=n_x, max_size=n_x)))
    keep = np.array(draw(st.lists(st.booleans(), min_size=n_x, max_size=n_x)))
    if system == 'car_following' and draw(st.booleans()):
        me, ahead, gap = draw(st.sampled_from([(2, 0, 6.0), (4, 2, 6.0), (8, 4, 12.0)]))
        x[me] = np.round(x[me])  # whole metres: x_ahead - x_me is the gap exactly
        x[ahead] = x[me] + draw(st.sampled_from([gap, -gap]))
        keep[[me, ahead]] = True
    x = np.where(keep, x, hostile)
    u = np.array(draw(st.lists(ENTRY, min_size=n_u, max_size=n_u)))
    mean = np.array(draw(st.lists(ENTRY, min_size=n_x, max_size=n_x)))
    std = np.array(draw(st.lists(SPREAD, min_size=n_x, max_size=n_x)))
    return x, u, mean, std


@pytest.mark.parametrize('system', SYSTEMS)
def test_the_generated_assembly_equals_autograd_on_hostile_inputs(system):
    """h, G and the right-hand side of the generated code against RCBFProblem.qp (autograd
    through every barrier and cascade), on the shipped config and three variations, at
    states, proposals and boxes of any size the filter accepts."""
    @HOSTILE
    @given(data=st.data())
    def check(data: st.DataObject) -> None:
        problem, assembly = data.draw(st.sampled_from(ASSEMBLIES[system]))
        n_x, n_u = problem.system.n_x, problem.system.n_u
        x, u, mean, std = data.draw(hostile_call(system, n_x, n_u))
        h, rows, upper, size = assembly.evaluate(*(a.tolist() for a in (x, u, mean, std)))
        tensors = [torch.from_numpy(a)[None] for a in (x, u, mean, std)]
        want = problem.qp(*tensors)
        assert_close(np.array(h), problem.terms(tensors[0], tensors[1]).h[0].numpy(), 'h')
        assert_close(np.array(rows), want.G[0].numpy(), 'G')
        assert_close(np.array(upper), want.h[0].numpy(), 'h_qp')
        squares = sum(float(np.square(a).sum()) for a in (h, rows, upper))
        assert size == pytest.approx(squares, rel=1e-12)

    check()


# --- which problems get the closed form ------------------------------------------------------

@dataclass(frozen=True)
class OwnUnicycle(Unicycle):
    """A user's system derived from a built-in one, with its own drift."""

    n_x: int = field(default=3, init=False)

    def f(self, x):
        return 0.1 * torch.ones_like(x)


@dataclass(frozen=True)
class OwnFamily:
    """A user's barrier family (h = 1 - x_0^2)."""

    count: int = 1
    names: tuple = ('own',)

    def value(self, x, index):
        return 1.0 - x[:, 0] ** 2


LOOKAHEAD = CircleObstacles(centers=((0.0, 0.0),), radii=(0.5,), heading_index=2,
                            lookahead=0.03)
CIRCLE = CircleObstacles(centers=((1.0, 0.0),), radii=(0.5,))


@pytest.mark.parametrize('problem, reason', [
    (RCBFProblem(OwnUnicycle(), (LOOKAHEAD,)), 'a system by dotted path'),
    (RCBFProblem(Unicycle(), (LOOKAHEAD, OwnFamily())), 'a family by dotted path'),
    (RCBFProblem(PVTOL(), (cascade(CIRCLE, PVTOL(), [1.0, 1.0, 1.0]),)), 'cascaded 3 times'),
    (RCBFProblem(Unicycle(), (cascade(LOOKAHEAD, Unicycle(), [1.0]),)), 'cascaded look-ahead'),
    (RCBFProblem(PVTOL(), (cascade(CIRCLE, PVTOL(operator_gain=1.0), [1.0]),)),
     'a cascade over another system'),
])
def test_other_problems_keep_the_autograd_path(problem, reason):
    assert ClosedFormTerms.from_problem(problem) is None, reason
    assert not has_closed_form(problem), reason
    assert BatchClosedForm.from_problem(problem) is None, reason
    assert SafetyFilter(problem).assembly == 'autograd', reason


@pytest.mark.parametrize('system', SYSTEMS)
def test_the_shipped_problems_take_the_closed_form(system):
    problem = filter_config_from_params(shipped(system)).problem
    assert SafetyFilter(problem).assembly == 'closed_form'
    assert SafetyFilter(problem, closed_form=False).assembly == 'autograd'
    assert select_assembly(problem)[0] == 'closed_form'


# --- the filter on either path ---------------------------------------------------------------

@pytest.mark.parametrize('system', SYSTEMS)
def test_both_paths_give_the_same_safe_actions(system):
    problem = filter_config_from_params(shipped(system)).problem
    fast, autograd = SafetyFilter(problem), SafetyFilter(problem, closed_form=False)
    rng = np.random.default_rng(8)
    n_x, n_u = problem.system.n_x, problem.system.n_u
    active = 0
    for _ in range(60):
        x = random_state(system, rng, n_x)
        u = rng.uniform(-3.0, 3.0, n_u)
        std = rng.uniform(0.0, 0.05, n_x)
        a, b = fast.filter(x, u, std=std), autograd.filter(x, u, std=std)
        assert a.fail_safe == b.fail_safe
        assert_close(a.h, b.h, 'h')
        np.testing.assert_allclose(a.u_safe, b.u_safe, atol=1e-6)  # OSQP's tolerance
        active += b.active
    assert active >= 5


@pytest.mark.slow  # the compile takes seconds
def test_compiling_is_for_the_autograd_path_only():
    problem = filter_config_from_params(shipped('unicycle')).problem
    assert SafetyFilter(problem, compile_assembly=True).assembly == 'closed_form'
    compiled = SafetyFilter(problem, closed_form=False, compile_assembly=True)
    assert compiled.assembly == 'compiled'
    fast = SafetyFilter(problem)
    rng = np.random.default_rng(10)
    for _ in range(30):
        x, u = random_state('unicycle', rng, 3), rng.uniform(-3.0, 3.0, 2)
        a, b = fast.filter(x, u), compiled.filter(x, u)
        assert_close(a.h, b.h, 'h')
        np.testing.assert_allclose(a.u_safe, b.u_safe, atol=1e-6)


def test_the_direct_osqp_calls_give_bit_identical_results(monkeypatch):
    problem = filter_config_from_params(shipped('pvtol')).problem
    direct = SafetyFilter(problem)
    monkeypatch.setattr(filter_module._DirectOSQP, 'wrap', staticmethod(lambda solver: solver))
    public = SafetyFilter(problem)
    assert type(direct._solver) is filter_module._DirectOSQP
    assert type(public._solver) is not filter_module._DirectOSQP
    rng = np.random.default_rng(9)
    for _ in range(60):
        x, u = random_state('pvtol', rng, 7), rng.uniform(-3.0, 3.0, 2)
        a, b = direct.filter(x, u), public.filter(x, u)
        assert (a.status, a.fail_safe) == (b.status, b.fail_safe)
        np.testing.assert_array_equal(a.u_safe, b.u_safe)
        np.testing.assert_array_equal(a.slack, b.slack)


def test_huge_inputs_within_wide_bounds_are_refused_without_numpy_warnings():
    problem = filter_config_from_params(shipped('pvtol')).problem
    safety_filter = SafetyFilter(problem, input_bounds=InputBounds(1e300, 1e300, 1e300))
    x = np.array([1e200, 0.0, 1e200, 0.0, 0.0, 1e200, 0.0])
    with warnings.catch_warnings():
        warnings.simplefilter('error')
        result = safety_filter.filter(x, [0.0, 0.0])
    assert result.fail_safe and result.status == 'input_refused'


BOUND = 1e6


def expected_refusal(field: str, value: float) -> str | None:
    """The field-by-field rules: finite, then |value| <= bound, then (std only) >= 0."""
    if not np.isfinite(value):
        return 'NaN or inf'
    if abs(value) > BOUND:
        return 'beyond the bound'
    if field == 'disturbance_std' and value < 0:
        return 'must be >= 0'
    return None


@pytest.mark.parametrize('others', [1.0, 3.0], ids=['one bound', 'three bounds'])
@pytest.mark.parametrize('field', ['state', 'u_rl', 'disturbance_mean', 'disturbance_std'])
@pytest.mark.parametrize('value', [BOUND, np.nextafter(BOUND, np.inf), -BOUND,
                                   -np.nextafter(BOUND, np.inf), np.nan, np.inf, -np.inf,
                                   -0.0, -1e-300])
def test_input_checks_hold_exactly_at_their_edges(field, value, others):
    # The one-comparison check of every input must accept exactly what the field-by-field
    # checks accept (they give the reason), with the three bounds equal (one comparison for
    # all inputs) and with the other fields' bounds larger.
    own = {'state': 'state', 'u_rl': 'command'}.get(field, 'disturbance')
    bounds = InputBounds(**{name: BOUND if name == own else others * BOUND
                            for name in ('state', 'command', 'disturbance')})
    safety_filter = SafetyFilter(filter_config_from_params(shipped('unicycle')).problem,
                                 input_bounds=bounds)
    args = {'state': [2.0, -2.5, 0.0], 'u_rl': [0.0, 0.0], 'disturbance_mean': [0.0] * 3,
            'disturbance_std': [0.0] * 3}
    args[field][-1] = value
    result = safety_filter.filter(args['state'], args['u_rl'], args['disturbance_mean'],
                                  args['disturbance_std'])
    refused = expected_refusal(field, value)
    if refused is None:
        assert result.status != 'input_refused', result.reason
    else:
        assert result.status == 'input_refused'
        assert result.reason.startswith(f'{field}:') and refused in result.reason, result.reason


def test_constants_that_overflow_are_refused_on_both_paths_alike():
    # Gains and a centre whose products overflow: the generated code holds inf (and the NaN
    # of inf - inf) among its constants and runs; both paths refuse the data.
    system = PVTOL()
    circle = CircleObstacles(centers=((1e200, 0.0),), radii=(0.5,))
    problem = RCBFProblem(system, (cascade(circle, system, [1e200, 1e200]),))
    fast, autograd = SafetyFilter(problem), SafetyFilter(problem, closed_form=False)
    assert fast.assembly == 'closed_form'
    x = np.array([0.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0])
    a, b = fast.filter(x, [0.0, 0.0]), autograd.filter(x, [0.0, 0.0])
    assert a.status == b.status == 'input_refused'
    assert a.reason == b.reason
