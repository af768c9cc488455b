"""Launching the nodes: one table of launch setups and arguments (:mod:`.table`) shared by
``ros2 launch`` (:mod:`.description`) and the launcher without ROS (:mod:`.local`)."""
