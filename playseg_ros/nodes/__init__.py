"""playseg's ROS 2 nodes, one module (and console entry point) each."""
