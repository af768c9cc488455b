"""What each experiment runs: methods per system, budgets, and the run specifications.

=================  ==============  ============================================================
experiment         systems         methods (training mode)
=================  ==============  ============================================================
sample_efficiency  unicycle        baseline, baseline_compensator, sac_rcbf (MF: ``diff``),
                                   sac_rcbf_mb (MB: ``diff`` + model rollouts)
                   car_following   baseline, baseline_compensator, sac_rcbf (no MB: Car
                                   Following has no state-only observation model, see
                                   SafetyEnv.torch_models)
transfer           unicycle, pvtol sac_no_obstacles (``unconstrained``, trained without obstacles,
                                   PVTOL also without its operator: the upper bound; only
                                   PVTOL's tilt/thrust/arena envelope is filtered), baseline,
                                   sac_rcbf, modular
value_maps         unicycle        sac_no_obstacles, sac_rcbf, modular (the transfer runs)
=================  ==============  ============================================================

A run is identified by (budget, system, method, seed) only, so experiments that need the same
training run (transfer and value_maps on the Unicycle) share it; the runner trains it once.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Sequence

from rcbf_ros.learning.sac import SACConfig
from rcbf_ros.training.build import RunConfig
from rcbf_ros.training.settings import SETTING_NAMES, TrainingSettings

EXPERIMENTS: tuple[str, ...] = ('sample_efficiency', 'transfer', 'value_maps')
"""Experiment names (``all`` runs every one)."""


@dataclass(frozen=True)
class Method:
    """One compared approach: a training mode plus flags."""

    label: str
    """Name in tables and legends (the paper's wording)."""
    mode: str
    """Training mode (rcbf_ros.training.agent.MODES)."""
    model_based: bool = False
    """MB SAC-RCBF (synthetic rollouts)."""
    no_obstacles: bool = False
    """Train without the layout (transfer upper bound; see RunConfig.no_obstacles)."""
    envelope: bool = False
    """Modular only: keep the layout-independent constraints (PVTOL's tilt/thrust/arena
    envelope) in the losses (LearnerConfig.modular_envelope)."""


METHODS: dict[str, Method] = {
    'sac_no_obstacles': Method('SAC w/o obstacles (upper bound)', 'unconstrained',
                               no_obstacles=True),
    'baseline': Method('Baseline', 'baseline'),
    'baseline_compensator': Method('Baseline + compensator', 'baseline_compensator'),
    'sac_rcbf': Method('SAC-RCBF (MF)', 'diff'),
    'sac_rcbf_mb': Method('SAC-RCBF (MB)', 'diff', model_based=True),
    'modular': Method('Mod. SAC-RCBF', 'modular'),
    'modular_envelope': Method('Mod. SAC-RCBF, envelope kept', 'modular', envelope=True),
}
"""Every method by key (keys name run directories)."""

PLAN: dict[str, dict[str, tuple[str, ...]]] = {
    'sample_efficiency': {
        'unicycle': ('baseline', 'baseline_compensator', 'sac_rcbf', 'sac_rcbf_mb'),
        'car_following': ('baseline', 'baseline_compensator', 'sac_rcbf'),
    },
    'transfer': {
        'unicycle': ('sac_no_obstacles', 'baseline', 'sac_rcbf', 'modular'),
        'pvtol': ('sac_no_obstacles', 'baseline', 'sac_rcbf', 'modular'),
    },
    'value_maps': {
        'unicycle': ('sac_no_obstacles', 'sac_rcbf', 'modular'),
    },
}
"""experiment -> system -> method keys."""

OPTIONAL: dict[str, dict[str, tuple[str, ...]]] = {
    'transfer': {'pvtol': ('modular_envelope',)},
}
"""experiment -> system -> method keys that run only when named (``--methods``): variants
that are not in the paper's tables. On the Unicycle the envelope is empty, so
``modular_envelope`` would equal ``modular``; it is offered for PVTOL only."""


@dataclass(frozen=True)
class Budget:
    """How much compute one experiment spends (per run and per evaluation)."""

    name: str
    """Budget name; names the output sub-directory."""
    episodes: dict[str, int]
    """Training episodes per system."""
    max_steps: dict[str, int | None] = field(default_factory=dict)
    """Episode length per system (None or absent: the env's default)."""
    eval_max_steps: dict[str, int | None] = field(default_factory=dict)
    """Episode length of transfer evaluation per system (None: the env's default)."""
    random_start: dict[str, bool] = field(default_factory=dict)
    """Random episode starts in training, per system (absent: the config file's setting). The
    Unicycle trains from its corner and edge starts, as the paper's value-map figure shows."""
    layouts: int = 200
    """Random transfer layouts (seeds 0 .. layouts - 1) each policy is evaluated on."""
    start_steps: int | None = None
    """LearnerConfig.start_steps (None: its default)."""
    update_after: int | None = None
    """LearnerConfig.update_after (None: its default)."""
    batch_size: int | None = None
    """LearnerConfig.batch_size (None: its default)."""
    gp_refit_interval: int | None = None
    """LearnerConfig.gp_refit_interval (None: its default)."""
    rollout_interval: int | None = None
    """LearnerConfig.rollout_interval (None: its default)."""
    rollouts: int | None = None
    """LearnerConfig.rollouts (None: its default)."""
    rollout_horizon: int | None = None
    """LearnerConfig.rollout_horizon (None: its default)."""
    hidden_sizes: tuple[int, ...] | None = None
    """SAC hidden widths (None: SACConfig's default, 256 x 256)."""
    value_map_grid: int = 61
    """Grid points per axis of the value maps."""
    record_bag: bool = True
    """Record every training run to MCAP (as ``rcbf_ros train``)."""
    policy_box: str = 'config'
    """Where the policy's proposals are drawn from: ``config``, the config file's
    ``/learner`` ``policy_limits`` (the Unicycle's: forward speeds only); ``inputs``, the input
    limits (the reference's box, reversing allowed)."""

    def __post_init__(self) -> None:
        for system, count in self.episodes.items():
            if count < 1:
                raise ValueError(f'episodes: {system} needs >= 1 episode, got {count}')
        for name in ('max_steps', 'eval_max_steps'):
            for system, steps in getattr(self, name).items():
                if steps is not None and steps < 1:
                    raise ValueError(f'{name}: {system} needs >= 1 step, got {steps}')
        if self.layouts < 1:
            raise ValueError(f'layouts: must be >= 1, got {self.layouts}')
        if self.value_map_grid < 2:
            raise ValueError(f'value_map_grid: must be >= 2, got {self.value_map_grid}')
        if self.policy_box not in POLICY_BOXES:
            raise ValueError(f'policy_box: expected one of {POLICY_BOXES}, got '
                             f'{self.policy_box!r}')

    def learner_overrides(self) -> dict[str, Any]:
        """The LearnerConfig fields this budget sets."""
        names = ('start_steps', 'update_after', 'batch_size', 'gp_refit_interval',
                 'rollout_interval', 'rollouts', 'rollout_horizon')
        out: dict[str, Any] = {n: getattr(self, n) for n in names if getattr(self, n) is not None}
        if self.hidden_sizes is not None:
            out['sac'] = SACConfig(hidden_sizes=tuple(self.hidden_sizes))
        if self.policy_box == 'inputs':  # () is the input limits; None defers to the file
            out.update(policy_min=(), policy_max=())
        return out

    def with_overrides(self, *, episodes: int | None = None, max_steps: int | None = None,
                       eval_max_steps: int | None = None, layouts: int | None = None,
                       record_bag: bool | None = None, policy_box: str | None = None
                       ) -> Budget:
        """The same budget with command-line overrides applied to every system.

        Overrides that change training (episodes, episode length, policy box) are appended to
        the name (``paper-e12-s500``, ``...-box_inputs``), so that runs of different schedules
        never share a directory and the runner never mistakes one for the other as complete.
        """
        changes: dict[str, Any] = {}
        suffix = ''
        if episodes is not None:
            changes['episodes'] = {s: episodes for s in self.episodes}
            suffix += f'-e{episodes}'
        if max_steps is not None:
            changes['max_steps'] = {s: max_steps for s in self.episodes}
            suffix += f'-s{max_steps}'
        if eval_max_steps is not None:
            changes['eval_max_steps'] = {s: eval_max_steps for s in self.episodes}
        if layouts is not None:
            changes['layouts'] = layouts
        if record_bag is not None:
            changes['record_bag'] = record_bag
        if policy_box is not None and policy_box != self.policy_box:
            changes['policy_box'] = policy_box
            suffix += f'-box_{policy_box}'
        if suffix:
            changes['name'] = self.name + suffix
        return replace(self, **changes)


_SYSTEMS = ('unicycle', 'car_following', 'pvtol')
POLICY_BOXES = ('config', 'inputs')
"""Values of Budget.policy_box (``--policy-box``)."""

BUDGETS: dict[str, Budget] = {
    # Minutes on one core: proves the pipeline end to end, says nothing about learning.
    'smoke': Budget(
        name='smoke', episodes={s: 2 for s in _SYSTEMS},
        max_steps={s: 40 for s in _SYSTEMS}, eval_max_steps={s: 40 for s in _SYSTEMS},
        layouts=3, start_steps=20, update_after=20, batch_size=16, gp_refit_interval=30,
        rollout_interval=20, rollouts=8, rollout_horizon=2, hidden_sizes=(16, 16),
        value_map_grid=9, record_bag=True, random_start={'unicycle': True}),
    # The paper's scale: full-length episodes (ref lengths), 200 layouts, LearnerConfig's
    # defaults (256 x 256 networks, batch 256). Episode counts are ours (the paper shows its
    # curves over episodes without stating the count in the text).
    'paper': Budget(
        name='paper', episodes={'unicycle': 200, 'car_following': 200, 'pvtol': 200},
        layouts=200, random_start={'unicycle': True}),
}
"""Named budgets (``--budget``)."""


@dataclass(frozen=True)
class RunSpec:
    """One training run of an experiment: (budget, system, method, seed)."""

    system: str
    """unicycle | car_following | pvtol."""
    method: str
    """Key of :data:`METHODS`."""
    seed: int
    """Learner seed (networks, exploration, GP subsample, episode starts)."""
    budget: Budget = field(compare=False)
    """The budget it trains under (not part of equality/hash: specs of one call share it)."""

    @property
    def episodes(self) -> int:
        """Training episodes."""
        return self.budget.episodes[self.system]

    def run_dir(self, root: str | Path) -> Path:
        """``<root>/<budget>/<system>/<method>/seed<k>``."""
        return Path(root) / self.budget.name / self.system / self.method / f'seed{self.seed}'

    def run_config(self, root: str | Path, *, resume: bool = False) -> RunConfig:
        """The trainer's RunConfig of this run."""
        method = METHODS[self.method]
        learner = self.budget.learner_overrides()
        schedule = {name: learner.pop(name) for name in list(learner) if name in SETTING_NAMES}
        settings = TrainingSettings(
            system=self.system, mode=method.mode, model_based=method.model_based,
            seed=self.seed, modular_envelope=method.envelope, episodes=self.episodes,
            out_dir=str(self.run_dir(root)), max_steps=self.budget.max_steps.get(self.system),
            no_obstacles=method.no_obstacles, record_bag=self.budget.record_bag,
            random_start=self.budget.random_start.get(self.system), resume=resume,
            **schedule)
        return settings.run_config(**learner)


def experiment_names(name: str) -> tuple[str, ...]:
    """``all`` -> every experiment; otherwise the one name.

    Raises:
        ValueError: naming ``experiment`` when unknown.
    """
    if name == 'all':
        return EXPERIMENTS
    if name not in EXPERIMENTS:
        raise ValueError(f"experiment: expected one of {EXPERIMENTS + ('all',)}, got {name!r}")
    return (name,)


def experiment_methods(experiment: str, system: str,
                       optional: Sequence[str] = ()) -> tuple[str, ...]:
    """The method keys ``experiment`` runs on ``system``: its PLAN entry, then those of
    :data:`OPTIONAL` named in ``optional``."""
    extra = OPTIONAL.get(experiment, {}).get(system, ())
    return PLAN[experiment].get(system, ()) + tuple(m for m in extra if m in optional)


def experiment_runs(name: str, budget: Budget, seeds: int,
                    optional: Sequence[str] = ()) -> list[RunSpec]:
    """Every training run of experiment ``name`` (or ``all``), seeds 0 .. seeds - 1, without
    duplicates (order: experiment, system, method, seed). ``optional`` names the
    :data:`OPTIONAL` methods to add.

    Raises:
        ValueError: unknown experiment, ``seeds`` < 1, or a system the budget does not cover.
    """
    if seeds < 1:
        raise ValueError(f'seeds: must be >= 1, got {seeds}')
    specs: list[RunSpec] = []
    seen: set[tuple[str, str, int]] = set()
    for experiment in experiment_names(name):
        for system in PLAN[experiment]:
            if system not in budget.episodes:
                raise ValueError(f'episodes: budget {budget.name!r} has no entry for {system}')
            for method in experiment_methods(experiment, system, optional):
                for seed in range(seeds):
                    key = (system, method, seed)
                    if key not in seen:
                        seen.add(key)
                        specs.append(RunSpec(system, method, seed, budget))
    return specs
