"""The ``rcbf_ros`` command (:mod:`.main`) and the commands it hands on, such as the generator
of docs/INTERFACE.md (:mod:`.interface_doc`); the top layer: it may import every other."""
