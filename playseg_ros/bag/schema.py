"""What a rosbag2 bag records about its topics and files: message definitions (``ros2msg`` schema text),
QoS profiles, topic metadata and the ``metadata.yaml`` layout (rosbag2 metadata version 9).

Messages enter bags as already-serialized CDR bytes; `topic_info` builds a topic's schema text and RIHS01
type hash from the installed ``.msg`` files.
"""

from __future__ import annotations

import os
import re
import sys
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml
from mcap.records import Channel, Schema
from rosbags.typesys.store import Typestore

from playseg_core.errors import PlaysegError
from playseg_core.yaml_io import parse_yaml
from playseg_ros.typestore import msg_dir, playseg_typestore, split_type_name

METADATA_FILE = "metadata.yaml"
METADATA_VERSION = 9  # rosbag2 (Jazzy, Kilted) metadata format; rosbags reads versions up to 9
PARTIAL_SUFFIX = ".partial"
ROS_DISTRO = os.environ.get("ROS_DISTRO", "kilted")
_DEFINITION_DELIMITER = "=" * 80
_PRIMITIVE_TYPES = frozenset(
    "bool byte char float32 float64 int8 uint8 int16 uint16 int32 uint32 int64 uint64 string wstring".split()
)
# rclpy's "infinite" duration as rosbag2 writes it into QoS profiles.
_INFINITE_DURATION = {"sec": 9223372036, "nsec": 854775807}


# --- message definitions ------------------------------------------------------------------------------


def _msg_search_dirs(package: str) -> list[Path]:
    prefixes = [Path(sys.prefix), *(Path(p) for p in os.environ.get("AMENT_PREFIX_PATH", "").split(":") if p)]
    dirs = [prefix / "share" / package / "msg" for prefix in prefixes]
    if package == "playseg_msgs":
        dirs.append(msg_dir())  # a source checkout without the installed interface package
    return dirs


def msg_file_text(type_name: str) -> str:
    """The text of the installed ``.msg`` file of ``type_name`` (exactly as rosbag2 embeds it)."""
    package, name = split_type_name(type_name)
    for directory in _msg_search_dirs(package):
        path = directory / f"{name}.msg"
        if path.is_file():
            return path.read_text()
    raise PlaysegError(f"no .msg file for {type_name!r} in {[str(d) for d in _msg_search_dirs(package)]}")


def _msg_dependencies(text: str, package: str) -> list[str]:
    """Non-primitive field types of a .msg text as 'pkg/Type', sorted like rosbag2's std::set."""
    found = set()
    for line in text.splitlines():
        tokens = line.split("#", 1)[0].split()
        if len(tokens) < 2:
            continue
        field_type = re.sub(r"(\[[^\]]*\]|<=\d+)", "", tokens[0])  # drop array and string bounds
        if field_type in _PRIMITIVE_TYPES or "=" in field_type:
            continue
        found.add(field_type if "/" in field_type else f"{package}/{field_type}")
    return sorted(found)


def ros2msg_definition(type_name: str) -> str:
    """The complete ``ros2msg`` schema text rosbag2 writes for ``type_name``.

    The type's .msg text, then every dependency (depth first, each once) after a line of 80 '=' and a
    line ``MSG: pkg/Type``.
    """
    seen: set[str] = set()

    def render(name: str) -> str:
        package, _ = split_type_name(name)
        text = msg_file_text(name)
        for dependency in _msg_dependencies(text, package):
            if dependency not in seen:
                seen.add(dependency)
                text += f"\n{_DEFINITION_DELIMITER}\nMSG: {dependency}\n" + render(dependency)
        return text

    return render(type_name)


# --- topics -------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class QosProfile:
    """An offered QoS profile as rosbag2 stores it (policy names in lower case)."""

    history: str = "keep_last"
    depth: int = 10
    reliability: str = "reliable"
    durability: str = "volatile"
    liveliness: str = "automatic"

    def to_dict(self) -> dict[str, Any]:
        return {
            "history": self.history,
            "depth": self.depth,
            "reliability": self.reliability,
            "durability": self.durability,
            "deadline": dict(_INFINITE_DURATION),
            "lifespan": dict(_INFINITE_DURATION),
            "liveliness": self.liveliness,
            "liveliness_lease_duration": dict(_INFINITE_DURATION),
            "avoid_ros_namespace_conventions": False,
        }

    @classmethod
    def from_dict(cls, values: dict[str, Any]) -> QosProfile:
        return cls(
            history=str(values.get("history", "keep_last")),
            depth=int(values.get("depth", 10)),
            reliability=str(values.get("reliability", "reliable")),
            durability=str(values.get("durability", "volatile")),
            liveliness=str(values.get("liveliness", "automatic")),
        )


@dataclass(frozen=True)
class TopicInfo:
    """What a bag needs to know about a topic: name, type, schema text, QoS and RIHS01 type hash."""

    name: str
    type: str  # 'pkg/msg/Type'
    definition: str  # complete ros2msg text
    offered_qos_profiles: tuple[QosProfile, ...] = (QosProfile(),)
    type_hash: str = ""  # 'RIHS01_<sha256>' or '' when unknown
    serialization_format: str = "cdr"

    def qos_yaml(self) -> str:
        """The channel metadata value ``offered_qos_profiles``: a YAML list of profiles."""
        return yaml.safe_dump([q.to_dict() for q in self.offered_qos_profiles], sort_keys=False)

    def metadata(self) -> dict[str, Any]:
        """The ``topic_metadata`` entry of metadata.yaml."""
        return {
            "name": self.name,
            "type": self.type,
            "serialization_format": self.serialization_format,
            "offered_qos_profiles": [q.to_dict() for q in self.offered_qos_profiles],
            "type_description_hash": self.type_hash,
        }


def topic_info(
    name: str,
    type_name: str,
    typestore: Typestore | None = None,
    qos: Sequence[QosProfile] = (QosProfile(),),
) -> TopicInfo:
    """A `TopicInfo` from the installed .msg files; the type hash from ``typestore`` (playseg's default)."""
    store = typestore or playseg_typestore()
    type_hash = store.hash_rihs01(type_name) if type_name in store.types else ""
    return TopicInfo(name, type_name, ros2msg_definition(type_name), tuple(qos), type_hash)


def topic_from_channel(channel: Channel, schema: Schema | None) -> TopicInfo:
    qos_text = channel.metadata.get("offered_qos_profiles", "")
    profiles = parse_yaml(qos_text, channel.topic, "offered_qos_profiles of topic") if qos_text else []
    return TopicInfo(
        name=channel.topic,
        type=schema.name if schema else "",
        definition=schema.data.decode() if schema else "",
        offered_qos_profiles=tuple(QosProfile.from_dict(p) for p in profiles or []),
        type_hash=channel.metadata.get("topic_type_hash", ""),
        serialization_format=channel.message_encoding,
    )


# --- metadata -----------------------------------------------------------------------------------------


@dataclass
class FileStats:
    """Messages of one .mcap file, for metadata.yaml."""

    path: str  # relative to the bag directory
    message_count: int = 0
    start_ns: int = 0
    end_ns: int = 0
    topic_counts: dict[str, int] = field(default_factory=dict)

    def add(self, topic: str, log_time_ns: int) -> None:
        if self.message_count == 0:
            self.start_ns = self.end_ns = log_time_ns
        self.start_ns = min(self.start_ns, log_time_ns)
        self.end_ns = max(self.end_ns, log_time_ns)
        self.message_count += 1
        self.topic_counts[topic] = self.topic_counts.get(topic, 0) + 1


@dataclass
class BagSummary:
    """A finished bag: where it is, its files and message counts."""

    path: Path
    files: list[FileStats]
    topics: dict[str, TopicInfo]
    custom_data: dict[str, str] = field(default_factory=dict)  # rosbag2's free-form string map

    @property
    def message_count(self) -> int:
        return sum(f.message_count for f in self.files)

    @property
    def topic_counts(self) -> dict[str, int]:
        counts = dict.fromkeys(self.topics, 0)
        for stats in self.files:
            for topic, count in stats.topic_counts.items():
                counts[topic] = counts.get(topic, 0) + count
        return counts

    @property
    def start_ns(self) -> int:
        used = [f.start_ns for f in self.files if f.message_count]
        return min(used) if used else 0

    @property
    def duration_ns(self) -> int:
        used = [f.end_ns for f in self.files if f.message_count]
        return max(used) - self.start_ns if used else 0

    def bagfile_information(self) -> dict[str, Any]:
        """The ``rosbag2_bagfile_information`` mapping (keys in rosbag2's order)."""
        counts = self.topic_counts
        return {
            "version": METADATA_VERSION,
            "storage_identifier": "mcap",
            "duration": {"nanoseconds": self.duration_ns},
            "starting_time": {"nanoseconds_since_epoch": self.start_ns},
            "message_count": self.message_count,
            "topics_with_message_count": [
                {"topic_metadata": info.metadata(), "message_count": counts[name]}
                for name, info in self.topics.items()
            ],
            # Chunks are zstd-compressed inside MCAP (storage-level), as rosbag2's MCAP plugin does it:
            # rosbag2 then leaves its own (file/message) compression fields empty.
            "compression_format": "",
            "compression_mode": "",
            "relative_file_paths": [f.path for f in self.files],
            "files": [
                {
                    "path": f.path,
                    "starting_time": {"nanoseconds_since_epoch": f.start_ns},
                    "duration": {"nanoseconds": f.end_ns - f.start_ns},
                    "message_count": f.message_count,
                }
                for f in self.files
            ],
            "custom_data": dict(self.custom_data),
            "ros_distro": ROS_DISTRO,
        }

    def write_metadata(self, directory: Path) -> None:
        text = yaml.safe_dump({"rosbag2_bagfile_information": self.bagfile_information()}, sort_keys=False)
        tmp = directory / (METADATA_FILE + ".tmp")
        tmp.write_text(text)
        tmp.replace(directory / METADATA_FILE)
