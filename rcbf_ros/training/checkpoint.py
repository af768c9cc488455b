"""``checkpoint.pt``: what a training run's checkpoint holds, how it is written and read.

One format for both entry points, ``rcbf_ros train`` (:mod:`rcbf_ros.training.loop`) and the
learner node, so that each resumes the other's run in the same ``out_dir``. A checkpoint holds

- ``learner``: :meth:`SafeLearner.state_dict` (networks, optimisers, GP, buffers, RNG states);
- ``episode`` and ``history``: the episodes done and their ``metrics.jsonl`` rows;
- ``identity``: the settings that give the learner's tensors their shapes or their meaning
  (:func:`learner_identity`). A resume compares them with its own before any tensor is loaded
  and refuses a difference in one line naming it; the schedule (batch size, warm-up, refit
  interval), the seed and the layout may change between starts;
- ``env_rng``: the episode generator of the env the run's episodes came from, or None when the
  env lives in another process (the learner node: the simulator node owns it). ``rcbf_ros
  train`` restores it; resuming a checkpoint without one it seeds its env from (seed,
  episode) instead, so that the resumed episodes do not replay episode 0's starts. The learner
  node never restores one (its simulator keeps its own seed) and writes None;
- ``made_by`` and ``run``: which entry point wrote it and its settings (for people; never
  compared).

Written beside the file, flushed to disk and renamed over it (:func:`save_payload`): a crash or
a full disk leaves the previous checkpoint, never a torn one. Read with torch's
``weights_only`` unpickler (:func:`load_payload`): reading runs no code from the file.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from rcbf_ros.core.dynamics import ControlAffineSystem
from rcbf_ros.training.agent import LearnerConfig, policy_box, SafeLearner
from rcbf_ros.training.run_files import load_payload, save_payload

CHECKPOINT = 'checkpoint.pt'
"""The checkpoint's name in a run's ``out_dir``."""
FORMAT = 1
"""Version of the layout below (a checkpoint without one predates ``identity``)."""
SETTINGS = ('system', 'mode', 'model_based', 'modular_envelope', 'hidden_sizes', 'buffer_size',
            'gamma')
"""Identity entries a run sets; named first when they differ."""
SHAPES = ('n_x', 'n_u', 'obs_dim', 'policy_low', 'policy_high')
"""Identity entries that follow from the system and its config file (named when no setting
differs, e.g. another ``policy_limits`` or an observation of another size)."""


class CheckpointError(ValueError):
    """A checkpoint that cannot be resumed by this run (one line naming the file and why)."""


@dataclass(frozen=True)
class Checkpoint:
    """A checkpoint as read back (see the module docstring for each entry)."""

    learner: dict[str, Any]
    """:meth:`SafeLearner.state_dict`."""
    episode: int
    """Episodes done: the next one to play."""
    history: list[dict[str, Any]]
    """The ``metrics.jsonl`` rows of those episodes."""
    identity: dict[str, Any]
    """What the learner's tensors and their meaning depend on (:func:`learner_identity`)."""
    env_rng: dict[str, Any] | None
    """The env's episode generator state; None when the env was another process's."""
    made_by: str
    """'rcbf_ros train' or 'learner node' ('' for a checkpoint older than this field)."""


def learner_identity(*, system_name: str, system: ControlAffineSystem, config: LearnerConfig,
                     obs_dim: int | None) -> dict[str, Any]:
    """The settings a checkpoint's learner state depends on, as plain data.

    ``config`` is the learner's resolved configuration (its policy box and envelope flag
    filled in); ``obs_dim`` None: not known yet (the learner node learns it at the first step),
    not compared.
    """
    low, high = policy_box(system, config)
    return {
        'system': system_name, 'mode': config.mode, 'model_based': bool(config.model_based),
        'modular_envelope': config.uses_envelope,
        'hidden_sizes': [int(h) for h in config.sac.hidden_sizes],
        'buffer_size': int(config.buffer_size), 'gamma': float(config.sac.gamma),
        'n_x': int(system.n_x), 'n_u': int(system.n_u),
        'obs_dim': None if obs_dim is None else int(obs_dim),
        'policy_low': [float(v) for v in np.asarray(low).reshape(-1)],
        'policy_high': [float(v) for v in np.asarray(high).reshape(-1)],
    }


def identity_of(learner: SafeLearner, system_name: str) -> dict[str, Any]:
    """:func:`learner_identity` of a built learner."""
    return learner_identity(system_name=system_name, system=learner.system,
                            config=learner.config, obs_dim=learner.sac.obs_dim)


def write_checkpoint(path: str | Path, *, learner: SafeLearner, system_name: str, episode: int,
                     history: Sequence[Mapping[str, Any]], env_rng: Mapping[str, Any] | None,
                     made_by: str, run: Mapping[str, Any]) -> Path:
    """Write ``learner``'s state and the run's progress to ``path`` at once.

    Raises:
        OSError: the file could not be written (a full disk); the previous checkpoint is
            intact and no partial file is left.
    """
    return save_payload(path, {
        'format': FORMAT, 'learner': learner.state_dict(), 'episode': int(episode),
        'history': [dict(row) for row in history],
        'identity': identity_of(learner, system_name),
        'env_rng': None if env_rng is None else dict(env_rng),
        'made_by': made_by, 'run': _plain_data(run)})


def read_checkpoint(path: str | Path, *, identity: Mapping[str, Any]) -> Checkpoint:
    """Read ``path`` and check that this run (``identity``, :func:`learner_identity`) can
    resume it, before any tensor goes into a learner.

    Raises:
        CheckpointError: one line: the file is refused (it holds more than tensors and plain
            data), damaged, not a checkpoint, or of a run that differs in a setting that shapes
            the learner (naming the setting and both values).
    """
    path = Path(path)
    try:
        payload = load_payload(path)
    except (OSError, ValueError) as exc:
        raise CheckpointError(f'resume: {_with_path(exc, path)}') from None
    for key in ('learner', 'episode', 'history'):
        if key not in payload:
            raise CheckpointError(f"resume: {path}: no '{key}' entry (not a checkpoint?)")
    learner, episode, history = payload['learner'], payload['episode'], payload['history']
    if not isinstance(learner, dict):
        raise CheckpointError(f'resume: {path}: learner: expected a dict, got a '
                              f'{type(learner).__name__}')
    if isinstance(episode, bool) or not isinstance(episode, int) or episode < 0:
        raise CheckpointError(f'resume: {path}: episode: expected a count >= 0, got '
                              f'{episode!r:.40}')
    if not isinstance(history, list) or not all(isinstance(r, dict) for r in history):
        raise CheckpointError(f'resume: {path}: history: expected a list of metrics rows')
    if len(history) != episode:
        raise CheckpointError(f'resume: {path}: history holds {len(history)} rows for '
                              f'{episode} episodes')
    env_rng = payload.get('env_rng')
    if env_rng is not None and not isinstance(env_rng, dict):
        raise CheckpointError(f'resume: {path}: env_rng: expected a dict or None, got a '
                              f'{type(env_rng).__name__}')
    stored = payload.get('identity')
    if stored is None:
        stored = _legacy_identity(payload)
    if not isinstance(stored, dict):
        raise CheckpointError(f'resume: {path}: identity: expected a dict, got a '
                              f'{type(stored).__name__}')
    difference = describe_difference(stored, identity)
    if difference:
        raise CheckpointError(f'resume: {path} {difference}')
    made_by = payload.get('made_by', '')
    return Checkpoint(learner=learner, episode=episode, history=history, identity=stored,
                      env_rng=env_rng, made_by=made_by if isinstance(made_by, str) else '')


def restore_learner(learner: SafeLearner, checkpoint: Checkpoint, path: str | Path) -> None:
    """Load ``checkpoint``'s learner state into ``learner`` (same identity, checked by
    :func:`read_checkpoint`).

    Raises:
        CheckpointError: the state does not fit the learner after all (a damaged or crafted
            file whose identity does not tell the truth), in one line naming the file.
    """
    try:
        learner.load_state_dict(checkpoint.learner)
    except (KeyError, IndexError, RuntimeError, TypeError, ValueError, AttributeError) as exc:
        first = str(exc).splitlines()[0] if str(exc) else ''
        detail = f'no {exc} entry' if isinstance(exc, KeyError) else \
            f'{type(exc).__name__}: {first[:160]}'
        raise CheckpointError(f'resume: {path}: its learner state does not fit this run '
                              f'({detail})') from None


def describe_difference(stored: Mapping[str, Any], ours: Mapping[str, Any]) -> str:
    """'' when a run with identity ``ours`` may resume a checkpoint made with ``stored``; else
    'was made with <key> <value>, ...; this run has <key> <value>, ...' naming the run
    settings that differ (or, when none does, the shapes that follow from them). An entry
    either side does not hold (None or absent) is not compared."""
    def differs(key: str) -> bool:
        a, b = stored.get(key), ours.get(key)
        return a is not None and b is not None and _plain(a) != _plain(b)

    keys = [k for k in SETTINGS if differs(k)] or [k for k in SHAPES if differs(k)]
    if not keys:
        return ''
    made = ', '.join(f'{k} {_show(stored[k])}' for k in keys)
    this = ', '.join(f'{k} {_show(ours[k])}' for k in keys)
    return f'was made with {made}; this run has {this}'


def env_seed(seed: int, episode: int) -> int:
    """The seed of the env's first episode when ``rcbf_ros train`` resumes a checkpoint
    without the env's generator (the learner node's): a function of the run's seed and the
    episode, so a resumed run is repeatable and does not replay episode 0's starts."""
    return int(np.random.SeedSequence([int(seed), int(episode)]).generate_state(1)[0])


def _legacy_identity(payload: Mapping[str, Any]) -> dict[str, Any]:
    """The identity of a checkpoint written before it held one, from what it does hold: the
    learner's configuration, its buffer's widths and the trainer's ``run`` settings. What it
    does not tell (the policy box when it was the system's limits) is not compared."""
    learner = payload.get('learner') or {}
    config = learner.get('config') if isinstance(learner, dict) else None
    run = payload.get('run')
    identity: dict[str, Any] = {}
    if isinstance(run, dict) and isinstance(run.get('system'), str):
        identity['system'] = run['system']
    if isinstance(config, dict):
        sac = config.get('sac') if isinstance(config.get('sac'), dict) else {}
        identity.update({
            'mode': config.get('mode'), 'model_based': config.get('model_based'),
            'modular_envelope': (config.get('mode') == 'modular'
                                 and bool(config.get('modular_envelope'))),
            'hidden_sizes': sac.get('hidden_sizes'), 'buffer_size': config.get('buffer_size'),
            'gamma': sac.get('gamma')})
        if config.get('policy_min'):
            identity['policy_low'] = config.get('policy_min')
            identity['policy_high'] = config.get('policy_max')
    data = learner.get('buffer', {}).get('data') if isinstance(learner, dict) and \
        isinstance(learner.get('buffer'), dict) else None
    if isinstance(data, dict):
        for key, name in (('obs_dim', 'obs'), ('n_x', 'state'), ('n_u', 'u_rl')):
            shape = getattr(data.get(name), 'shape', None)
            if shape is not None and len(shape) == 2:
                identity[key] = int(shape[1])
    return identity


def _plain_data(value: Any) -> Any:
    """``value`` with tuples as lists and anything not plain (a path) as its string: the
    ``run`` entry is for people, never compared."""
    if isinstance(value, Mapping):
        return {str(k): _plain_data(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain_data(v) for v in value]
    if isinstance(value, (bool, int, float, str, type(None))):
        return value
    return str(value)


def _plain(value: Any) -> Any:
    """Lists and tuples compare alike (a checkpoint may hold either)."""
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    return value


def _show(value: Any) -> str:
    text = str(_plain(value)) if isinstance(value, (list, tuple)) else str(value)
    return text if len(text) <= 60 else text[:57] + '...'


def _with_path(exc: BaseException, path: Path) -> str:
    text = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
    return text if text.startswith(str(path)) else f'{path}: {text}'
