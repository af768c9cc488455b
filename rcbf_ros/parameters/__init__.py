"""ROS 2 parameters read as rcl and rclpy read them (:mod:`.rules`: params files, ``-p``,
wildcards, typing), and the packaged ``config/<system>.yaml`` files."""
