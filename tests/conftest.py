"""Test-wide set-up: every test run gets a private ROS graph.

A domain id derived from the process id (unless ROS_DOMAIN_ID is already set) plus localhost-only
discovery keep concurrent test runs and any other ROS 2 processes on the machine apart. Set before rclpy
is imported anywhere; subprocesses inherit it.
"""

import os

os.environ.setdefault("ROS_DOMAIN_ID", str(100 + os.getpid() % 100))
os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
os.environ.setdefault("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp")
