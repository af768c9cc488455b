"""A small rclpy-compatible runtime over Eclipse Cyclone DDS (used when rclpy is absent).

Modules: :mod:`.messages` (message classes, CDR, DDS types from rosbags' Jazzy store),
:mod:`.arguments` (``--ros-args``, parameter files, names), :mod:`.qos`, :mod:`.context`
(init/shutdown, signals, executor), :mod:`.node` (Node and endpoints), :mod:`.rclpy_compat`
(the module-level rclpy functions). Import through :mod:`rcbf_ros.ros.runtime`, not directly.
"""
