"""CSV + PNG + markdown of each experiment, from the run directories (no training here).

Files written into the report directory (``<out>/<budget>/report``):

- sample_efficiency: ``sample_efficiency_<system>.csv`` (method, seed, episode, return,
  violations, goal), ``sample_efficiency_<system>_band.csv`` (mean and 2-std band per episode),
  ``sample_efficiency_<system>.png``, ``sample_efficiency.md``; where the runs logged them,
  ``sample_efficiency_<system>_critic.csv|png`` (critic at each episode's first step vs the
  discounted return, per seed);
- transfer: ``transfer_<system>_episodes.csv`` (one row per policy x layout),
  ``transfer_<system>.csv`` (mean/std reward, completion per method, ours and the paper's),
  ``transfer_<system>_completion.png`` (bar chart), ``transfer_<system>_endings.csv|png``
  (how the episodes ended per method: goal, held, stalled, moving), ``transfer.md``;
  plus the training curves of the transfer runs as ``transfer_training_<system>.*``, and
  ``transfer_<system>_paths_layout<k>.png`` (every method's path on the first layouts, from a
  re-run of its deterministic episode) with ``transfer_paths.md``;
- value_maps: ``value_maps_unicycle.csv`` (method, x, y, V), ``value_maps_unicycle.png``,
  ``value_maps.md``;
- ``report.md``: the markdown of every experiment present.
"""
from __future__ import annotations

import csv
from pathlib import Path
from typing import Any, Iterable, Sequence

import numpy as np

from rcbf_ros.experiments.definitions import METHODS, RunSpec
from rcbf_ros.experiments.metrics import (
    completion_rate,
    count_violations,
    ENDINGS,
    final_window_mean,
    mean_std,
    reward_band,
)
from rcbf_ros.experiments.runner import metrics_rows

PAPER_TRANSFER: dict[str, dict[str, tuple[float, float, float]]] = {
    'unicycle': {'sac_no_obstacles': (7.009, 1.745, 0.81), 'baseline': (3.533, 2.685, 0.21),
                 'sac_rcbf': (3.223, 2.413, 0.17), 'modular': (6.189, 2.317, 0.63)},
    'pvtol': {'sac_no_obstacles': (11.969, 2.376, 0.87), 'baseline': (7.228, 4.622, 0.34),
              'sac_rcbf': (9.450, 3.808, 0.52), 'modular': (10.656, 3.411, 0.69)},
}
"""The paper's transfer tables: (mean episode reward, std, completion rate) over 200 layouts."""

REPORT_PARTS = ('sample_efficiency', 'transfer', 'transfer_paths', 'transfer_training',
                'value_maps')
"""Markdown parts of ``report.md``, in order."""


def write_csv(path: Path, header: Sequence[str], rows: Iterable[Sequence[Any]]) -> Path:
    """A CSV with a header row."""
    with Path(path).open('w', newline='') as stream:
        writer = csv.writer(stream)
        writer.writerow(header)
        writer.writerows(rows)
    return Path(path)


def _by_system(specs: Sequence[RunSpec]) -> dict[str, dict[str, list[RunSpec]]]:
    """system -> method -> runs, methods in the order of :data:`METHODS` (the tables')."""
    out: dict[str, dict[str, list[RunSpec]]] = {}
    order = list(METHODS)
    for spec in sorted(specs, key=lambda s: (order.index(s.method), s.seed)):
        out.setdefault(spec.system, {}).setdefault(spec.method, []).append(spec)
    return out


def _finite(value: Any) -> bool:
    return isinstance(value, (int, float)) and bool(np.isfinite(value))


def _fmt(value: float, digits: int = 3) -> str:
    return f'{value:.{digits}f}'


# --------------------------------------------------------------------------- sample efficiency
def sample_efficiency_report(specs: Sequence[RunSpec], root: str | Path,
                             report_dir: Path, *, prefix: str = 'sample_efficiency',
                             heading: str = 'Sample efficiency') -> str:
    """Curves, bands and the summary table of training runs; returns markdown.

    ``prefix`` names the files (``<prefix>_<system>.csv|png``, ``<prefix>.md``): the
    sample-efficiency experiment, or the training curves of the transfer runs.
    """
    from rcbf_ros.reports.plots import plot_critic_vs_return, plot_reward_bands
    lines = [f'## {heading}', '',
             'Episode return per training episode, mean over seeds with a 2-std band. '
             '"final" is the mean of the last 10 episodes of each seed (mean +/- std over '
             'seeds); violations are steps with a true clearance < 0, summed over all '
             'training episodes of all seeds.', '']
    for system, methods in _by_system(specs).items():
        rows, band_rows, table, critic_rows = [], [], [], []
        curves: dict[str, list[list[float]]] = {}
        critic: dict[str, dict[int, tuple[list[float], list[float]]]] = {}
        for method, runs in methods.items():
            label = METHODS[method].label
            per_seed, violations, goals, wall = [], 0, 0, 0.0
            for spec in runs:
                history = metrics_rows(spec.run_dir(root))
                if not history:
                    continue
                per_seed.append([float(r['ret']) for r in history])
                violations += count_violations(history)
                goals += sum(bool(r['goal_reached']) for r in history)
                wall += sum(float(r['wall_s']) for r in history)
                rows += [(method, spec.seed, r['episode'] + 1, r['ret'], r['violations'],
                          int(bool(r['goal_reached']))) for r in history]
                values = [r for r in history if _finite(r.get('q_start'))
                          and _finite(r.get('disc_return'))]
                if values:  # runs from before these metrics existed have none
                    critic.setdefault(label, {})[spec.seed] = (
                        [float(r['q_start']) for r in values],
                        [float(r['disc_return']) for r in values])
                    critic_rows += [(method, spec.seed, r['episode'] + 1, r['q_start'],
                                     r['disc_return']) for r in values]
            if not per_seed:
                continue
            curves[label] = per_seed
            band = reward_band(per_seed)
            band_rows += [(method, int(e), m, lo, hi, band.n_runs)
                          for e, m, lo, hi in zip(band.episode, band.mean, band.lower,
                                                  band.upper)]
            final_mean, final_std = mean_std(final_window_mean(c) for c in per_seed)
            table.append(f'| {label} | {len(per_seed)} | {min(len(c) for c in per_seed)} | '
                         f'{_fmt(final_mean)} +/- {_fmt(final_std)} | {goals} | {violations} '
                         f'| {wall:.0f} |')
        if not curves:
            continue
        write_csv(report_dir / f'{prefix}_{system}.csv',
                  ('method', 'seed', 'episode', 'return', 'violations', 'goal_reached'), rows)
        write_csv(report_dir / f'{prefix}_{system}_band.csv',
                  ('method', 'episode', 'mean', 'lower_2std', 'upper_2std', 'n_runs'),
                  band_rows)
        plot_reward_bands(curves, report_dir / f'{prefix}_{system}.png',
                          title=f'{system}: return vs training episode (mean, 2 std)')
        lines += [f'### {system}', '', f'![{system}]({prefix}_{system}.png)', '']
        if critic:
            write_csv(report_dir / f'{prefix}_{system}_critic.csv',
                      ('method', 'seed', 'episode', 'q_start', 'disc_return'), critic_rows)
            plot_critic_vs_return(critic, report_dir / f'{prefix}_{system}_critic.png',
                                  title=f'{system}: critic at the first step vs return')
            lines += [f'![{system} critic]({prefix}_{system}_critic.png)', '',
                      "The critics' value of each episode's first step against the "
                      'discounted return that followed (soft values also count the entropy '
                      'bonus): a solid line far above its dashed one is over-estimation.', '']
        lines += [
                  '| Method | seeds | episodes | final return | goals reached (train) | '
                  'safety violations | train wall [s] |',
                  '|---|---|---|---|---|---|---|', *table, '']
    text = '\n'.join(lines)
    (report_dir / f'{prefix}.md').write_text(text)
    return text


# --------------------------------------------------------------------------- transfer
def _plot_endings(ending_rows: Sequence[tuple[Any, ...]], path: Path, title: str) -> None:
    """Horizontal stacked bars: per method, the share of episodes of each ending."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    height = 0.6 * len(ending_rows) + 1.8
    fig, ax = plt.subplots(figsize=(6.5, height), dpi=100)
    left = np.zeros(len(ending_rows))
    positions = np.arange(len(ending_rows))
    for k, ending in enumerate(ENDINGS):
        share = np.array([row[3 + k] / row[2] for row in ending_rows])
        ax.barh(positions, share, left=left, label=ending)
        left += share
    ax.set_yticks(positions, [row[1] for row in ending_rows], fontsize=8)
    ax.invert_yaxis()
    ax.set_xlim(0, 1)
    ax.set_xlabel('share of episodes')
    ax.set_title(title)
    fig.legend(*ax.get_legend_handles_labels(), ncol=len(ENDINGS), fontsize=8,
               loc='lower center')
    fig.tight_layout(rect=(0.0, 0.35 / height, 1.0, 1.0))  # the legend's strip at the bottom
    fig.savefig(path)
    plt.close(fig)


def transfer_report(results: dict[RunSpec, list[dict[str, Any]]], report_dir: Path, *,
                    layouts: int, eval_max_steps: dict[str, int | None]) -> str:
    """Transfer tables (ours next to the paper's), per-episode CSV and completion bars."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    lines = ['## Zero-shot transfer', '',
             f"Deterministic policy, per-step RCBF filter with the NEW layout's barriers and "
             f"the run's trained GP, on random layouts 0..{layouts - 1} (seeded, "
             'rcbf_ros.envs.layouts). Mean/std of the episode reward pooled over seeds x '
             'layouts (population std); completion = goal reached before the time limit.', '']
    for system, methods in _by_system(list(results)).items():
        episode_rows, summary_rows, table, bars, ending_rows = [], [], [], [], []
        for method, runs in methods.items():
            rows = [dict(r, seed=spec.seed) for spec in runs for r in results[spec]]
            if not rows:
                continue
            mean, std = mean_std(r['ret'] for r in rows)
            completion = completion_rate(r['goal_reached'] for r in rows)
            violations = count_violations(rows)
            fail_safe = sum(int(r['fail_safe']) for r in rows)
            paper = PAPER_TRANSFER.get(system, {}).get(method)
            episode_rows += [(method, r['seed'], r['layout_seed'], r['ret'], r['steps'],
                              int(bool(r['goal_reached'])), r['violations'], r['fail_safe'],
                              r['ending'], r.get('goal_dist', ''))
                             for r in rows]
            counts = [sum(r['ending'] == e for r in rows) for e in ENDINGS]
            ending_rows.append((method, METHODS[method].label, len(rows), *counts))
            summary_rows.append((method, METHODS[method].label, mean, std, completion,
                                 len(runs), len(rows), violations,
                                 *(paper if paper else ('', '', ''))))
            paper_cells = ' | '.join(_fmt(v, 3 if i < 2 else 2) for i, v in enumerate(paper)) \
                if paper else '- | - | -'
            table.append(f'| {METHODS[method].label} | {paper_cells} | {_fmt(mean)} | '
                         f'{_fmt(std)} | {completion:.2f} | {len(runs)} | {violations} | '
                         f'{fail_safe} |')
            bars.append((METHODS[method].label, completion, paper[2] if paper else None))
        if not summary_rows:
            continue
        write_csv(report_dir / f'transfer_{system}_episodes.csv',
                  ('method', 'seed', 'layout_seed', 'return', 'steps', 'goal_reached',
                   'violations', 'fail_safe_steps', 'ending', 'goal_dist'), episode_rows)
        write_csv(report_dir / f'transfer_{system}_endings.csv',
                  ('method', 'label', 'episodes', *ENDINGS), ending_rows)
        _plot_endings(ending_rows, report_dir / f'transfer_{system}_endings.png',
                      f'{system}: how the transfer episodes ended')
        write_csv(report_dir / f'transfer_{system}.csv',
                  ('method', 'label', 'mean_reward', 'std_reward', 'completion', 'seeds',
                   'episodes', 'violations', 'paper_mean_reward', 'paper_std_reward',
                   'paper_completion'), summary_rows)
        fig, ax = plt.subplots(figsize=(6.5, 3.6), dpi=100)
        positions = np.arange(len(bars))
        ax.bar(positions - 0.2, [b[1] for b in bars], 0.4, label='ours')
        ax.bar(positions + 0.2, [b[2] if b[2] is not None else 0.0 for b in bars], 0.4,
               label='paper', alpha=0.6)
        ax.set_xticks(positions, [b[0] for b in bars], rotation=15, fontsize=8)
        ax.set_ylim(0, 1)
        ax.set_ylabel('completion rate')
        ax.set_title(f'{system}: zero-shot transfer completion')
        ax.legend()
        fig.tight_layout()
        fig.savefig(report_dir / f'transfer_{system}_completion.png')
        plt.close(fig)
        steps = eval_max_steps.get(system)
        lines += [f'### {system} (episode limit: {steps or "env default"} steps)', '',
                  f'![{system}](transfer_{system}_completion.png)', '',
                  '| Approach | paper mean | paper std | paper comp. | ours mean | ours std | '
                  'ours comp. | seeds | violations | fail-safe steps |',
                  '|---|---|---|---|---|---|---|---|---|---|', *table, '',
                  'How the episodes ended (rcbf_ros.experiments.metrics: the last 200 steps; '
                  'held = standing still with the filter correcting, stalled = standing still '
                  'with the filter idle, moving = not standing still at the time limit):', '',
                  f'![{system} endings](transfer_{system}_endings.png)', '',
                  '| Approach | episodes | ' + ' | '.join(ENDINGS) + ' |',
                  '|---|---|' + '---|' * len(ENDINGS),
                  *(f'| {r[1]} | {r[2]} | ' + ' | '.join(str(c) for c in r[3:]) + ' |'
                    for r in ending_rows), '']
    text = '\n'.join(lines)
    (report_dir / 'transfer.md').write_text(text)
    return text


# --------------------------------------------------------------------------- transfer paths
PATH_LAYOUTS = 3
"""Transfer layouts (seeds 0, 1, ...) drawn with every method's path."""


def transfer_paths_report(specs: Sequence[RunSpec], root: str | Path, report_dir: Path, *,
                          layouts: int, eval_max_steps: dict[str, int | None],
                          gp: str = 'learned') -> str:
    """Every method's path (its first seed's deterministic policy, re-run exactly as the
    transfer evaluation runs it) on the first :data:`PATH_LAYOUTS` transfer layouts, one
    picture per layout (:func:`rcbf_ros.reports.plots.plot_trajectories`); returns markdown."""
    from rcbf_ros.core.scene import scene_geometry
    from rcbf_ros.envs import make_env
    from rcbf_ros.experiments.evaluate import evaluate_layout, load_trained_learner
    from rcbf_ros.parameters.rules import find_config, load_params
    from rcbf_ros.reports.plots import plot_trajectories
    from rcbf_ros.training.pictures import episode_path
    lines = ['## Transfer paths', '',
             "Each method's deterministic policy (its first seed) on the first transfer "
             "layouts, with the filter of that layout, as in the table above: the true "
             'obstacles filled, the radius + margin the filter keeps dashed, the steps where '
             'the filter corrected the command ringed.', '']
    for system, methods in _by_system(specs).items():
        learners = {method: load_trained_learner(runs[0].run_dir(root))
                    for method, runs in methods.items()}
        config = find_config(next(iter(learners.values()))[0].config_file or system)
        for seed in range(min(layouts, PATH_LAYOUTS)):
            paths, labels = [], {}
            for number, (method, (run, learner)) in enumerate(learners.items(), 1):
                trace: list[tuple[np.ndarray, bool]] = []
                evaluate_layout(learner, system, seed, max_steps=eval_max_steps.get(system),
                                gp=gp, config_file=run.config_file,  # type: ignore[arg-type]
                                trace=trace)
                paths.append(episode_path(number, trace))
                labels[number] = METHODS[method].label
            params = load_params(config, 'simulator')
            params.update({'layout': 'random', 'layout_seed': seed})
            env = make_env(system, params)
            env.reset(seed=seed)
            geometry = scene_geometry(env.filter_params(load_params(config, 'safety_filter')))
            name = f'transfer_{system}_paths_layout{seed}.png'
            picture = plot_trajectories(
                paths, geometry, report_dir / name, obstacles=getattr(env, 'obstacles', None),
                goal=getattr(env, 'goal', None), labels=labels,
                title=f'{system}: transfer layout {seed}')
            closest = picture.closest
            lines += [f'![{system} layout {seed}]({name})', '']
            if closest is not None:
                lines += [f'Closest approach on layout {seed}: {closest.distance:.3f} m '
                          f'({labels[closest.episode]}).', '']
    text = '\n'.join(lines)
    (report_dir / 'transfer_paths.md').write_text(text)
    return text


# --------------------------------------------------------------------------- value maps
def value_maps_report(maps: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]],
                      report_dir: Path, *, seed: int) -> str:
    """CSV and figure of the Unicycle value maps (keys: method)."""
    from rcbf_ros.experiments.value_map import map_contrast, plot_value_maps
    from rcbf_ros.parameters.rules import find_config, load_params
    rows = []
    for method, (xs, ys, values) in maps.items():
        for iy, y in enumerate(ys):
            for ix, x in enumerate(xs):
                rows.append((method, float(x), float(y), float(values[iy, ix])))
    write_csv(report_dir / 'value_maps_unicycle.csv', ('method', 'x', 'y', 'value'), rows)
    params = load_params(find_config('unicycle'), 'simulator')
    obstacles = list(zip(params['obstacles.x'], params['obstacles.y'],
                         params['obstacles.radius']))
    from rcbf_ros.envs.layouts import UNICYCLE_STARTS
    plot_value_maps({METHODS[m].label: v for m, v in maps.items()},
                    report_dir / 'value_maps_unicycle.png', obstacles=obstacles,
                    starts=UNICYCLE_STARTS, goal=params.get('goal', (2.5, 2.5)),
                    goal_radius=float(params.get('goal_radius', 0.3)))
    contrast = map_contrast(maps, obstacles)
    table = [f'| {METHODS[m].label} | {c["corr_reference"]:.3f} | {c["ring_z"]:.3f} |'
             for m, c in contrast.items()]
    text = '\n'.join([
        '## Value maps (Unicycle)', '',
        f'V(x, y) = max over 8 headings of min(Q1, Q2)(o(x, y, theta), mean action), seed {seed}; '
        'training obstacles in red, starts blue, goal green.', '',
        '![value maps](value_maps_unicycle.png)', '',
        'Outside the obstacles: correlation of each map with the map of SAC without obstacles, '
        'and the mean standardised value within 0.4 m of an obstacle edge (negative: the '
        'critic is low next to the training obstacles). `map_contrast` in '
        'rcbf_ros/experiments/value_map.py.', '',
        '| Method | correlation with the upper bound | standardised value near obstacles |',
        '|---|---|---|', *table, ''])
    (report_dir / 'value_maps.md').write_text(text)
    return text


def write_report_md(report_dir: Path, header: str) -> Path:
    """``report.md``: the header, then every experiment's markdown present in the directory."""
    parts = [header]
    for name in REPORT_PARTS:
        path = report_dir / f'{name}.md'
        if path.exists():
            parts.append(path.read_text())
    out = report_dir / 'report.md'
    out.write_text('\n'.join(parts) + '\n')
    return out
