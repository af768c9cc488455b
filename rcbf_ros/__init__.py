"""rcbf_ros: safe reinforcement learning with robust control barrier functions for ROS 2."""
import os

from rcbf_ros.openblas import configure as _configure_openblas

# Before numpy is first imported (every entry point imports this package first): numpy's
# OpenBLAS with one thread and the kernels the CPU supports (rcbf_ros/openblas.py says why).
_configure_openblas(os.environ)

__version__ = '0.1.0'
