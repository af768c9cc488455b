"""ament_python package setup for rcbf_ros (also installable with pip)."""
from glob import glob
import os

from setuptools import find_packages, setup

package_name = 'rcbf_ros'

FILTER_REQUIRES = ['numpy', 'osqp', 'pyyaml', 'cyclonedds', 'rosbags', 'mcap',
                   'gymnasium']
"""What the filter's path imports (no torch)."""
LEARNING_REQUIRES = ['torch', 'gpytorch', 'matplotlib']
"""What learning adds to :data:`FILTER_REQUIRES`."""

setup(
    name=package_name,
    version='0.1.0',
    # config/*.yaml ship inside the package as rcbf_ros/config (package data), so that
    # rcbf_ros.parameters.rules.find_config finds them in a wheel or any pip install; colcon also
    # gets share/rcbf_ros/config (data_files) for ros2 launch and $(ros2 pkg prefix).
    packages=find_packages(exclude=['test', 'test.*', 'benchmarks']) + ['rcbf_ros.config'],
    package_dir={'rcbf_ros.config': 'config'},
    package_data={'rcbf_ros.config': ['*.yaml', '*.json']},
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
        (os.path.join('share', package_name, 'config'),
         glob('config/*.yaml') + glob('config/*.json')),
        (os.path.join('share', package_name, 'launch'), glob('launch/*.py')),
    ],
    # ROS 2's convention: what rosdep provides is in package.xml, colcon installs no Python
    # dependencies, and a node script does not check them.
    install_requires=['setuptools'],
    extras_require={
        # The filter's path, without torch: the safety_filter, simulator, nominal_controller,
        # recorder, replay and scene_markers nodes and rcbf_ros launch / refilter / bag /
        # summary on the built-in systems (test/unit/test_lean_filter.py refuses torch and runs
        # them). On ROS 2, rosdep provides numpy and yaml, and rclpy stands in for cyclonedds.
        'filter': FILTER_REQUIRES,
        # Learning on top: the learner and policy nodes, rcbf_ros train / experiment, the
        # pictures (reward curve, trajectories). torch from constraints.txt's pin (CPU wheel).
        'learning': FILTER_REQUIRES + LEARNING_REQUIRES,
        # Everything the package needs where rosdep does not provide it (the full install).
        'standalone': FILTER_REQUIRES + LEARNING_REQUIRES + ['mcap-ros2-support'],
        'test': ['pytest', 'pytest-timeout', 'hypothesis', 'qpth', 'cvxpylayers', 'proxsuite',
                 'pymcap-cli', 'ruff', 'ray'],
        'ray': ['ray'],
    },
    zip_safe=True,
    maintainer='rcbf_ros developers',
    maintainer_email='rcbf-ros@example.org',
    description='Safe RL with robust control barrier functions for ROS 2',
    license='Apache-2.0',
    entry_points={
        'console_scripts': [
            'safety_filter = rcbf_ros.ros.node_main:safety_filter',
            'simulator = sim_nodes.simulator_node:main',
            'nominal_controller = sim_nodes.nominal_controller_node:main',
            'unicycle_lidar = sim_nodes.unicycle_lidar_node:main',
            'recorder = rcbf_ros.ros.recorder_node:main',
            'replay = rcbf_ros.ros.replay_node:main',
            'learner = rcbf_ros.ros.learner_node:main',
            'policy = rcbf_ros.ros.policy_node:main',
            'scene_markers = rcbf_ros.ros.scene_node:main',
            'rcbf_ros = rcbf_ros.cli.main:main',
            # The same as `rcbf_ros launch` and `rcbf_ros refilter`, under their first names.
            'rcbf_ros_launch = rcbf_ros.cli.main:launch_alias',
            'rcbf_ros_refilter = rcbf_ros.cli.main:refilter_alias',
        ],
    },
)
