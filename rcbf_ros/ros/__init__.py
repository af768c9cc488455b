"""The nodes (parameters in, bytes <-> arrays, one call into the layers below, publish) and
the runtime they import: real rclpy where installed, else the Cyclone DDS one in :mod:`.dds`."""
