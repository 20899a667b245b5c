"""playseg_core: Play Segmentation without ROS (data model, datasets, models, decoding, metrics).

Never imports rclpy or playseg_ros: everything here runs in a plain Python process.
"""

__version__ = "0.1.0"
