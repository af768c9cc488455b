"""A small rclpy-compatible runtime over Eclipse Cyclone DDS, used where rclpy is absent;
import it through :mod:`rcbf_ros.ros.runtime`. Its modules split as rclpy splits itself."""
