"""One training run's lifecycle in its ``out_dir``: start, resume, metrics, checkpoints, finish.

Both entry points drive a :class:`TrainingRun`: ``rcbf_ros train``
(:mod:`rcbf_ros.training.loop`, the env in-process) and the learner node (the env in the
simulator node). So both refuse an ``out_dir`` that holds a run unless resuming, resume each
other's checkpoints (:mod:`rcbf_ros.training.checkpoint`, one format), append the same
``metrics.jsonl`` rows, and end the same way: a failed write stops the run with one line saying
what the last checkpoint holds, and nothing more is written.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterable, Mapping

from rcbf_ros.training.agent import SafeLearner
from rcbf_ros.training.build import RunSetupError
from rcbf_ros.training.checkpoint import (
    CHECKPOINT,
    Checkpoint,
    CheckpointError,
    describe_difference,
    identity_of,
    read_checkpoint,
    restore_learner,
    write_checkpoint,
)
from rcbf_ros.training.policy_io import save_policy
from rcbf_ros.training.run_files import (
    append_row,
    describe_cut,
    describe_write_error,
    reconcile_metrics,
    run_data,
    RunWriteError,
)

METRICS = 'metrics.jsonl'
"""The per-episode rows' file in a run's ``out_dir``."""


@dataclass(frozen=True)
class EntryPoint:
    """What a run says about the program driving it."""

    made_by: str
    """The ``made_by`` of its checkpoints ('rcbf_ros train', 'learner node')."""
    resume_option: str
    """How its user asks to resume ('--resume', 'resume:=true')."""
    refusal: str
    """What the refusal of an ``out_dir`` that holds a run ends with (what to do instead)."""
    restores_env: bool
    """Whether it restores a checkpoint's env generator (False: another process owns the env,
    and a resume says so)."""


TRAINER = EntryPoint('rcbf_ros train', '--resume',
                     'resume it (--resume) or choose another directory', restores_env=True)
"""``rcbf_ros train``."""
NODE = EntryPoint('learner node', 'resume:=true',
                  'set resume:=true to continue it or choose another out_dir',
                  restores_env=False)
"""The learner node."""


class TrainingRun:
    """The files of one run in ``out_dir`` and what its checkpoints hold.

    The driver calls :meth:`open` once (before any episode), :meth:`restore` once its learner
    exists, :meth:`record` at the end of every episode (then :meth:`save_checkpoint` when
    :meth:`checkpoint_due`), and :meth:`finish` at the end, also after Ctrl-C. A failed write
    raises the ``OSError``; :meth:`stopped` words it, and the driver writes nothing more.
    """

    def __init__(self, out_dir: str | Path, *, entry: EntryPoint, system_name: str,
                 resume: bool, checkpoint_every: int, settings: Mapping[str, Any],
                 log: Callable[[str], None]) -> None:
        """
        Args:
            settings: the run's settings as plain data, kept in every checkpoint for people.
            log: where progress lines go (print, a node's logger).
        """
        self.out = Path(out_dir)
        self.entry = entry
        self.system_name = system_name
        self.resume = resume
        self.checkpoint_every = checkpoint_every
        self.settings = settings
        self.log = log
        self.history: list[dict[str, Any]] = []
        """The rows of the episodes done (a resumed checkpoint's, then this start's)."""
        self.saved_episodes: int | None = None
        """Episodes the checkpoint on disk holds (None: none yet)."""
        self._saved_at = -1  # env steps the checkpoint on disk holds (-1: none of this start's)

    @property
    def checkpoint_path(self) -> Path:
        """``out_dir/checkpoint.pt``."""
        return self.out / CHECKPOINT

    @property
    def metrics_path(self) -> Path:
        """``out_dir/metrics.jsonl``."""
        return self.out / METRICS

    @property
    def episodes(self) -> int:
        """Episodes done (the next episode's number)."""
        return len(self.history)

    def check_out_dir(self) -> list[str]:
        """The run data already in ``out_dir`` (``run_files.run_data``).

        Raises:
            RunSetupError: there is some and the run does not resume.
        """
        existing = run_data(self.out)
        if existing and not self.resume:
            raise RunSetupError(f"out_dir: {self.out} already holds a run "
                                f"({', '.join(existing)}); {self.entry.refusal}")
        return existing

    def open(self, identity: Mapping[str, Any]) -> Checkpoint | None:
        """Start the run: check ``out_dir``, read the checkpoint to resume (if any, checked
        against ``identity``, :func:`~rcbf_ros.training.checkpoint.learner_identity`), then
        create ``out_dir`` and cut ``metrics.jsonl`` back to the checkpoint's episodes.
        Returns the checkpoint, for :meth:`restore`.

        Raises:
            RunSetupError: ``out_dir`` holds a run and the run does not resume.
            CheckpointError: the checkpoint is refused, damaged or of another run; nothing
                was written.
            RunWriteError: ``out_dir`` or the metrics could not be written.
        """
        existing = self.check_out_dir()
        checkpoint = None
        if self.resume and self.checkpoint_path.exists():
            checkpoint = read_checkpoint(self.checkpoint_path, identity=identity)
            self.history = list(checkpoint.history)
            self.saved_episodes = checkpoint.episode
            made_by = checkpoint.made_by
            self.log(f'resumed at episode {checkpoint.episode}'
                     + (f' of a run of {made_by}' if made_by and made_by != self.entry.made_by
                        else '')
                     + f' from {self.checkpoint_path}'
                     + ('; the simulator keeps its own episode generator'
                        if checkpoint.env_rng is not None and not self.entry.restores_env
                        else ''))
        elif self.resume:
            self.log(f'no checkpoint in {self.out}: starting at episode 0'
                     + (' (the files there are kept)' if existing else ''))
        try:
            self.out.mkdir(parents=True, exist_ok=True)
            cut = reconcile_metrics(self.metrics_path, history=self.history)
        except OSError as exc:
            raise RunWriteError(f'{describe_write_error(exc)}; the run did not start') from None
        if cut:
            self.log(describe_cut(count=cut, history=self.history))
        return checkpoint

    def restore(self, learner: SafeLearner, checkpoint: Checkpoint) -> None:
        """Load ``checkpoint``'s learner state into ``learner``, after checking the built
        learner's identity (its observation size too) against the checkpoint's.

        Raises:
            CheckpointError: one line naming the file and what does not fit.
        """
        difference = describe_difference(checkpoint.identity,
                                         identity_of(learner, self.system_name))
        if difference:
            raise CheckpointError(f'resume: {self.checkpoint_path} {difference}')
        restore_learner(learner, checkpoint, self.checkpoint_path)
        self._saved_at = learner.env_steps

    def record(self, row: Mapping[str, Any]) -> None:
        """One episode done: its row joins the history and is appended to ``metrics.jsonl``
        (flushed to disk). Raises OSError: the row could not be written (it stays in the
        history; :meth:`finish` does not write it either, after a failure)."""
        self.history.append(dict(row))
        append_row(self.metrics_path, row)

    def checkpoint_due(self) -> bool:
        """Whether the episodes done call for a checkpoint (every ``checkpoint_every``)."""
        return self.episodes % self.checkpoint_every == 0

    def save_checkpoint(self, learner: SafeLearner, *,
                        env_rng: Mapping[str, Any] | None) -> None:
        """Write ``learner`` and the episodes done to ``checkpoint.pt`` at once.

        Raises:
            OSError: not written (a full disk); the previous checkpoint is intact.
        """
        write_checkpoint(self.checkpoint_path, learner=learner, system_name=self.system_name,
                         episode=self.episodes, history=self.history, env_rng=env_rng,
                         made_by=self.entry.made_by, run=self.settings)
        self._saved_at, self.saved_episodes = learner.env_steps, self.episodes

    def finish(self, learner: SafeLearner | None, *, env_rng: Mapping[str, Any] | None,
               then: Iterable[Callable[[], Any]] = ()) -> None:
        """End the run: ``metrics.jsonl`` gets any row it has not received, the checkpoint
        any step it does not hold, ``policy.pt`` the actor; then ``then``'s steps (pictures,
        a summary). ``learner`` None: none was built (nothing learned to save).

        Raises:
            OSError: the first write that failed; the steps after it were not run.
        """
        reconcile_metrics(self.metrics_path, history=self.history)
        if learner is not None:
            if learner.env_steps != self._saved_at:  # not already saved with every step
                self.save_checkpoint(learner, env_rng=env_rng)
            save_policy(self.out / 'policy.pt', learner.sac, u_low=learner.u_low,
                        u_high=learner.u_high, system=self.system_name)
        for step in then:
            step()

    def stopped(self, exc: OSError) -> str:
        """One line for a run that a failed write stopped: the file, why, what is kept."""
        kept = ('no checkpoint written yet' if self.saved_episodes is None else
                f'{CHECKPOINT} holds {self.saved_episodes} episode(s); '
                f'{self.entry.resume_option} continues from it')
        return f'{describe_write_error(exc)}; the run stopped ({kept})'
