"""`playseg convert --inspect BAG`: the bag's topics (type, count, rate) and a proposed mapping.

The output is a YAML file: the topic table as comments, then a mapping that `playseg convert --mapping`
accepts as it is when the bag has a camera or a JointState, and a command topic or a state to derive the
action from. It is a starting point: names, the step rate and the tolerance are guesses from the bag.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from playseg_core.data.features import ACTION, IMAGE_PREFIX, STATE
from playseg_ros.convert.decode import COMPRESSED_IMAGE, IMAGE, IMAGE_TYPES, JOINT_STATE
from playseg_ros.convert.source import TIMED_ANNOTATION, open_bag, topic_types

TWISTS = {"geometry_msgs/msg/Twist": "", "geometry_msgs/msg/TwistStamped": "twist."}
ODOMETRY = "nav_msgs/msg/Odometry"
_GENERIC_TOPIC_PARTS = {
    "image_raw",
    "image",
    "compressed",
    "image_color",
    "image_rect",
    "image_rect_color",
    "raw",
}


@dataclass(frozen=True)
class TopicStats:
    topic: str
    msgtype: str
    count: int
    rate_hz: float | None
    first: Any  # the first message, deserialized (None when the topic has none)


def topic_stats(bag: Path) -> tuple[list[TopicStats], float]:
    """Every topic's type, message count and median rate, and the bag's duration in seconds."""
    with open_bag(bag) as reader:
        types = topic_types(reader)
        times: dict[str, list[int]] = {t: [] for t in types}
        first: dict[str, Any] = {}
        for connection, stamp, raw in reader.messages():
            times[connection.topic].append(stamp)
            if connection.topic not in first and connection.msgtype in reader.typestore.fielddefs:
                first[connection.topic] = reader.deserialize(raw, connection.msgtype)
        duration = (reader.end_time - reader.start_time) / 1e9 if reader.message_count else 0.0
    stats = []
    for topic in sorted(types):
        intervals = np.diff(np.sort(np.asarray(times[topic], dtype=np.int64)))
        rate = 1e9 / float(np.median(intervals)) if len(intervals) and np.median(intervals) > 0 else None
        stats.append(TopicStats(topic, types[topic], len(times[topic]), rate, first.get(topic)))
    return stats, duration


def camera_name(topic: str) -> str:
    parts = [p for p in topic.split("/") if p and p not in _GENERIC_TOPIC_PARTS]
    return re.sub(r"[^A-Za-z0-9_]", "_", "_".join(parts)) or "camera"


def propose_mapping(stats: list[TopicStats]) -> dict[str, Any]:
    """A mapping for a bag with these topics (see the module docstring)."""
    features: dict[str, Any] = {}
    cameras = [s for s in stats if s.msgtype in IMAGE_TYPES and s.count]
    rates: dict[str, float | None] = {}
    for camera in cameras:
        name = IMAGE_PREFIX + camera_name(camera.topic)
        if _is_depth(camera):
            name += "_depth" if not name.endswith("depth") else ""
        features[name] = {"topic": camera.topic}
        rates[name] = camera.rate_hz
    joints = next((s for s in stats if s.msgtype == JOINT_STATE and s.count), None)
    odometry = next((s for s in stats if s.msgtype == ODOMETRY and s.count), None)
    if joints is not None:
        features[STATE] = {"topic": joints.topic, "field": "position"}
        rates[STATE] = joints.rate_hz
    elif odometry is not None:
        fields = [f"pose.pose.position.{a}" for a in "xy"] + [f"pose.pose.orientation.{a}" for a in "zw"]
        features[STATE] = {"topic": odometry.topic, "fields": fields}
        rates[STATE] = odometry.rate_hz
    primary = next((n for n in features if n.startswith(IMAGE_PREFIX) and not n.endswith("depth")), None)
    primary = primary or next(iter(features), None)
    fps = float(round(rates.get(primary) or 10.0)) if primary else 10.0
    fps = fps or 10.0
    tolerance_ms = float(math.ceil(500.0 / fps))
    command = next((s for s in stats if s.msgtype in TWISTS and s.count), None)
    if command is not None:
        prefix = TWISTS[command.msgtype]
        period_ms = 1000.0 / command.rate_hz if command.rate_hz else tolerance_ms
        features[ACTION] = {
            "topic": command.topic,
            "fields": [f"{prefix}linear.x", f"{prefix}linear.y", f"{prefix}angular.z"],
            "align": "previous",  # a command holds until the next one
            "tolerance_ms": float(math.ceil(max(period_ms * 1.5, tolerance_ms))),
        }
    elif STATE in features:
        features[ACTION] = {"derive": "next", "of": STATE}
    mapping: dict[str, Any] = {
        "fps": fps,
        "primary": primary,
        "tolerance_ms": tolerance_ms,
        "features": features,
    }
    annotations = next((s for s in stats if s.msgtype == TIMED_ANNOTATION), None)
    if annotations is not None:
        mapping["annotations"] = {"topic": annotations.topic}
    mapping["episodes"] = {"split": "bag"}
    return mapping


def _is_depth(stats: TopicStats) -> bool:
    msg = stats.first
    if msg is None:
        return False
    if stats.msgtype == IMAGE:
        return str(msg.encoding) in ("16UC1", "mono16")
    return stats.msgtype == COMPRESSED_IMAGE and "16UC1" in str(msg.format)


def inspect_text(bag: Path) -> str:
    """The topic table (as YAML comments) and the proposed mapping."""
    stats, duration = topic_stats(bag)
    lines = [f"# bag {str(bag)!r}: {duration:.1f} s, {sum(s.count for s in stats)} messages", "#"]
    width = max((len(s.topic) for s in stats), default=5)
    type_width = max((len(s.msgtype) for s in stats), default=4)
    lines.append(f"# {'topic'.ljust(width)}  {'type'.ljust(type_width)}  {'count':>7}  {'rate':>9}")
    for s in stats:
        rate = f"{s.rate_hz:7.2f} Hz" if s.rate_hz else "        -"
        lines.append(f"# {s.topic.ljust(width)}  {s.msgtype.ljust(type_width)}  {s.count:>7}  {rate}")
    mapping = propose_mapping(stats)
    lines += ["#", "# proposed mapping (check the names, fps and tolerances; docs/convert.md):"]
    if ACTION not in mapping["features"]:
        lines.append("# no command topic and no state to derive an action from: add features.action by hand")
    lines.append(yaml.safe_dump(mapping, sort_keys=False, default_flow_style=None, width=110).rstrip())
    return "\n".join(lines) + "\n"
