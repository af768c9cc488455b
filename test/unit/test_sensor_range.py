"""Range sources (sonar, infrared rangers): a reading is the arc its object may lie on, widened so
that the arc is covered whole; REP 117's infinities; hostile bytes (messages encoded by rosbags,
coverage checked by dense sampling of the arc or sector, not by the reader's own formula)."""
from __future__ import annotations

import math

from hypothesis import example, given, HealthCheck, settings
from hypothesis import strategies as st
import numpy as np
import pytest
from sensor_messages import range_bytes

from rcbf_ros.core.config import filter_config_from_params
from rcbf_ros.core.filter import SafetyFilter
from rcbf_ros.messages import sensor
from rcbf_ros.node_logic.sources import ObservationSources

PROPERTY = settings(max_examples=150, deadline=None, derandomize=True,
                    suppress_health_check=[HealthCheck.too_slow])


def _nearest(points: np.ndarray, samples: np.ndarray) -> np.ndarray:
    """For each of ``samples`` (M, 2), its distance to the nearest of ``points`` (N, 2)."""
    return np.sqrt(((samples[:, None, :] - points[None, :, :]) ** 2).sum(-1)).min(1)


def _cone(r: float, half: float, rng: np.random.Generator, n: int = 3000) -> np.ndarray:
    """(x, y) of ``n`` points at distance ``r`` whose direction lies within ``half`` of the x
    axis (a sonar's cone, sampled uniformly on its cap by rejection), its rim and the arc of
    its plane included."""
    directions = rng.normal(size=(40 * n, 3))
    directions /= np.linalg.norm(directions, axis=1)[:, None]
    inside = directions[directions[:, 0] >= math.cos(half)][:n]
    phi = np.linspace(-half, half, 501)
    rim = np.stack([np.full(501, math.cos(half)), np.sin(half) * np.cos(phi),
                    np.sin(half) * np.sin(phi)], axis=1)   # the cone's edge, all round
    arc = np.stack([np.cos(phi), np.sin(phi), np.zeros(501)], axis=1)
    return r * np.concatenate([inside, rim, arc])[:, :2]


@PROPERTY
@given(reading=st.floats(0.02, 4.0), fov=st.floats(0.0, 2 * math.pi),
       angle=st.floats(sensor.MIN_OBSTACLES_ANGLE * 10, math.pi), seed=st.integers(0, 2**16))
@example(reading=4.0, fov=2 * math.pi, angle=math.pi, seed=0)  # a full turn: the whole disc
@example(reading=1.0, fov=0.0, angle=0.1, seed=0)  # a beam: one point, no widening
@example(reading=2.0, fov=0.5, angle=math.pi / 180, seed=0)  # a sonar's 0.5 rad cone
def test_a_reading_covers_wherever_its_object_may_lie(reading, fov, angle, seed):
    # the object lies at distance r within the cone of half-angle fov / 2: wherever it projects
    # onto the plane, a drawn point's circle widened by spread holds it
    out = sensor.range_points(range_bytes(reading, field_of_view=fov), obstacles_angle=angle)
    r, half = float(np.float32(reading)), float(np.float32(fov)) / 2
    assert not isinstance(out, sensor.Refused), out
    assert (out.frame_id, out.received, out.reach) == ('sonar', 1, r)
    radii = np.hypot(*out.points.T)
    np.testing.assert_allclose(radii, radii[0], rtol=1e-12)
    assert r * max(math.cos(half), 0.0) - 1e-12 <= radii[0] <= r + 1e-12
    if half <= math.pi / 2:
        covered = _cone(r, half, np.random.default_rng(seed))
    else:  # a cone wider than a half-space reaches every point within r, at any azimuth
        rho, phi = r * np.sqrt(np.random.default_rng(seed).uniform(0, 1, 3000)), np.linspace(
            -math.pi, math.pi, 3000)
        covered = np.stack([rho * np.cos(phi), rho * np.sin(phi)], axis=1)
    assert _nearest(out.points, covered).max() <= out.spread * (1 + 1e-9) + 1e-12
    if fov == 0.0:
        assert len(out.points) == 1 and out.spread == 0.0
    elif half <= math.pi / 2:
        assert len(out.points) == math.ceil(2 * half / angle) + 1
        assert out.spread <= r * (1 - math.cos(half)) / 2 + r * min(angle, fov) / 2 + 1e-12


@PROPERTY
@given(min_range=st.floats(0.0, 2.0), fov=st.floats(0.0, 2 * math.pi),
       angle=st.floats(0.01, math.pi), seed=st.integers(0, 2**16))
def test_too_close_to_measure_covers_the_whole_sector_within_min_range(min_range, fov, angle,
                                                                        seed):
    # Range.msg: -inf is a detection nearer than the ranger can measure
    out = sensor.range_points(range_bytes(-math.inf, field_of_view=fov, min_range=min_range),
                              obstacles_angle=angle)
    assert not isinstance(out, sensor.Refused), out
    m, half = float(np.float32(min_range)), float(np.float32(fov)) / 2
    rng = np.random.default_rng(seed)
    rho, phi = m * np.sqrt(rng.uniform(0, 1, 2000)), rng.uniform(-half, half, 2000)
    rho[:2], phi[:2] = (0.0, m), (half, -half)  # the apex and a far corner
    sector = np.stack([rho * np.cos(phi), rho * np.sin(phi)], axis=1)
    assert _nearest(out.points, sector).max() <= out.spread * (1 + 1e-9) + 1e-12
    assert out.reach == m


@pytest.mark.parametrize('reading', [math.inf, math.nan, 0.01, 4.5, 1e30])
def test_a_reading_that_says_nothing_is_no_point_and_no_refusal(reading):
    # +inf: nothing within range; NaN or outside [min_range, max_range]: discarded (REP 117)
    out = sensor.range_points(range_bytes(reading))
    assert not isinstance(out, sensor.Refused), out
    assert out.points.shape == (0, 2) and out.received == 1


@pytest.mark.parametrize(('kwargs', 'words'), [
    ({'field_of_view': math.nan}, 'field_of_view nan is not within [0, 2 pi]'),
    ({'field_of_view': -0.1}, 'field_of_view -0.1'),
    ({'field_of_view': 7.0}, 'field_of_view 7.0'),
    ({'field_of_view': math.inf}, 'field_of_view inf'),
    ({'min_range': math.nan}, 'min_range is nan'),
    ({'max_range': math.nan}, 'max_range is nan'),
    ({'min_range': 3.0, 'max_range': 2.0}, 'min_range 3.0 > max_range 2.0'),
])
def test_bad_geometry_is_refused_in_one_line_naming_the_field(kwargs, words):
    out = sensor.range_points(range_bytes(1.0, **kwargs))
    assert isinstance(out, sensor.Refused)
    assert out.reason.startswith(f'{sensor.RANGE}: ') and words in out.reason, out.reason


def test_too_close_with_no_bound_and_a_bad_resolution_are_refused():
    out = sensor.range_points(range_bytes(-math.inf, min_range=math.inf, max_range=math.inf))
    assert isinstance(out, sensor.Refused) and 'range is -inf with min_range inf' in out.reason
    for angle in (0.0, 1e-4, math.nan, 4.0, -1.0):
        out = sensor.range_points(range_bytes(1.0), obstacles_angle=angle)
        assert isinstance(out, sensor.Refused) and 'obstacles_angle' in out.reason


@pytest.mark.filterwarnings('error::RuntimeWarning')  # no numpy warning on the node's log
@PROPERTY
@given(reading=st.floats(width=32), fov=st.floats(width=32), low=st.floats(width=32),
       high=st.floats(width=32), little=st.booleans(), cut=st.integers(0, 60),
       flips=st.lists(st.tuples(st.integers(0, 80), st.integers(0, 255)), max_size=4))
def test_hostile_range_bytes_never_raise(reading, fov, low, high, little, cut, flips):
    data = bytearray(range_bytes(reading, field_of_view=fov, min_range=low, max_range=high,
                                 little_endian=little))
    for where, value in flips:
        if where < len(data):
            data[where] = value
    out = sensor.range_points(bytes(data[:max(len(data) - cut, 0)]))
    if isinstance(out, sensor.Refused):
        assert out.reason and '\n' not in out.reason and len(out.reason) <= 300
    else:
        assert out.points.ndim == 2 and out.points.shape[1] == 2
        assert np.all(np.isfinite(out.points)) and math.isfinite(out.spread)
        assert len(out.points) <= 2 * math.pi / (math.pi / 180) + 2


_PARAMS = {
    'system': 'unicycle', 'alpha': 2.0, 'input_weight': [1.0, 0.01],
    'input_limits.min': [-1.0, -2.0], 'input_limits.max': [1.0, 2.0],
    'obstacles.margin': 0.05, 'obstacles.lookahead': 0.015, 'obstacles.heading_index': 2,
    'obstacles.speed_input': 0, 'footprint.radius': 0.2,
    'observation_sources': ['sonar'], 'sonar.type': 'range', 'sonar.topic': 'sonar/front',
}


def test_a_sonar_reading_ahead_brakes_the_robot_and_nothing_in_range_lets_it_go():
    config = filter_config_from_params(_PARAMS)
    assert config.sources.sources[0][1].obstacles_angle == pytest.approx(math.pi / 180)
    sources = ObservationSources(config.sources)
    safety_filter = SafetyFilter(config.problem, footprint=config.footprint)
    state = np.array([0.0, 0.0, 0.0])
    answers = []
    for reading in (0.5, math.inf):
        data = bytearray(range_bytes(reading, field_of_view=0.6, frame_id='base_link'))
        data[4:8] = (10).to_bytes(4, 'little')  # header.stamp 10 s
        data[8:12] = (0).to_bytes(4, 'little')
        assert sources.read('sonar', bytes(data), received_ns=0) == ''
        assert sources.note_state(state, stamp_ns=10 * 10**9) == ''
        assert sources.sense(safety_filter, state, now_ns=0, stamp_now_ns=10 * 10**9) == ''
        answers.append(safety_filter.filter(state, [1.0, 0.0]))
    braked, free = answers
    assert not braked.fail_safe and braked.u_safe[0] < 0.5  # kept off the whole arc
    assert np.all(braked.points.h >= 0.0)
    assert np.array_equal(free.u_safe, [1.0, 0.0])


@pytest.mark.parametrize(('value', 'words'), [(0.0, 'sonar.obstacles_angle'),
                                              (4.0, 'sonar.obstacles_angle')])
def test_a_bad_obstacles_angle_is_refused_at_start_naming_the_key(value, words):
    from rcbf_ros.parameters.reader import ParameterError
    with pytest.raises((ParameterError, ValueError)) as error:
        filter_config_from_params({**_PARAMS, 'sonar.obstacles_angle': value})
    assert str(error.value).startswith(words), str(error.value)
