"""The files of a training run: kept through a crash, and never able to run code when read.

Shared by the in-process trainer (:mod:`rcbf_ros.training.loop`) and the learner node:

- ``checkpoint.pt`` and ``policy.pt`` hold tensors and plain data only (dicts, lists, tuples,
  numbers, strings, None): :func:`save_payload` checks that before writing (beside the file,
  then renamed over it) and :func:`load_payload` reads with torch's ``weights_only`` unpickler,
  which refuses anything else. A general pickle can run any code while it is loaded.
- ``metrics.jsonl`` gets one row per finished episode, appended and flushed to disk when the
  episode ends (:func:`append_row`). A resume cuts it back to the episodes its checkpoint holds
  (:func:`reconcile_metrics`, atomically); the rows cut, of episodes the resumed run plays
  again, move to ``metrics_superseded.jsonl``.
- A run that already holds data (:func:`run_data`) is continued with ``resume`` or refused.
- Each start of the in-process trainer records into a bag directory of its own,
  ``bag_0000``, ``bag_0001``, ... (:func:`next_bag_dir`); none is ever written twice.
"""
from __future__ import annotations

import io
import json
import os
from pathlib import Path
import pickle
import re
from typing import Any, Mapping, Sequence

import torch

from rcbf_ros.bag.recover import sync_directory
from rcbf_ros.training.settings import TrainingSettings

DEFAULT_CHECKPOINT_EVERY: int = TrainingSettings.checkpoint_every
"""Episodes between checkpoints: every episode, so a crash loses at most the episode under
way. A Unicycle diff checkpoint with a full replay buffer (200 000 rows) is 35 MB and takes
about 0.1 s, under 1 % of a 1000-step episode (benchmarks/bench_checkpoint.py)."""
SUPERSEDED = 'metrics_superseded.jsonl'
"""Rows a resume cut from ``metrics.jsonl`` (their episodes are played again)."""
_RUN_FILES = ('checkpoint.pt', 'policy.pt', 'summary.json', SUPERSEDED)
_PLAIN = (bool, int, float, str, type(None), torch.Tensor)


class RunWriteError(OSError):
    """A run's file could not be written (a full disk): one line naming the file, the reason
    and what the run keeps."""


class UnsafeFileError(ValueError):
    """A checkpoint or policy file that holds more than tensors and plain data."""


def check_plain(value: Any, *, where: str = 'payload') -> None:
    """Raise TypeError naming the first entry of ``value`` that is not a tensor or plain data
    (``where`` is the name of ``value`` in that message)."""
    if isinstance(value, _PLAIN):
        return
    if isinstance(value, dict):
        for key, item in value.items():
            if not isinstance(key, (str, int)):
                raise TypeError(f'{where}: key {key!r} is a {type(key).__name__}')
            check_plain(item, where=f'{where}.{key}')
        return
    if isinstance(value, (list, tuple)):
        for index, item in enumerate(value):
            check_plain(item, where=f'{where}[{index}]')
        return
    raise TypeError(f'{where}: a {type(value).__module__}.{type(value).__qualname__} is not '
                    'a tensor or plain data')


def save_payload(path: str | Path, payload: Mapping[str, Any]) -> Path:
    """Write ``payload`` (tensors and plain data only) to ``path`` at once: written beside it,
    flushed to disk and renamed over it, so a crash leaves the old file or the new one.

    The payload is serialised in memory first, so that the only writes to the disk are plain
    file writes: a full disk (or a file-size limit) raises OSError from them, the partial file
    is removed and ``path`` is left as it was.

    Raises:
        TypeError: an entry that is not a tensor or plain data (named).
        OSError: the file could not be written (nothing of it is left).
    """
    path = Path(path)
    check_plain(dict(payload), where=path.name)
    buffer = io.BytesIO()
    torch.save(dict(payload), buffer)
    write_atomically(path, buffer.getbuffer())
    return path


def write_atomically(path: str | Path, data: bytes | memoryview | str) -> None:
    """Make ``path`` hold ``data`` at once: written to ``<path>.partial``, flushed to disk and
    renamed over ``path`` (then the directory flushed, so the rename survives a power cut).

    Raises:
        OSError: a write failed (a full disk); the partial file is removed, ``path`` is as it
            was.
    """
    path = Path(path)
    partial = path.with_name(path.name + '.partial')
    raw = data.encode() if isinstance(data, str) else data
    try:
        with partial.open('wb') as stream:
            stream.write(raw)
            stream.flush()
            os.fsync(stream.fileno())
        os.replace(partial, path)
    except BaseException as exc:
        partial.unlink(missing_ok=True)
        if isinstance(exc, OSError) and exc.filename is None:
            exc.filename = str(path)  # a failed write() does not say which file
        raise
    sync_directory(path.parent)


def describe_write_error(exc: OSError) -> str:
    """One line for a failed write: the file and the system's reason (``File too large``,
    ``No space left on device``), without errno numbers or a second line."""
    if exc.filename is not None and exc.strerror:
        name = str(exc.filename)
        if name.endswith('.partial'):
            name = name[:-len('.partial')]
        return f'{name}: {exc.strerror}'
    text = ' '.join(str(exc).split()) or type(exc).__name__
    return text


def load_payload(path: str | Path) -> dict[str, Any]:
    """Read a file written by :func:`save_payload` without running any code from it.

    Raises:
        FileNotFoundError: no such file.
        UnsafeFileError: the file asks for code or objects beyond tensors and plain data
            (a crafted or foreign pickle); nothing of it was executed.
        ValueError: the file is damaged or not a torch file.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f'{path}: no such file')
    try:
        payload = torch.load(path, map_location='cpu', weights_only=True)
    except pickle.UnpicklingError as exc:
        wanted = re.search(r'GLOBAL (\S+)', str(exc))
        detail = f' (it asks for {wanted.group(1)})' if wanted else ''
        raise UnsafeFileError(f'{path}: refused to load: it holds more than tensors and plain '
                              f'data{detail}') from None
    except Exception as exc:  # torch reports a damaged file with many exception types
        first = str(exc).splitlines()[0] if str(exc) else ''
        raise ValueError(f'{path}: not a readable torch file ({type(exc).__name__}: '
                         f'{first[:120]})') from None
    if not isinstance(payload, dict):
        raise ValueError(f'{path}: expected a dict, got a {type(payload).__name__}')
    return payload


def append_row(path: str | Path, row: Mapping[str, Any]) -> None:
    """Append one JSON row to ``path`` and flush it to disk before returning.

    Raises:
        OSError: naming ``path`` (a full disk; a torn row is cut by the next resume,
            :func:`reconcile_metrics`).
    """
    _append(path, json.dumps(row) + '\n')


def _append(path: str | Path, text: str) -> None:
    """Append ``text`` to ``path`` and flush it to disk; an OSError names ``path``."""
    try:
        with Path(path).open('a') as stream:
            stream.write(text)
            stream.flush()
            os.fsync(stream.fileno())
    except OSError as exc:
        if exc.filename is None:
            exc.filename = str(path)  # a failed write() does not say which file
        raise


def write_jsonl(path: str | Path, rows: Sequence[Mapping[str, Any]]) -> None:
    """Make ``path`` hold exactly ``rows``, one JSON object per line, at once
    (:func:`write_atomically`): a crash leaves the old file or the new one."""
    write_atomically(path, ''.join(json.dumps(row) + '\n' for row in rows))


def reconcile_metrics(path: str | Path, *, history: Sequence[Mapping[str, Any]]) -> int:
    """Make ``metrics.jsonl`` at ``path`` hold the rows of ``history`` (a checkpoint's, or
    none without one) when a run resumes; returns how many rows were cut.

    Rows past ``history`` belong to episodes a killed run finished after its last checkpoint;
    the resumed run plays them again. They are appended, as they were, to
    ``metrics_superseded.jsonl`` beside ``path`` before ``path`` is rewritten atomically.
    """
    path = Path(path)
    lines = path.read_text().splitlines(keepends=True) if path.exists() else []
    lines = [line for line in lines if line.strip()]
    cut = lines[len(history):]
    if cut:
        _append(path.with_name(SUPERSEDED),
                ''.join(line if line.endswith('\n') else line + '\n' for line in cut))
    if cut or len(lines) < len(history) or not path.exists():
        write_jsonl(path, history)
    return len(cut)


def run_data(out_dir: str | Path) -> list[str]:
    """Names of the files and bags in ``out_dir`` that hold a run's results (empty: no run
    there, a new one may start)."""
    out = Path(out_dir)
    if not out.is_dir():
        return []
    found = [name for name in _RUN_FILES if (out / name).exists()]
    metrics = out / 'metrics.jsonl'
    if metrics.is_file() and metrics.stat().st_size > 0:
        found.append(metrics.name)
    found += sorted(p.name for p in out.glob('bag_*') if p.is_dir())
    return found


def next_bag_dir(out_dir: str | Path) -> Path:
    """``out_dir/bag_NNNN`` with NNNN one past the highest existing one (``bag_0000`` first)."""
    out = Path(out_dir)
    taken = [int(p.name[4:]) for p in out.glob('bag_*') if p.name[4:].isdigit()]
    return out / f'bag_{max(taken, default=-1) + 1:04d}'


def describe_cut(*, count: int, history: Sequence[Mapping[str, Any]]) -> str:
    """One line saying that ``count`` rows past the checkpoint's episodes were moved aside."""
    return (f"metrics.jsonl: cut back to the checkpoint's {len(history)} episode(s); "
            f'{count} later row(s) moved to {SUPERSEDED}')

