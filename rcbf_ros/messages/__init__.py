"""ROS 2 messages without middleware: the Jazzy type store and CDR (:mod:`.typestore`), and
message <-> numpy conversion (:mod:`.conversions`). Shared by the bag tools and the nodes."""
