"""Shared machinery of the simulated systems: parameters, the Gymnasium loop, the step info.

Every env is built from the *flat* ROS parameters of ``config/<system>.yaml`` (``/**`` merged
with ``/simulator``, e.g.
``rcbf_ros.parameters.rules.load_params(find_config('unicycle'), 'simulator')``)
plus keyword overrides, where a double underscore stands for the dot of a nested key
(``obstacles__x=[...]`` overrides ``obstacles.x``). The layout therefore comes from the same
``obstacles.*`` keys the safety filter reads; :meth:`SafetyEnv.filter_params` hands back those
keys for the env's *current* layout, so that ``filter_config_from_params(env.filter_params())``
builds the safety problem the env is actually running.

``step(u)`` applies u as given (the env never filters); it saturates u at the actuator limits of
the nominal model (physical saturation) when the model has limits. ``info`` of every step (and of
``reset``) holds:

- ``state``: (n_x,) the QP state (what the filter and the learner see);
- ``h_true``: (K_true,) signed clearances on the TRUE geometry, > 0 safe (names in
  ``env.h_true_names``); ``violation``: any ``h_true < 0``;
- ``goal_reached``: the episode ended at the goal; ``t``: time since reset [s].

An env class that sets ``system_name`` joins that system's entry of the table
(:mod:`rcbf_ros.messages.systems`) when it is defined; it also holds the system's deliberately
unsafe nominal controller (:meth:`SafetyEnv.nominal_controller`) and, where the reward and
observation are functions of the state, their batched torch restatement for model-based
rollouts (:meth:`SafetyEnv.torch_models`).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, ClassVar, Mapping, Sequence, TYPE_CHECKING

import gymnasium as gym
import numpy as np

from rcbf_ros.core.config import FILTER_OPEN_PREFIXES, FilterParameters, flatten
from rcbf_ros.core.dynamics import CLOSED_FORM_SYSTEMS, ControlAffineSystem, DriftJetFunction
from rcbf_ros.core.torch_import import LazyTorch, load_torch
from rcbf_ros.envs.layouts import layout_from_params
from rcbf_ros.messages import systems
from rcbf_ros.parameters.reader import parameter_keys, read_floats, read_parameters, setting

torch = LazyTorch(globals())  # imported where first used: see rcbf_ros.core.torch_import
if TYPE_CHECKING:
    from torch import Tensor

Controller = Callable[[np.ndarray], np.ndarray]
"""A nominal controller: the QP state (n_x,) -> u (n_u,)."""
RewardFn = Callable[['Tensor', 'Tensor', 'Tensor'], tuple['Tensor', 'Tensor']]
"""(state, u, next_state): (B, n_x), (B, n_u), (B, n_x) -> reward (B,), goal reached (B,)."""
ObsFn = Callable[['Tensor'], 'Tensor']
"""state (B, n_x) -> observation (B, n_obs)."""

FILTER_KEYS: tuple[str, ...] = parameter_keys(FilterParameters)
"""Flat keys (exact) that :func:`rcbf_ros.core.config.filter_config_from_params` reads."""
FILTER_PREFIXES: tuple[str, ...] = FILTER_OPEN_PREFIXES
"""Key prefixes (names the user chooses) that
:func:`rcbf_ros.core.config.filter_config_from_params` reads."""


def merge_params(params: Mapping[str, Any] | None, overrides: Mapping[str, Any]) -> dict[str, Any]:
    """Flatten ``params`` and apply keyword overrides (``a__b`` -> ``a.b``)."""
    merged = flatten(dict(params or {}))
    for key, value in overrides.items():
        merged[key.replace('__', '.')] = value
    return merged


DT_LIMITS_S = (1e-4, 1.0)
"""The range of an integration step ``dt`` (s): an Euler step of the shipped systems beyond a
second leaves them (and overflows); one under 0.1 ms never gets anywhere."""


@dataclass(frozen=True)
class EnvSettings:
    """Parameters every simulated system reads (subclassed per system)."""

    dt: float = setting(0.02, minimum=DT_LIMITS_S[0], maximum=DT_LIMITS_S[1],
                        description='integration step (s)')
    """Euler step [s]."""


@dataclass(frozen=True)
class GoToGoalSettings(EnvSettings):
    """The keys the go-to-goal systems (Unicycle, PVTOL) share; each subclass adds its goal,
    start, episode length and goal reward with its own defaults."""

    goal_radius: float = setting(
        0.3, positive=True,
        description='the episode ends with the goal reward within this distance (m)')
    """The episode ends at the goal within this distance (m)."""
    random_start: bool = setting(
        False, text_bool=True,
        description='start among the packaged start points with a random heading')
    """Start among the system's packaged start points."""
    layout: str = setting(
        'fixed', choices=('fixed', 'random'),
        description='fixed (obstacles.* here) or random (a seeded transfer layout per reset)')
    """fixed (the obstacles.* keys) or random (a seeded layout per reset)."""
    layout_seed: int = setting(-1, description='>= 0 pins one random layout (-1: a new one per '
                                               'reset)')
    """>= 0 pins one random layout."""
    max_steps: int = setting(1000, minimum=1,
                             description='steps per episode before it is truncated')
    """Steps before truncation."""
    goal: tuple[float, ...] = setting((0.0, 0.0), length=2,
                                      description='goal position [x, y] (m)')
    """Goal position (m)."""
    goal_reward: float = setting(1.0, description='reward for reaching the goal')
    """Reward for reaching the goal."""


def layout_lists(params: Mapping[str, Any]) -> tuple[tuple[float, ...], ...]:
    """``obstacles.x``, ``.y`` and ``.radius`` as floats (each may be empty)."""
    return tuple(read_floats(f'obstacles.{name}', params.get(f'obstacles.{name}'))
                 for name in ('x', 'y', 'radius'))


def input_limits(params: Mapping[str, Any], n_u: int) -> dict[str, tuple[float, ...]]:
    """``u_min`` / ``u_max`` of ``input_limits.min/max`` (n_u values each) when the parameters
    set them, else {} (the system's own)."""
    if 'input_limits.min' not in params:
        return {}
    return {'u_min': read_floats('input_limits.min', params['input_limits.min'], length=n_u),
            'u_max': read_floats('input_limits.max', params.get('input_limits.max', ()),
                                 length=n_u)}


class SafetyEnv(gym.Env):
    """Base of the three simulated systems (see module docstring).

    Subclasses set ``system_name`` and implement ``_reset_state``, ``_true_derivative``,
    ``_observation``, ``_reward_and_goal``, ``_h_true`` and ``_set_layout_filter_params``.
    """

    system_name: ClassVar[str] = ''
    """The table name this env simulates (a subclass that sets it joins that entry)."""
    gymnasium_id: ClassVar[str] = ''
    """Its id in Gymnasium's registry ('': not registered)."""
    settings_type: ClassVar[type[EnvSettings]] = EnvSettings
    """The dataclass of the system's parameters (read into ``self.settings``)."""
    controller_settings: ClassVar[type | None] = None
    """The dataclass of the nominal controller's own parameters (``/nominal_controller``),
    None: it reads the env's (the goal)."""
    metadata: ClassVar[dict[str, Any]] = {'render_modes': []}

    nominal_system: ControlAffineSystem
    """The agent's prior f, g (rcbf_ros.core.dynamics) for the current layout."""
    dt: float
    """Euler step [s]."""
    max_steps: int
    """Steps before truncation."""
    h_true_names: list[str]
    """Names of the ``info['h_true']`` entries."""

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        systems.join(cls, 'env')

    @classmethod
    def nominal_controller(cls, params: Mapping[str, Any]) -> Controller:
        """The system's deliberately unsafe nominal controller (:mod:`rcbf_ros.envs.nominal`)
        with its parameters from the flat ``params`` bound.

        Raises:
            ValueError: naming ``system`` where the system has none, or the parameter refused.
        """
        raise ValueError(f'system: no nominal controller for {cls.system_name!r}')

    def torch_models(self) -> tuple[RewardFn, ObsFn] | None:
        """The reward and observation of this env as batched torch functions of the state (for
        model-based rollouts: synthetic transitions from states the plant never visited); None
        where the observation is not a function of the state alone."""
        return None

    def __init__(self, params: Mapping[str, Any] | None, overrides: Mapping[str, Any]) -> None:
        self.params = merge_params(params, overrides)
        system = self.params.get('system', self.system_name)
        if system != self.system_name:
            raise ValueError(f'system: this env simulates {self.system_name!r}, '
                             f'the parameters name {system!r}')
        self.settings = read_parameters(self.settings_type, self.params)
        self.dt = self.settings.dt
        self._state = np.zeros(0)
        self._steps = 0
        self._has_reset = False
        self._nominal_jet: tuple[ControlAffineSystem, DriftJetFunction | None] | None = None
        """The model :meth:`nominal_terms` last evaluated, and its closed form (or None)."""

    # -- public API -------------------------------------------------------------------------

    @property
    def state(self) -> np.ndarray:
        """(n_x,) the current QP state (a copy)."""
        return self._state.copy()

    @property
    def t(self) -> float:
        """Time since reset [s]."""
        return self._steps * self.dt

    @property
    def steps(self) -> int:
        """Steps since reset."""
        return self._steps

    def filter_params(self, base: Mapping[str, Any] | None = None) -> dict[str, Any]:
        """Flat safety-filter parameters for the env's CURRENT layout.

        Args:
            base: optional extra parameters (e.g. the ``/safety_filter`` section) merged over
                the env's own before the layout keys are set.

        Returns:
            Only the keys :func:`rcbf_ros.core.config.filter_config_from_params` reads, with
            ``system`` and the layout keys (``obstacles.x/y/radius``, operator band, ...) of the
            current episode.
        """
        source = dict(self.params)
        source.update(flatten(dict(base or {})))
        out = {k: v for k, v in source.items()
               if k in FILTER_KEYS or k.startswith(FILTER_PREFIXES)}
        out['system'] = self.system_name
        self._set_layout_filter_params(out)
        return out

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None
              ) -> tuple[np.ndarray, dict[str, Any]]:
        """Start an episode; ``seed`` seeds the env's generator (layouts, starts, noise)."""
        super().reset(seed=seed)
        self._steps = 0
        self._state = np.asarray(self._reset_state(options or {}), dtype=np.float64)
        self._has_reset = True
        return self._observation(), self._info(goal_reached=False)

    def step(self, action: Sequence[float] | np.ndarray
             ) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        """Apply u for one Euler step of the TRUE dynamics (the env never filters).

        Raises:
            RuntimeError: before the first ``reset``.
            ValueError: naming ``action`` for a wrong length or NaN/inf.
        """
        if not self._has_reset:
            raise RuntimeError('step() before reset()')
        u = np.asarray(action, dtype=np.float64).reshape(-1)
        n_u = self.nominal_system.n_u
        if u.shape != (n_u,):
            raise ValueError(f'action: expected {n_u} values, got {u.size}')
        if not np.all(np.isfinite(u)):
            raise ValueError('action: contains NaN or inf')
        u = self.saturate(u)
        previous = self._state
        self._state = previous + self.dt * self._true_derivative(previous, u)
        self._state = self._post_step(self._state)
        self._steps += 1
        reward, goal_reached = self._reward_and_goal(previous, u)
        terminated = goal_reached
        truncated = (not terminated) and self._steps >= self.max_steps
        return (self._observation(), float(reward), terminated, truncated,
                self._info(goal_reached=goal_reached))

    def saturate(self, u: np.ndarray) -> np.ndarray:
        """Clip u to the nominal model's actuator limits (unchanged when it has none)."""
        system = self.nominal_system
        if system.u_min is None or system.u_max is None:
            return u
        return np.clip(u, system.u_min, system.u_max)

    def nominal_terms(self, state: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """f(x): (n_x,) and g(x): (n_x, n_u) of the nominal model at one state.

        A built-in model (by exact type) is evaluated through its closed form, the source the
        filter's assembly inlines (numpy, no torch); any other model through its batched torch
        ``f`` and ``g`` (torch imported here, saying how to install it where it is missing).
        """
        system = self.nominal_system
        cached = self._nominal_jet
        if cached is None or cached[0] is not system:
            jet = (system.closed_form_source().function()
                   if type(system) in CLOSED_FORM_SYSTEMS else None)
            cached = self._nominal_jet = (system, jet)
        jet: DriftJetFunction | None = cached[1]
        if jet is not None:
            terms = jet(state)
            return terms.f, terms.g
        torch = load_torch()
        x = torch.as_tensor(state, dtype=torch.float64).unsqueeze(0)
        return system.f(x)[0].numpy(), system.g(x)[0].numpy()

    def h_true(self, state: np.ndarray | None = None) -> np.ndarray:
        """(K_true,) true signed clearances at ``state`` (default: the current state)."""
        return np.asarray(self._h_true(self._state if state is None else state),
                          dtype=np.float64)

    # -- subclass hooks -----------------------------------------------------------------------

    def _reset_state(self, options: dict[str, Any]) -> np.ndarray:
        raise NotImplementedError

    def _true_derivative(self, state: np.ndarray, u: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    def _post_step(self, state: np.ndarray) -> np.ndarray:
        return state

    def _observation(self) -> np.ndarray:
        raise NotImplementedError

    def _reward_and_goal(self, previous: np.ndarray, u: np.ndarray) -> tuple[float, bool]:
        raise NotImplementedError

    def _h_true(self, state: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    def _set_layout_filter_params(self, params: dict[str, Any]) -> None:
        """Write the current layout's keys into the flat filter parameters (in place)."""

    # -- helpers --------------------------------------------------------------------------------

    def _info(self, *, goal_reached: bool) -> dict[str, Any]:
        h = self.h_true()
        return {'state': self.state, 'h_true': h, 'violation': bool(np.any(h < 0.0)),
                'goal_reached': bool(goal_reached), 't': self.t}


class GoToGoalReward:
    """Reward of the go-to-goal systems (Unicycle, PVTOL): progress toward ``goal`` plus
    ``goal_reward`` once on arrival within ``goal_radius``, which ends the episode."""

    goal: np.ndarray
    goal_radius: float
    goal_reward: float
    max_steps: int
    obstacles: tuple[Any, ...]
    params: dict[str, Any]
    _last_distance: float
    _state: np.ndarray

    def _take_goal_settings(self, settings: GoToGoalSettings) -> None:
        """The goal, episode length and fixed layout of ``settings`` (a random layout is drawn
        later, see the subclasses)."""
        self.max_steps = settings.max_steps
        self.goal = np.asarray(settings.goal)
        self.goal_radius = settings.goal_radius
        self.goal_reward = settings.goal_reward
        self.random_start = settings.random_start
        self.obstacles = layout_from_params(*layout_lists(self.params),
                                            self.params.get('obstacles.shape'))

    def _reward_and_goal(self, previous: np.ndarray, u: np.ndarray) -> tuple[float, bool]:
        distance = float(np.linalg.norm(self._state[:2] - self.goal))
        reward = self._last_distance - distance
        self._last_distance = distance
        reached = distance <= self.goal_radius
        return reward + (self.goal_reward if reached else 0.0), reached

    go_to_goal: ClassVar[Callable[..., np.ndarray]]
    """The nominal controller: (state, goal) -> u, straight at the goal."""
    settings_type: ClassVar[type[GoToGoalSettings]]

    @classmethod
    def nominal_controller(cls, params: Mapping[str, Any]) -> Controller:
        """:attr:`go_to_goal` at ``goal`` (default: the env's own goal, the one an episode
        rewards).

        Raises:
            ValueError: naming ``goal`` when malformed.
        """
        goal = read_floats('goal', params.get('goal', cls.settings_type.goal), length=2)
        drive = cls.go_to_goal
        return lambda x: drive(x, goal)

    def torch_models(self) -> tuple[RewardFn, ObsFn] | None:
        """The go-to-goal reward (:func:`go_to_goal_reward`) and :meth:`_torch_observation`."""
        goal = torch.as_tensor(self.goal, dtype=torch.float64)

        def obs(state: Tensor) -> Tensor:
            return self._torch_observation(state, goal.to(state.dtype))

        return go_to_goal_reward(goal, self.goal_radius, self.goal_reward), obs

    def _torch_observation(self, state: Tensor, goal: Tensor) -> Tensor:
        """The observation of a batch of states (B, n_x), as :meth:`_observation` gives it."""
        raise NotImplementedError


def goal_terms(position: Tensor, heading: Tensor, goal: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """cos/sin of the heading, the unit goal direction in the body frame, the distance
    (batched: position (B, 2), heading (B,), goal (2,))."""
    to_goal = goal - position
    distance = to_goal.norm(dim=-1)
    c, s = torch.cos(heading), torch.sin(heading)
    body = torch.stack([c * to_goal[:, 0] + s * to_goal[:, 1],
                        -s * to_goal[:, 0] + c * to_goal[:, 1]], dim=-1)
    body = body / (body.norm(dim=-1, keepdim=True) + 1e-3)
    return torch.stack([c, s], dim=-1), body, distance


def go_to_goal_reward(goal: Tensor, radius: float, bonus: float) -> RewardFn:
    """Progress toward the goal plus ``bonus`` (once) on arrival; arrival ends the episode."""

    def reward(state: Tensor, u: Tensor, next_state: Tensor) -> tuple[Tensor, Tensor]:
        g = goal.to(state.dtype)
        before = (state[:, :2] - g).norm(dim=-1)
        after = (next_state[:, :2] - g).norm(dim=-1)
        reached = after <= radius
        return before - after + bonus * reached.to(state.dtype), reached

    return reward
