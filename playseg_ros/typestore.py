"""Message definitions of playseg_msgs for bag I/O without a ROS graph.

The `.msg` files are read from the installed interface package (``<prefix>/share/playseg_msgs/msg``) or,
in a source checkout, from ``msg_defs/playseg_msgs/msg``. From them we build a `rosbags` typestore (for
CDR (de)serialization without rclpy) and the full ``ros2msg`` schema text that rosbag2 writes into MCAP
files (the message definition followed by each dependency, separated by ``=`` lines).
"""

from __future__ import annotations

import sys
from functools import cache
from pathlib import Path

from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from rosbags.typesys.store import Typestore

PLAYSEG_MSG_TYPES = ("PlayStep", "Annotation", "LabelledSegment", "TrainerStatus")
_REPO_MSG_DIR = Path(__file__).resolve().parent.parent / "msg_defs" / "playseg_msgs" / "msg"


def split_type_name(type_name: str) -> tuple[str, str]:
    """'pkg/msg/Type' or 'pkg/Type' -> ('pkg', 'Type')."""
    parts = type_name.split("/")
    if len(parts) == 3 and parts[1] == "msg" and all(parts):
        return parts[0], parts[2]
    if len(parts) == 2 and all(parts):
        return parts[0], parts[1]
    raise ValueError(f"message type name {type_name!r} is not 'package/msg/Type' or 'package/Type'")


def msg_dir() -> Path:
    """Directory holding playseg_msgs' .msg files (installed copy first, then the source tree)."""
    for candidate in (Path(sys.prefix) / "share" / "playseg_msgs" / "msg", _REPO_MSG_DIR):
        if (candidate / "PlayStep.msg").is_file():
            return candidate
    raise FileNotFoundError(
        f"playseg_msgs .msg files not found in {sys.prefix}/share/playseg_msgs/msg or {_REPO_MSG_DIR}"
    )


def msg_text(name: str) -> str:
    """The .msg definition of playseg_msgs/msg/<name>."""
    return (msg_dir() / f"{name}.msg").read_text()


@cache
def playseg_typestore() -> Typestore:
    """A rosbags typestore with ROS 2 Kilted's standard types plus playseg_msgs."""
    store = get_typestore(Stores.ROS2_KILTED)
    types = {}
    for name in PLAYSEG_MSG_TYPES:
        types.update(get_types_from_msg(msg_text(name), f"playseg_msgs/msg/{name}"))
    store.register(types)
    return store
