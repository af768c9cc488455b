"""ROS 2 Jazzy messages without middleware: the type store, message classes, CDR and message
<-> numpy, shared by the bag tools and the nodes (DDS specifics: :mod:`rcbf_ros.ros.dds`)."""
