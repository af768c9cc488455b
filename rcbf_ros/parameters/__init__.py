"""Parameters as ROS 2 reads them, without middleware: rcl's arguments and params files, the
packaged configs, bounded YAML, and the typed reader that turns them into settings dataclasses."""
