"""playseg_ros: the ROS 2 side of playseg (nodes, message conversion, rosbag2/MCAP I/O, CLI)."""

__version__ = "0.1.0"
