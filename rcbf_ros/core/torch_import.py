"""PyTorch, imported where it is first used rather than where a module is imported.

The safety filter's per-step path for the built-in systems is numpy and OSQP; only the
autograd assembly (a system or barrier without a closed form), the interior-point fallback and
training need torch. A module of that path binds ``torch = LazyTorch(globals())``: the first
attribute read imports torch and rebinds the global name of every such module to it, so that
every later ``torch.<name>`` is an ordinary module attribute (no cost on the training path), and
a process that never reaches such code never imports torch. A module that needs torch anyway
(the differentiable layer) calls :func:`bind_torch` when it is imported, so that compiled and
traced code never meets the stand-in. Where torch is not installed,
that first read raises one ``ImportError`` saying how to install it.
"""
from __future__ import annotations

import importlib
from types import ModuleType
from typing import Any

INSTALL_HINT = ('PyTorch is needed here (no closed form, the interior-point fallback, learning): '
                'pip install torch==2.13.0 or apt install python3-torch')
"""What the ImportError of a missing torch says (one line, short enough for a node's
error line)."""


def load_torch() -> ModuleType:
    """``import torch``, its ImportError saying how to install it.

    Raises:
        ImportError: torch is not installed (:data:`INSTALL_HINT`).
    """
    try:
        return importlib.import_module('torch')
    except ImportError as exc:
        raise ImportError(f'{INSTALL_HINT} ({exc})') from exc


def import_error_line(exc: ImportError) -> str:
    """What an ImportError says in one line: :data:`INSTALL_HINT` where torch is what is
    missing (a user's module that imports it), else the error itself."""
    missing = getattr(exc, 'name', None) or ''
    if missing.partition('.')[0] == 'torch' and INSTALL_HINT not in str(exc):
        return f'{INSTALL_HINT} ({exc})'
    return str(exc)


_WAITING: list[dict[str, Any]] = []
"""The globals of every module whose ``torch`` is still a :class:`LazyTorch`."""


def bind_torch() -> ModuleType:
    """Import torch and rebind ``torch`` in every module that waits for it (all at once, so
    that no module holds the stand-in when a caller compiles or traces its functions: a module
    that needs torch anyway calls this when it is imported).

    Raises:
        ImportError: torch is not installed (:data:`INSTALL_HINT`).
    """
    module = load_torch()
    while _WAITING:
        namespace = _WAITING.pop()
        if isinstance(namespace.get('torch'), LazyTorch):
            namespace['torch'] = module
    return module


class LazyTorch:
    """Stands for ``torch`` in a module's globals until torch is first used (by any module
    that waits for it, or by :func:`bind_torch`)."""

    __slots__ = ()

    def __init__(self, namespace: dict[str, Any]) -> None:
        """Args: namespace: the module's ``globals()``, whose ``torch`` is rebound on use."""
        _WAITING.append(namespace)

    def __getattr__(self, name: str) -> Any:
        return getattr(bind_torch(), name)
