"""Plots (matplotlib, headless): reward curves, mean +/- 2 std bands over seeds, and the
trajectory picture of a run (:func:`plot_trajectories`)."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping, NamedTuple, Sequence

import numpy as np

from rcbf_ros.core.scene import SceneGeometry
from rcbf_ros.envs.layouts import Obstacle, signed_clearance

MATPLOTLIB_HINT = ('matplotlib draws the pictures: pip install matplotlib (or apt install '
                   'python3-matplotlib)')
"""What the ImportError of a missing matplotlib says."""


def _pyplot():
    try:
        import matplotlib
    except ImportError as exc:  # not in the filter's install (setup.py's extra 'filter')
        raise ImportError(f'{MATPLOTLIB_HINT} ({exc})') from exc
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    return plt


def plot_reward_curve(returns: Sequence[float], path: str | Path, *, title: str = '') -> Path:
    """Return per episode (and a moving average) as a PNG."""
    plt = _pyplot()
    returns = np.asarray(returns, dtype=float)
    fig, ax = plt.subplots(figsize=(6, 3.5), dpi=120)
    episodes = np.arange(1, len(returns) + 1)
    ax.plot(episodes, returns, color='tab:blue', alpha=0.4, label='episode return')
    window = max(1, min(10, len(returns) // 5))
    if window > 1:
        smooth = np.convolve(returns, np.ones(window) / window, mode='valid')
        ax.plot(episodes[window - 1:], smooth, color='tab:blue', label=f'mean of {window}')
    ax.set_xlabel('episode')
    ax.set_ylabel('return')
    ax.set_title(title)
    ax.grid(alpha=0.3)
    ax.legend(loc='lower right')
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path)
    plt.close(fig)
    return path


def plot_reward_bands(curves: Mapping[str, Sequence[Sequence[float]]], path: str | Path, *,
                      title: str = '') -> Path:
    """Mean return per episode with a 2-standard-deviation band, one line per method.

    Args:
        curves: method -> list over seeds of per-episode returns (truncated to the shortest).
    """
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(6.5, 4), dpi=120)
    for method, runs in curves.items():
        length = min(len(r) for r in runs)
        data = np.asarray([r[:length] for r in runs], dtype=float)
        mean, std = data.mean(0), data.std(0)
        episodes = np.arange(1, length + 1)
        ax.plot(episodes, mean, label=f'{method} (n={len(runs)})')
        ax.fill_between(episodes, mean - 2 * std, mean + 2 * std, alpha=0.2)
    ax.set_xlabel('episode')
    ax.set_ylabel('return')
    ax.set_title(title)
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path)
    plt.close(fig)
    return path


def plot_critic_vs_return(runs: Mapping[str, Mapping[int, tuple[Sequence[float],
                                                                  Sequence[float]]]],
                          path: str | Path, *, title: str = '') -> Path:
    """The critics' value of each training episode's first step (solid) against the
    discounted return that followed (dashed): one panel per method, one colour per seed.
    A solid line far above its dashed one is over-estimation.

    Args:
        runs: method -> seed -> (q_start per episode, disc_return per episode).
    """
    from matplotlib.ticker import MaxNLocator
    plt = _pyplot()
    fig, axes = plt.subplots(1, len(runs), figsize=(3.2 * len(runs) + 0.8, 3.6), dpi=120,
                             squeeze=False, sharey=True)
    for ax, (method, seeds) in zip(axes[0], runs.items()):
        for index, (seed, (q_start, disc_return)) in enumerate(sorted(seeds.items())):
            colour = f'C{index % 10}'
            ax.plot(np.arange(1, len(q_start) + 1), q_start, color=colour, label=f'seed {seed}')
            ax.plot(np.arange(1, len(disc_return) + 1), disc_return, color=colour,
                    linestyle='--')
        ax.set_title(method, fontsize=9)
        ax.set_xlabel('episode')
        ax.xaxis.set_major_locator(MaxNLocator(integer=True))
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    axes[0][0].set_ylabel('Q(x0, u0) solid, discounted return dashed')
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path)
    plt.close(fig)
    return path


# --------------------------------------------------------------------------- trajectories
CORRECTION_THRESHOLD = 1e-7
"""A step counts as corrected by the filter when |u_S| exceeds this."""
MAX_LEGEND_EPISODES = 10
"""Up to this many episodes get a legend entry each; more get a colour bar."""


@dataclass(frozen=True)
class EpisodePath:
    """One episode as a trajectory picture draws it."""

    episode: int
    """The episode's number (1 = the first)."""
    states: np.ndarray
    """(T, n_x) the states, in step order."""
    corrected: np.ndarray
    """(T,) bool: the filter corrected the command answering ``states[t]`` (|u_S| > 1e-7)."""

    def __post_init__(self) -> None:
        states = np.asarray(self.states, dtype=np.float64)
        corrected = np.asarray(self.corrected, dtype=bool).reshape(-1)
        if states.ndim != 2 or corrected.size != states.shape[0]:
            raise ValueError(f'episode {self.episode}: states {states.shape} and corrected '
                             f'{corrected.shape} do not match')
        object.__setattr__(self, 'states', states)
        object.__setattr__(self, 'corrected', corrected)


@dataclass(frozen=True)
class ClosestApproach:
    """Where the robot came closest to an obstacle (or the cars closest to each other)."""

    distance: float
    """Clearance [m]: from the robot's position to the obstacle's true boundary (negative
    inside); for car following, the distance between the two cars."""
    episode: int
    """The episode's number."""
    step: int
    """Index into that episode's states."""
    barrier: str
    """Name of the obstacle's (or gap's) barrier."""

    def describe(self) -> str:
        """``0.052 m to obstacle_3 (episode 4, step 310)``."""
        return (f'{self.distance:.3f} m to {self.barrier} (episode {self.episode}, step '
                f'{self.step})')


class TrajectoryPicture(NamedTuple):
    """What :func:`plot_trajectories` wrote."""

    path: Path
    """The PNG."""
    closest: ClosestApproach | None
    """The closest approach it labels (None: no obstacle or gap, or no state)."""


def _true_obstacles(geometry: SceneGeometry, obstacles: Sequence[Obstacle] | None
                    ) -> list[Obstacle]:
    if obstacles is not None:
        return list(obstacles)
    return [Obstacle(d.x, d.y, d.radius) for d in geometry.obstacles if d.radius > 0]


def _clearances(points: np.ndarray, obstacle: Obstacle) -> np.ndarray:
    """(T,) signed clearance of points (T, 2) to an obstacle's true shape."""
    if obstacle.shape == 'circle':
        return np.hypot(points[:, 0] - obstacle.x, points[:, 1] - obstacle.y) - obstacle.radius
    return np.array([signed_clearance(obstacle, p) for p in points])


def closest_approach(paths: Sequence[EpisodePath], geometry: SceneGeometry, *,
                     obstacles: Sequence[Obstacle] | None = None) -> ClosestApproach | None:
    """The closest approach over every episode (the first one found on a tie).

    Obstacle systems: the smallest signed clearance of the position (``geometry``'s position
    indices) to an obstacle's true shape (``obstacles``, default the geometry's discs at their
    true radius). Car following: the smallest |x_a - x_b| over the gaps.
    """
    best: ClosestApproach | None = None
    if geometry.gaps:
        for path in paths:
            for gap in geometry.gaps:
                distance = np.abs(path.states[:, gap.a] - path.states[:, gap.b])
                if distance.size and (best is None or distance.min() < best.distance):
                    step = int(np.argmin(distance))
                    best = ClosestApproach(float(distance[step]), path.episode, step, gap.name)
        return best
    shapes = _true_obstacles(geometry, obstacles)
    names = ([d.name for d in geometry.obstacles] if obstacles is None
             else [f'obstacle_{i}' for i in range(len(shapes))])
    i, j = geometry.position_indices
    for path in paths:
        points = path.states[:, [i, j]]
        for name, obstacle in zip(names, shapes):
            clearance = _clearances(points, obstacle)
            if clearance.size and (best is None or clearance.min() < best.distance):
                step = int(np.argmin(clearance))
                best = ClosestApproach(float(clearance[step]), path.episode, step, name)
    return best


def _episode_colours(paths: Sequence[EpisodePath]) -> tuple[list[Any], Any]:
    """One colour per path, and the colour map (None when the legend names each episode)."""
    import matplotlib
    if len(paths) <= MAX_LEGEND_EPISODES:  # tab10 without its red: red rings corrections
        palette = [f'C{k}' for k in (0, 1, 2, 4, 5, 6, 7, 8, 9)]
        return [palette[k % len(palette)] for k in range(len(paths))], None
    cmap = matplotlib.colormaps['viridis']
    first, last = paths[0].episode, paths[-1].episode
    span = max(last - first, 1)
    return [cmap((p.episode - first) / span) for p in paths], cmap


def _episode_range(paths: Sequence[EpisodePath]) -> str:
    if len(paths) == 1:
        return f'episode {paths[0].episode}'
    return f'episodes {paths[0].episode}-{paths[-1].episode}'


def _colour_bar(fig: Any, ax: Any, cmap: Any, paths: Sequence[EpisodePath]) -> None:
    import matplotlib
    norm = matplotlib.colors.Normalize(paths[0].episode, paths[-1].episode)
    bar = fig.colorbar(matplotlib.cm.ScalarMappable(norm=norm, cmap=cmap), ax=ax,
                       fraction=0.04, pad=0.02)
    bar.set_label('episode')


def _closest_text(closest: ClosestApproach, labels: Mapping[int, str]) -> str:
    return (f'closest: {closest.distance:.3f} m\n'
            f'({labels.get(closest.episode, f"episode {closest.episode}")})')


def _planar_picture(plt: Any, paths: Sequence[EpisodePath], geometry: SceneGeometry,
                    closest: ClosestApproach | None, *, obstacles: Sequence[Obstacle] | None,
                    goal: Sequence[float] | None, title: str, labels: Mapping[int, str]
                    ) -> Any:
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch
    vertical = geometry.system == 'pvtol'
    fig, ax = plt.subplots(figsize=(7.5, 5.2) if vertical else (7.0, 6.2), dpi=120)
    shapes = _true_obstacles(geometry, obstacles)
    for obstacle in shapes:
        vertices = obstacle.vertices()
        patch = (plt.Polygon(vertices, closed=True) if len(vertices)
                 else plt.Circle((obstacle.x, obstacle.y), obstacle.radius))
        patch.set(facecolor='0.55', edgecolor='0.3', alpha=0.8, zorder=1)
        ax.add_patch(patch)
    for disc in geometry.obstacles:
        ax.add_patch(plt.Circle((disc.x, disc.y), disc.radius + disc.margin, fill=False,
                                linestyle='--', edgecolor='0.25', linewidth=1.0, zorder=1))
    handles: list[Any] = []
    if shapes:
        handles.append(Patch(facecolor='0.55', edgecolor='0.3', label='obstacle (true size)'))
    if geometry.obstacles:
        handles.append(Line2D([], [], color='0.25', linestyle='--',
                              label='filter margin (radius + margin)'))
    arena = [geometry.band(name) for name in ('arena_x', 'arena_y')]
    if vertical and all(arena):
        (cx, wx), (cy, wy) = [(b.center, b.half_width) for b in arena]  # type: ignore
        ax.add_patch(plt.Rectangle((cx - wx, cy - wy), 2 * wx, 2 * wy, fill=False,
                                   linestyle=':', edgecolor='0.4', zorder=1))
        handles.append(Line2D([], [], color='0.4', linestyle=':', label='arena (filter)'))
    colours, cmap = _episode_colours(paths)
    i, j = geometry.position_indices
    for path, colour in zip(paths, colours):
        a, b = path.states[:, i], path.states[:, j]
        line, = ax.plot(a, b, color=colour, linewidth=1.3, zorder=3,
                        label=labels.get(path.episode, f'episode {path.episode}'))
        ax.plot(a[:1], b[:1], marker='o', color=colour, markersize=5, zorder=4)
        if cmap is None:
            handles.append(line)
        hits = path.corrected
        ax.scatter(a[hits], b[hits], s=9, facecolor='none', edgecolor='crimson',
                   linewidths=0.7, zorder=5)
    if any(p.corrected.any() for p in paths):
        handles.append(Line2D([], [], marker='o', linestyle='', markerfacecolor='none',
                              markeredgecolor='crimson', label='filter corrected (|u_S| > 1e-7)'))
    if goal is not None:
        ax.plot([goal[0]], [goal[1]], marker='*', markersize=14, color='gold',
                markeredgecolor='k', zorder=6, linestyle='')
        handles.append(Line2D([], [], marker='*', markersize=11, color='gold',
                              markeredgecolor='k', linestyle='', label='goal'))
    if closest is not None:
        path = next(p for p in paths if p.episode == closest.episode)
        point = path.states[closest.step, [i, j]]
        ax.plot([point[0]], [point[1]], marker='X', markersize=11, color='k', zorder=7,
                linestyle='')
        ax.annotate(_closest_text(closest, labels),
                    xy=point, xytext=(14, 14), textcoords='offset points', fontsize=9,
                    zorder=8, arrowprops={'arrowstyle': '-', 'color': 'k', 'lw': 0.8},
                    bbox={'boxstyle': 'round,pad=0.25', 'facecolor': 'white',
                          'edgecolor': '0.3', 'alpha': 0.9})
        handles.append(Line2D([], [], marker='X', markersize=9, color='k', linestyle='',
                              label=f'closest approach {closest.distance:.3f} m'))
    ax.set_aspect('equal', adjustable='datalim')
    ax.autoscale_view()
    ax.set_xlabel('x1 [m]' if vertical else 'x [m]')
    ax.set_ylabel('x2, height [m]' if vertical else 'y [m]')
    ax.grid(alpha=0.25)
    ax.set_title(title or f'{geometry.system}: {_episode_range(paths)}', fontsize=11)
    if cmap is not None:
        _colour_bar(fig, ax, cmap, paths)
    ax.legend(handles=handles, fontsize=8, loc='upper left', bbox_to_anchor=(1.02, 1.0),
              borderaxespad=0.0, framealpha=0.9)
    return fig


def _gap_picture(plt: Any, paths: Sequence[EpisodePath], geometry: SceneGeometry,
                 closest: ClosestApproach | None, *, dt: float | None,
                 true_gap: float | None, title: str, labels: Mapping[int, str]) -> Any:
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch
    fig, axes = plt.subplots(len(geometry.gaps), 1, figsize=(7.5, 2.6 * len(geometry.gaps) + 0.8),
                             dpi=120, sharex=True, squeeze=False)
    colours, cmap = _episode_colours(paths)
    scale = dt if dt else 1.0
    for ax, gap in zip(axes[:, 0], geometry.gaps):
        handles: list[Any] = []
        top = 0.0
        for path, colour in zip(paths, colours):
            t = np.arange(len(path.states)) * scale
            distance = np.abs(path.states[:, gap.a] - path.states[:, gap.b])
            top = max(top, float(distance.max(initial=0.0)))
            line, = ax.plot(t, distance, color=colour, linewidth=1.3,
                            label=labels.get(path.episode, f'episode {path.episode}'))
            if cmap is None:
                handles.append(line)
            hits = path.corrected
            ax.scatter(t[hits], distance[hits], s=9, facecolor='none', edgecolor='crimson',
                       linewidths=0.7, zorder=5)
        if true_gap is not None:
            ax.axhspan(0.0, true_gap, color='0.55', alpha=0.5, zorder=0)
            handles.append(Patch(color='0.55', alpha=0.5, label=f'collision (< {true_gap} m)'))
        ax.axhline(gap.delta, color='0.25', linestyle='--', linewidth=1.0)
        handles.append(Line2D([], [], color='0.25', linestyle='--',
                              label=f'filter keeps {gap.delta} m'))
        if any(p.corrected.any() for p in paths):
            handles.append(Line2D([], [], marker='o', linestyle='', markerfacecolor='none',
                                  markeredgecolor='crimson',
                                  label='filter corrected (|u_S| > 1e-7)'))
        if closest is not None and closest.barrier == gap.name:
            ax.plot([closest.step * scale], [closest.distance], marker='X', markersize=11,
                    color='k', linestyle='', zorder=7)
            ax.annotate(_closest_text(closest, labels),
                        xy=(closest.step * scale, closest.distance), xytext=(14, 14),
                        textcoords='offset points', fontsize=9, zorder=8,
                        arrowprops={'arrowstyle': '-', 'color': 'k', 'lw': 0.8},
                        bbox={'boxstyle': 'round,pad=0.25', 'facecolor': 'white',
                              'edgecolor': '0.3', 'alpha': 0.9})
        ax.set_ylim(0.0, max(top, gap.delta) * 1.1 + 0.5)
        if geometry.system == 'car_following':  # state [p1, v1, ..., p5, v5]
            ax.set_ylabel(f'car {gap.a // 2 + 1} to car {gap.b // 2 + 1} [m]')
        else:
            ax.set_ylabel(f'|x[{gap.a}] - x[{gap.b}]| [m]')
        ax.set_title(f'gap barrier {gap.name}', fontsize=9)
        ax.grid(alpha=0.25)
        ax.legend(handles=handles, fontsize=8, loc='upper left', bbox_to_anchor=(1.02, 1.0),
                  borderaxespad=0.0)
        if cmap is not None:
            _colour_bar(fig, ax, cmap, paths)
    axes[-1, 0].set_xlabel('time [s]' if dt else 'step')
    fig.suptitle(title or f'{geometry.system}: {_episode_range(paths)}', fontsize=11)
    return fig


def plot_trajectories(paths: Sequence[EpisodePath], geometry: SceneGeometry,
                      path: str | Path, *, title: str = '',
                      obstacles: Sequence[Obstacle] | None = None,
                      goal: Sequence[float] | None = None, dt: float | None = None,
                      true_gap: float | None = None,
                      labels: Mapping[int, str] | None = None) -> TrajectoryPicture:
    """The robot's paths over the scene as a PNG: one line per episode (coloured by episode),
    the steps where the filter corrected the command ringed, the closest approach labelled.

    Unicycle and other planar systems: the paths in the plane over the obstacles (true size
    filled, the filter's radius + margin dashed), equal axis scales. PVTOL: the same in the
    x1-x2 (horizontal-height) plane, with the filter's arena. Car following: each gap over
    time, the collision distance ``true_gap`` filled and the filter's distance dashed.

    Args:
        paths: the episodes, in order.
        geometry: the filter's geometry (:func:`rcbf_ros.core.scene.scene_geometry`).
        path: the PNG to write.
        obstacles: the obstacles' true shapes where they are not the geometry's discs (random
            transfer layouts: squares and triangles).
        goal: the goal's position, drawn as a star.
        dt: seconds per step (car following: time axis; None: steps).
        true_gap: car following: the distance that is a collision.
        labels: legend text per episode number, where a path is not an episode of one run
            (e.g. one method each); default ``episode <n>``.

    Raises:
        ValueError: no episode, or a state narrower than the geometry's n_x.
    """
    if not paths:
        raise ValueError('trajectories: no episode to draw')
    narrow = [p.episode for p in paths if p.states.shape[1] < geometry.n_x]
    if narrow:
        raise ValueError(f'trajectories: episode {narrow[0]} has states of '
                         f'{paths[0].states.shape[1]} values, the filter {geometry.n_x}')
    plt = _pyplot()
    closest = closest_approach(paths, geometry, obstacles=obstacles)
    labels = dict(labels or {})
    if geometry.gaps:
        fig = _gap_picture(plt, paths, geometry, closest, dt=dt, true_gap=true_gap,
                           title=title, labels=labels)
    else:
        fig = _planar_picture(plt, paths, geometry, closest, obstacles=obstacles, goal=goal,
                              title=title, labels=labels)
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path)
    plt.close(fig)
    return TrajectoryPicture(path, closest)
