"""Plots (matplotlib, headless): reward curves and mean +/- 2 std bands over seeds."""
from __future__ import annotations

from pathlib import Path
from typing import Mapping, Sequence

import numpy as np


def _pyplot():
    import matplotlib
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
