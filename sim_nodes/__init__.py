"""Simulator nodes (ROS-facing wrappers of rcbf_ros.envs)."""
# Before the nodes' numpy: rcbf_ros sets numpy's BLAS up (rcbf_ros/__init__.py).
import rcbf_ros  # noqa: F401
