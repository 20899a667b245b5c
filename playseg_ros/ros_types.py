"""Look up rclpy message classes by their ROS type name (there is no rosidl_runtime_py in the wheels)."""

from __future__ import annotations

import importlib

from playseg_core.errors import PlaysegError
from playseg_ros.typestore import split_type_name


def message_class(type_name: str) -> type:
    """'playseg_msgs/msg/PlayStep' (or 'playseg_msgs/PlayStep') -> the generated rclpy class."""
    package, name = split_type_name(type_name)
    try:
        module = importlib.import_module(f"{package}.msg")
        return getattr(module, name)
    except (ImportError, AttributeError) as exc:
        raise PlaysegError(f"message type {type_name!r} is not installed in this environment") from exc
