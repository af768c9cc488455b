"""The ``rcbf_ros`` command (:mod:`.main`)."""
