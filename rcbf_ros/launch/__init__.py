"""Launching the nodes: the table of launch setups and their arguments (:mod:`.table`), shared
by ``ros2 launch`` (:mod:`.description`, for the files in ``launch/``) and the launcher that
needs no ROS install (:mod:`.local`, ``rcbf_ros launch``)."""
