"""Learned value maps of the Unicycle (paper: "Modular Task Learning", value-function figure).

For a trained run, over a grid of positions (x, y) in the arena,

    V(x, y) = max_k  min_{i=1,2} Q_i(o(x, y, theta_k), mu_pi(o(x, y, theta_k)))

with o the env's observation of the state (x, y, theta) (SafetyEnv.torch_models, checked
against the env), mu_pi the policy's mean action and theta_k, k < n_headings, evenly spaced
headings: the value at the best heading, i.e. where the robot could be pointed. Using the mean
action and dropping the entropy term (-alpha log pi) gives the deterministic policy's value; the
shape of the map, not its offset, is what the comparison reads (low values around the training
obstacles for SAC-RCBF; none for the unconstrained and the modular critic).
"""
from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np
import torch

from rcbf_ros.envs import make_env
from rcbf_ros.parameters.rules import find_config, load_params
from rcbf_ros.training.agent import SafeLearner


def value_map(learner: SafeLearner, *, grid: int = 61, half_size: float = 3.0,
              n_headings: int = 8, config_file: str | None = None
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(xs: (grid,), ys: (grid,), V: (grid, grid) indexed [iy, ix]) of a Unicycle learner.

    Raises:
        ValueError: naming ``grid`` or ``n_headings`` when < 2 / < 1.
    """
    if grid < 2:
        raise ValueError(f'grid: must be >= 2, got {grid}')
    if n_headings < 1:
        raise ValueError(f'n_headings: must be >= 1, got {n_headings}')
    env = make_env('unicycle', load_params(find_config(config_file or 'unicycle'), 'simulator'))
    _, obs_fn = env.torch_models()
    xs = np.linspace(-half_size, half_size, grid)
    ys = np.linspace(-half_size, half_size, grid)
    headings = np.linspace(-np.pi, np.pi, n_headings, endpoint=False)
    gy, gx, gh = np.meshgrid(ys, xs, headings, indexing='ij')  # (grid, grid, n_headings)
    states = torch.as_tensor(np.stack([gx, gy, gh], axis=-1).reshape(-1, 3))
    sac = learner.sac
    with torch.no_grad():
        obs = obs_fn(states).to(sac.dtype)
        action = sac.policy_action(obs, deterministic=True)
        q = torch.minimum(sac.q1(obs, action), sac.q2(obs, action))
    values = q.reshape(grid, grid, n_headings).max(dim=-1).values.numpy().astype(np.float64)
    return xs, ys, values


def map_contrast(maps: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]],
                 obstacles: Sequence[tuple[float, float, float]], *,
                 reference: str = 'sac_no_obstacles', ring: float = 0.4
                 ) -> dict[str, dict[str, float]]:
    """Two numbers per map for the paper's reading of the figure (no eyeballing).

    Over the grid cells outside every obstacle (distance to its centre > radius):

    - ``corr_reference``: Pearson correlation with the ``reference`` map (the critic trained
      without obstacles); 1 means the same shape;
    - ``ring_z``: the mean standardised value, (V - mean V) / std V, on the cells within
      ``ring`` metres of an obstacle's edge. A critic that learned the filter's corrections
      near the training obstacles is low there (negative); a task-only critic is not.

    Args:
        maps: method -> (xs, ys, V[iy, ix]), all on the same grid.
        obstacles: (x, y, radius) of the training obstacles.
        reference: key of the reference map (absent: ``corr_reference`` is NaN).
        ring: width of the band around each obstacle, metres.

    Raises:
        ValueError: naming ``ring`` when <= 0, or ``maps`` when the grids differ.
    """
    if ring <= 0:
        raise ValueError(f'ring: must be > 0, got {ring}')
    grids = {(tuple(xs), tuple(ys)) for xs, ys, _ in maps.values()}
    if len(grids) > 1:
        raise ValueError('maps: every map must share one grid')
    out: dict[str, dict[str, float]] = {}
    if not maps:
        return out
    xs, ys, _ = next(iter(maps.values()))
    gx, gy = np.meshgrid(xs, ys)  # [iy, ix], like V
    clearance = np.full(gx.shape, np.inf)
    for x, y, r in obstacles:
        clearance = np.minimum(clearance, np.hypot(gx - x, gy - y) - r)
    outside, near = clearance > 0, (clearance > 0) & (clearance <= ring)
    ref = maps[reference][2][outside] if reference in maps else None
    for method, (_, _, values) in maps.items():
        v = values[outside]
        z = (values - v.mean()) / v.std() if v.std() > 0 else np.zeros_like(values)
        out[method] = {
            'corr_reference': (float(np.corrcoef(ref, v)[0, 1])
                               if ref is not None and v.std() > 0 and ref.std() > 0
                               else float('nan')),
            'ring_z': float(z[near].mean()) if near.any() else float('nan')}
    return out


def plot_value_maps(maps: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]],
                    path: str | Path, *, obstacles: Sequence[tuple[float, float, float]],
                    starts: Sequence[Sequence[float]], goal: Sequence[float],
                    goal_radius: float) -> Path:
    """One panel per method (own colour scale), training obstacles red, starts blue, goal
    green, as the paper's figure."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    fig, axes = plt.subplots(1, len(maps), figsize=(4.2 * len(maps), 3.8), dpi=100,
                             squeeze=False)
    for ax, (label, (xs, ys, values)) in zip(axes[0], maps.items()):
        image = ax.imshow(values, origin='lower', extent=(xs[0], xs[-1], ys[0], ys[-1]),
                          cmap='viridis')
        fig.colorbar(image, ax=ax, fraction=0.046)
        for x, y, r in obstacles:
            ax.add_patch(plt.Circle((x, y), r, fill=False, color='red', lw=1.5))
        for start in starts:
            ax.add_patch(plt.Circle(tuple(start[:2]), 0.15, fill=False, color='blue', lw=1.5))
        ax.add_patch(plt.Circle(tuple(goal), goal_radius, fill=False, color='lime', lw=2))
        ax.set_title(label)
        ax.set_aspect('equal')
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path)
    plt.close(fig)
    return path
