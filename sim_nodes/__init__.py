"""The simulator and nominal-controller nodes: ROS-facing wrappers of :mod:`rcbf_ros.envs`
that stand in for a robot and its controller in launches and tests."""
# Before the nodes' numpy: rcbf_ros sets numpy's BLAS up (rcbf_ros/__init__.py).
import rcbf_ros  # noqa: F401
