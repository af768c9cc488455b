"""Child processes for the integration tests: loopback Cyclone DDS, their own domain id."""
from __future__ import annotations

import os
from pathlib import Path
import signal
import subprocess
import sys

REPO = Path(__file__).resolve().parents[2]


def node_runtime() -> str:
    """The runtime the node processes use: this suite's ``RCBF_ROS_RUNTIME`` (test/conftest.py
    makes it ``cyclone`` unless set; the ros2 tier runs the suite with ``rclpy``)."""
    return os.environ.get('RCBF_ROS_RUNTIME', 'cyclone')


def subprocess_env(domain_id: int) -> dict[str, str]:
    """This environment, pinned to loopback, on ``domain_id``, with the repo importable."""
    from rcbf_ros.ros.loopback import ensure_loopback
    env = dict(os.environ)
    ensure_loopback(env, force=True)
    env['ROS_DOMAIN_ID'] = str(domain_id)
    env['RCBF_ROS_RUNTIME'] = node_runtime()
    env['PYTHONUNBUFFERED'] = '1'
    env['PYTHONPATH'] = os.pathsep.join(filter(None, [str(REPO), env.get('PYTHONPATH')]))
    return env


def spawn(domain_id: int, *args: str) -> subprocess.Popen:
    """``python *args`` in that environment, text pipes for stdout and stderr."""
    return subprocess.Popen([sys.executable, *args], env=subprocess_env(domain_id), cwd=REPO,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def stop(process: subprocess.Popen, sig: int = signal.SIGINT, timeout: float = 30.0) -> str:
    """Send ``sig`` (if still running), wait up to ``timeout`` s, then kill; all it printed."""
    if process.poll() is None:
        process.send_signal(sig)
    try:
        out, err = process.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        process.kill()
        out, err = process.communicate()
    return ''.join(part.decode(errors='replace') if isinstance(part, bytes) else part
                   for part in (out, err) if part)


def end_process(process: subprocess.Popen, *, sig: int = signal.SIGINT,
                timeout: float = 30.0) -> int:
    """Send ``sig`` (if still running), wait up to ``timeout`` s, then kill; the exit code.

    Unlike :func:`stop` it leaves the pipes alone: for a process whose output goes to a file,
    or is read by a thread of the test.
    """
    if process.poll() is None:
        process.send_signal(sig)
        try:
            process.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()
    return process.returncode
