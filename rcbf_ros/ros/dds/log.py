"""rclpy's logging over the Cyclone runtime: rcutils-style lines on stderr and ``/rosout``."""
from __future__ import annotations

import enum
import sys
import time
from typing import Any

from rcbf_ros.ros.console import console_line
from rcbf_ros.ros.dds.rosout import RosoutWriter


class LoggingSeverity(enum.IntEnum):
    """rclpy.logging.LoggingSeverity."""

    UNSET = 0
    DEBUG = 10
    INFO = 20
    WARN = 30
    ERROR = 40
    FATAL = 50


LEVEL_NAMES = {'debug': LoggingSeverity.DEBUG, 'info': LoggingSeverity.INFO,
               'warn': LoggingSeverity.WARN, 'warning': LoggingSeverity.WARN,
               'error': LoggingSeverity.ERROR, 'fatal': LoggingSeverity.FATAL}
"""The severity of each ``--log-level`` name."""


class Logger:
    """rcutils-style logger writing ``[LEVEL] [time] [name]: message`` to stderr, and, for a
    node's logger and its children, the same line to ``/rosout`` (:mod:`.rosout`). A line
    stderr cannot take (a full disk, a closed pipe) is dropped there, as rcutils drops it."""

    def __init__(self, name: str, level: LoggingSeverity = LoggingSeverity.INFO,
                 rosout: RosoutWriter | None = None) -> None:
        self.name = name
        self.level = level
        self._rosout = rosout
        self._once: set[tuple[str, str]] = set()
        self._last: dict[tuple[str, str], float] = {}

    def get_child(self, suffix: str) -> Logger:
        return Logger(f'{self.name}.{suffix}', self.level, self._rosout)

    def _log(self, severity: LoggingSeverity, message: str, *, once: bool = False,
             throttle_duration_sec: float | None = None, skip_first: bool = False,
             **_ignored: Any) -> bool:
        if severity < self.level:
            return False
        key = (severity.name, str(message))
        if once:
            if key in self._once:
                return False
            self._once.add(key)
        if throttle_duration_sec is not None or skip_first:
            now = time.monotonic()
            last = self._last.get(key)
            if last is None:
                self._last[key] = now
                if skip_first:
                    return False
            elif throttle_duration_sec is not None and now - last < throttle_duration_sec:
                return False
            else:
                self._last[key] = now
        stamp_ns = time.time_ns()
        console_line(f'[{severity.name}] [{stamp_ns // 10**9}.{stamp_ns % 10**9:09d}] '
                     f'[{self.name}]: {message}')
        if self._rosout is not None:
            caller = sys._getframe(2)  # the caller of debug() ... fatal()
            self._rosout.write(stamp_ns=stamp_ns, level=int(severity), name=self.name,
                               msg=str(message), file=caller.f_code.co_filename,
                               function=caller.f_code.co_name, line=caller.f_lineno)
        return True

    def debug(self, message: str, **kwargs: Any) -> bool:
        return self._log(LoggingSeverity.DEBUG, message, **kwargs)

    def info(self, message: str, **kwargs: Any) -> bool:
        return self._log(LoggingSeverity.INFO, message, **kwargs)

    def warning(self, message: str, **kwargs: Any) -> bool:
        return self._log(LoggingSeverity.WARN, message, **kwargs)

    def error(self, message: str, **kwargs: Any) -> bool:
        return self._log(LoggingSeverity.ERROR, message, **kwargs)
