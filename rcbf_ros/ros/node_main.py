"""The body of every node's ``main()``: the Jazzy pattern, written once.

``rclpy.init`` -> build the node -> spin -> Ctrl-C / SIGTERM end it quietly -> the node's own
exit work -> ``destroy_node`` -> ``rclpy.try_shutdown``, as in ros2/examples (STYLE.md). Each
node keeps a one-line ``main`` that says what differs: how it runs, what it does on exit and
which construction errors are the user's (bad parameters, a missing file) rather than bugs.
"""
from __future__ import annotations

import sys
from typing import Any, Callable, Sequence

from rcbf_ros.ros.runtime import ExternalShutdownException, rclpy


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
