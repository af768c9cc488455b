"""The body of every node's ``main()``: the Jazzy pattern, written once.

``rclpy.init`` -> build the node -> spin -> Ctrl-C / SIGTERM end it quietly -> the node's own
exit work -> ``destroy_node`` -> ``rclpy.try_shutdown``, as in ros2/examples (STYLE.md). Each
node keeps a one-line ``main`` that says what differs: how it runs, what it does on exit and
which construction errors are the user's (bad parameters, a missing file) rather than bugs.

``python -m rcbf_ros.ros.node_main <module> [args]`` imports a node module and calls its
``main()``, as its console script does (the local launcher starts every node this way). A SIGINT
that arrives while the module imports (torch, the middleware: seconds) ends the process at once
with status 130: nothing has started that could be lost, and a ``KeyboardInterrupt`` raised
there prints a traceback, or aborts the process when it surfaces inside torch's C++ start-up.
This module imports the middleware only when a node runs, so that protection starts right away.
"""
from __future__ import annotations

import importlib
import os
import signal
import sys
from typing import Any, Callable, Sequence

INTERRUPTED_EXIT = 130
"""Exit status of a node stopped by SIGINT before it started (128 + SIGINT, as a shell says)."""


def run_node(name: str, make_node: Callable[[], Any], args: Sequence[str] | None = None, *,
             run: Callable[[Any], None] | None = None,
             on_exit: Callable[[Any], None] | None = None,
             setup_errors: tuple[type[BaseException], ...] = (),
             setup_message: str = 'invalid parameters: ') -> int:
    """Run one node until it finishes or Ctrl-C / SIGTERM; the console script's exit status.

    Args:
        name: the node's name, for the error line (the node may not exist yet).
        make_node: builds the node (reads and checks its parameters).
        args: command line (None: ``sys.argv``, passed explicitly so every runtime reads it).
        run: drives the node (default ``rclpy.spin``).
        on_exit: the node's exit work, before ``destroy_node`` (also after Ctrl-C / SIGTERM).
        setup_errors: exceptions of ``make_node`` that are the user's: printed as
            ``<name>: <setup_message><error>`` on stderr, exit status 2.
        setup_message: the middle of that line ('' for none).

    Returns:
        0, or 2 on a setup error (including a bad ``--ros-args`` section or params file, which
        ``rclpy.init`` refuses). Other exceptions propagate (after the shutdown).
    """
    from rcbf_ros.ros.runtime import ExternalShutdownException, rclpy

    try:
        rclpy.init(args=list(sys.argv if args is None else args))
    except ValueError as exc:
        print(f'{name}: {exc}', file=sys.stderr)
        return 2
    node = None
    try:
        node = make_node()
        (run or rclpy.spin)(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except setup_errors as exc:
        if node is not None:
            raise
        print(f'{name}: {setup_message}{exc}', file=sys.stderr)
        return 2
    finally:
        if node is not None:
            if on_exit is not None:
                on_exit(node)
            node.destroy_node()
        rclpy.try_shutdown()
    return 0


def _exit_interrupted(signum: int, frame: Any) -> None:
    """SIGINT while a node module imports: leave at once (see the module doc)."""
    os._exit(INTERRUPTED_EXIT)


def run_module(argv: Sequence[str]) -> int:
    """Import node module ``argv[0]`` and return its ``main()``, with ``sys.argv = argv``.

    Returns:
        The node's exit status; :data:`INTERRUPTED_EXIT` after a SIGINT before the node
        installed its own handlers (during the import the process exits at once).
    """
    if not argv:
        print('usage: python -m rcbf_ros.ros.node_main <module> [args ...]', file=sys.stderr)
        return 2
    sys.argv = list(argv)
    previous = signal.signal(signal.SIGINT, _exit_interrupted)
    try:
        module = importlib.import_module(argv[0])
    except KeyboardInterrupt:
        return INTERRUPTED_EXIT
    finally:
        signal.signal(signal.SIGINT, previous)
    try:
        return module.main()
    except KeyboardInterrupt:  # before rclpy.init installed the node's handlers
        return INTERRUPTED_EXIT


if __name__ == '__main__':
    sys.exit(run_module(sys.argv[1:]))
