"""Simulator nodes (ROS-facing wrappers of rcbf_ros.envs)."""
