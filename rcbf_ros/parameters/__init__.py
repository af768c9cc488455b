"""ROS 2 parameters read as rcl and rclpy read them (:mod:`.rules`: params files, ``-p``,
wildcards, typing), the packaged ``config/<system>.yaml`` files, and the one typed reader
(:mod:`.reader`) that turns flat parameters into every node's frozen settings dataclass; and
YAML from outside read within size, depth, alias and tag limits (:mod:`.bounded_yaml`)."""
