"""Look up rclpy message classes by their ROS type name (there is no rosidl_runtime_py in the wheels)."""

from __future__ import annotations

import importlib


def message_class(type_name: str) -> type:
    """'playseg_msgs/msg/PlayStep' (or 'playseg_msgs/PlayStep') -> the generated rclpy class."""
    parts = type_name.split("/")
    if len(parts) == 2:
        parts = [parts[0], "msg", parts[1]]
    if len(parts) != 3 or not all(parts):
        raise ValueError(f"not a ROS message type name: {type_name!r}")
    package, kind, name = parts
    try:
        module = importlib.import_module(f"{package}.{kind}")
        return getattr(module, name)
    except (ImportError, AttributeError) as exc:
        raise ValueError(f"message type {type_name!r} is not installed in this environment") from exc
