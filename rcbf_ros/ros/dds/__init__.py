"""A small rclpy-compatible runtime over Eclipse Cyclone DDS (used when rclpy is absent).

Import through :mod:`rcbf_ros.ros.runtime`, not directly. Modules, split as rclpy splits itself:

- :mod:`.rclpy_compat`: the module-level rclpy functions (init, spin, shutdown, ...);
- :mod:`.context`: init/shutdown, signals, the executor;
- :mod:`.node`: ``Node`` (names, endpoints, teardown), with its parameter methods from
  :mod:`.node_parameters` and its graph queries from :mod:`.node_graph`;
- :mod:`.endpoints`: ``Publisher``, ``Subscription``, ``Timer``, ``TopicEndpointInfo``;
- :mod:`.services`: services, clients and futures in rmw_cyclonedds' wire format;
- :mod:`.parameters`: ``Parameter``, its exceptions, descriptors, range checks;
- :mod:`.parameter_service`: the rcl_interfaces parameter services and ``/parameter_events``;
- :mod:`.clock`: ``Time`` and ``Clock``; :mod:`.time_source`: ``use_sim_time`` and ``/clock``;
- :mod:`.log`: ``Logger`` and ``LoggingSeverity``; :mod:`.rosout`: the ``/rosout`` writer;
- :mod:`.graph`: ``ros_discovery_info`` (which node owns which endpoint);
- :mod:`.qos`: QoS profiles and their Cyclone equivalents;
- :mod:`.messages`: message classes, CDR, DDS types from rosbags' Jazzy store.

``--ros-args``, parameter files and names are parsed by :mod:`rcbf_ros.parameters.arguments`.
"""
