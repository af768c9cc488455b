"""One training run's settings as its user gives them, each default written once.

:class:`TrainingSettings` is what ``rcbf_ros train`` builds its options from, what the learner
node declares its parameters from (with the four defaults of its own in
:data:`rcbf_ros.ros.learner_node.NODE_DEFAULTS`) and what the experiments set per run. It
becomes the trainer's :class:`~rcbf_ros.training.build.RunConfig` (:meth:`run_config`) and
the learner's :class:`~rcbf_ros.training.agent.LearnerConfig` (:meth:`learner_config`), whose
defaults are the ones written here. Imports no torch: ``rcbf_ros train --help`` reads it.
"""
from __future__ import annotations

from dataclasses import dataclass, fields, replace
from typing import Any, TYPE_CHECKING

from rcbf_ros.parameters.reader import setting

if TYPE_CHECKING:
    from rcbf_ros.training.agent import LearnerConfig
    from rcbf_ros.training.build import RunConfig

MODES: tuple[str, ...] = ('unconstrained', 'baseline', 'baseline_compensator', 'diff',
                          'modular')
"""The SAC losses (``rcbf_ros.learning.sac.MODES``, named here without importing torch; a test
keeps the two equal)."""

SEED_MAX: int = 2 ** 32 - 1
"""The largest seed: numpy's and gymnasium's seeds are 0 .. 2**32 - 1 (a negative or larger one
is refused when the env is reset, after the run has started)."""
THREADS_MAX: int = 1024
"""The most torch threads (torch refuses more than a C int; more than cores only slows)."""
ALPHA_MAX: float = 1e6
"""The largest initial entropy temperature (a larger one drowns the Q values: the policy's
actions become NaN or inf once updates start)."""


@dataclass(frozen=True)
class TrainingSettings:
    """One training run: the system and mode, the schedule, where its files go."""

    system: str = setting('unicycle', description='unicycle, car_following or pvtol')
    """The simulated system (its env, safety problem and config/<system>.yaml); in-process
    also the dotted path of a SafetyEnv class (then give config_file)."""
    mode: str = setting('modular', description='SAC losses: modular, diff, baseline, '
                                               'baseline_compensator or unconstrained')
    """Which SAC losses (:data:`MODES`; rcbf_ros.learning.sac)."""
    model_based: bool = setting(False, description='add short model rollouts (MB SAC-RCBF; '
                                                   'needs mode diff)')
    """MB SAC-RCBF: k-step synthetic rollouts from prior + GP mean (needs mode 'diff')."""
    seed: int = setting(0, minimum=0, maximum=SEED_MAX,
                        description='seeds networks, buffers, exploration and the GP')
    """Seeds networks, buffers, exploration, the GP subsample and the first episode."""
    episodes: int = setting(20, minimum=1,
                            description='episodes to train, then the node exits')
    """Training episodes (the learner node's default: NODE_DEFAULTS)."""
    out_dir: str | None = setting(None, description='where metrics, checkpoint, policy and '
                                                    'plots go')
    """Where metrics, checkpoints, the bag and the plots go; None: runs/<:attr:`name`>."""
    start_steps: int = setting(1000, minimum=0, description='uniformly random proposals '
                                                            'before the policy acts')
    """Exploration warm-up: uniformly random proposals before the policy acts."""
    update_after: int = setting(500, minimum=0,
                                description='environment steps before the first update')
    """Environment steps before the first SAC update."""
    batch_size: int = setting(256, minimum=1, description='SAC minibatch size')
    """SAC minibatch size."""
    gp_refit_interval: int = setting(1000, minimum=1,
                                     description='environment steps between GP refits')
    """Environment steps between GP refits (Algorithm 1: once per iteration)."""
    checkpoint_every: int = setting(1, strict=True, minimum=1,
                                    description='episodes between checkpoints (also on exit)')
    """Episodes between checkpoints (a kill loses the episodes since the last one)."""
    resume: bool = setting(False, description="continue from out_dir's checkpoint (without: "
                                              'an out_dir holding a run is refused)')
    """Continue from out_dir/checkpoint.pt (without one: start at episode 0, keeping the files
    already there). Without it, an out_dir that already holds a run is refused."""
    k_c: float = setting(2.0, minimum=0.0,
                         description='the learned disturbance box is mean +/- k_c std')
    """Disturbance box mean +/- k_c std (paper eq. disturb_estimate)."""
    threads: int = setting(1, strict=True, minimum=1, maximum=THREADS_MAX,
                           description='torch threads')
    """torch threads. 1 leaves a core to other work (several runs side by side, or the other
    nodes); a lone in-process run gets 1.2-1.7x faster SAC updates from 2 on a 2-core machine
    (benchmarks/bench_training.py)."""
    initial_alpha: float | None = setting(None, positive=True, maximum=ALPHA_MAX,
                                          description="SAC's initial entropy temperature "
                                                      "(config/<system>.yaml's /learner sets "
                                                      'it)')
    """SAC's initial entropy temperature; None: the config file's ``/learner``
    ``initial_alpha``, else 0.2."""
    modular_envelope: bool | None = setting(
        None, description="modular mode: keep the system envelope's correction in the losses")
    """Modular mode: keep the envelope's correction in the losses (LearnerConfig
    .modular_envelope); None: the config file's ``/learner`` ``modular_envelope``, else
    False."""
    config_file: str | None = setting(None, description='ROS params file (default: the '
                                                        'packaged config/<system>.yaml)')
    """ROS params file (None: the packaged config/<system>.yaml)."""
    max_steps: int | None = setting(None, minimum=1,
                                    description="episode length (default: the env's)")
    """Override the env's episode length."""
    no_obstacles: bool = setting(False, description='train without the layout (the transfer '
                                                    'upper bound)')
    """Train without the layout (RunConfig.no_obstacles)."""
    random_start: bool | None = setting(None, description='random episode starts (default: '
                                                          "the config file's)")
    """Start each episode from a random start of the env; None: the config file's simulator
    ``random_start``."""
    record_bag: bool = setting(True, description="record the run's topics to MCAP")
    """Record the run's topics to MCAP."""
    compile_filter: bool = setting(False, description="compile the per-step filter's "
                                                      'constraint assembly')
    """Compile the per-step filter's autograd constraint assembly (RunConfig.compile_filter)."""
    compile_update: bool = setting(False, description='compile the SAC update')
    """Compile the SAC update (SACConfig.compile_update)."""

    @property
    def name(self) -> str:
        """``<system>_<mode>[_mb]_s<seed>``: the run's name (its default out_dir's)."""
        return f"{self.system}_{self.mode}{'_mb' if self.model_based else ''}_s{self.seed}"

    def learner_config(self, **more: Any) -> LearnerConfig:
        """The learner's configuration: these settings, and ``more`` LearnerConfig fields they
        do not name (buffer and rollout sizes, ``sac`` for its networks, the policy box).

        Raises:
            ValueError: a setting LearnerConfig refuses (naming it).
        """
        from rcbf_ros.learning.sac import SACConfig
        from rcbf_ros.training.agent import LearnerConfig
        sac = replace(more.pop('sac', None) or SACConfig(), initial_alpha=self.initial_alpha,
                      compile_update=self.compile_update)
        return LearnerConfig(
            mode=self.mode, model_based=self.model_based, seed=self.seed,
            batch_size=self.batch_size, start_steps=self.start_steps,
            update_after=self.update_after, gp_refit_interval=self.gp_refit_interval,
            k_c=self.k_c, modular_envelope=self.modular_envelope, sac=sac, **more)

    def run_config(self, **learner: Any) -> RunConfig:
        """The trainer's run (:class:`~rcbf_ros.training.build.RunConfig`); ``learner``: as
        :meth:`learner_config`'s ``more``.

        Raises:
            ValueError: a setting LearnerConfig refuses (naming it).
        """
        from rcbf_ros.training.build import RunConfig
        return RunConfig(
            system=self.system, episodes=self.episodes,
            out_dir=self.out_dir or f'runs/{self.name}', config_file=self.config_file,
            max_steps=self.max_steps, no_obstacles=self.no_obstacles,
            random_start=self.random_start, checkpoint_every=self.checkpoint_every,
            record_bag=self.record_bag, resume=self.resume,
            compile_filter=self.compile_filter, threads=self.threads,
            learner=self.learner_config(**learner))


SETTING_NAMES: tuple[str, ...] = tuple(f.name for f in fields(TrainingSettings))
"""The fields of :class:`TrainingSettings`, in order."""
