"""Session-wide test setup: loopback-only DDS and single-threaded torch, before anything else."""
from __future__ import annotations

import itertools
import os

import pytest

from rcbf_ros.ros.loopback import ensure_loopback

# Before any DDS participant can exist (brief: never send traffic off the machine).
ensure_loopback(force=True)

_domain_counter = itertools.count()


@pytest.fixture
def ros_domain_id() -> int:
    """A ROS_DOMAIN_ID of this test's own, so parallel runs and tests never cross.

    Derived from the pid so that two pytest processes on one machine pick different ids;
    kept in 1..200 (valid DDS domain ids that leave room for the port arithmetic).
    """
    return 1 + (os.getpid() * 7 + next(_domain_counter)) % 200


def pytest_configure(config):
    try:
        import torch
        torch.set_num_threads(1)
    except ImportError:
        pass
