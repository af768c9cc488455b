"""ROS 2 messages without middleware, shared by the bag tools and the nodes' runtime.

- :mod:`.typestore`: the one ROS 2 Jazzy type store (rosbags'), type names, message
  definitions and RIHS01 type hashes;
- :mod:`.classes`: message classes generated from it that behave like rclpy's;
- :mod:`.cdr`: CDR (de)serialisation of those classes, of rosbags' objects and of field dicts;
- :mod:`.conversions`: message <-> numpy, the one module where message layouts are decided.

No DDS here: the Cyclone DDS specifics (IDL types, DDS type names, payload padding) are in
:mod:`rcbf_ros.ros.dds.messages`.
"""
