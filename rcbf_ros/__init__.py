"""rcbf_ros: safe reinforcement learning with robust control barrier functions for ROS 2."""

__version__ = '0.1.0'
