"""rosbag2-compatible MCAP bags without rclpy: a writer for serialized CDR messages, a reader, recovery.

A bag is a directory holding ``metadata.yaml`` and one or more ``<bag name>_<i>.mcap`` files, as
rosbag2 writes them: MCAP profile ``ros2``, schemas in ``ros2msg`` encoding (the full message definition
followed by each dependency), ``cdr`` messages, channel metadata ``offered_qos_profiles`` and
``topic_type_hash``, a ``rosbag2`` metadata record per file and zstd-compressed chunks.

While a bag is being written it lives in ``<path>.partial`` and is renamed to ``<path>`` when closed, so
an interrupted write never leaves something that looks like a finished bag. A writer killed mid-way
(SIGKILL, power loss) leaves the partial directory behind; `recover_bag` turns it into a finished bag
holding every message up to the last complete chunk.

Messages enter as already-serialized CDR bytes, so a recorder with raw subscriptions can use `BagWriter`
as is; `topic_info` builds a topic's schema text and type hash from the installed ``.msg`` files.
"""

from __future__ import annotations

import os
import re
import shutil
import sys
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from types import TracebackType
from typing import Any

import yaml
from mcap.exceptions import McapError
from mcap.reader import make_reader
from mcap.records import Channel, Footer, Message, Schema
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, Writer
from rosbags.rosbag2 import Reader as Rosbag2Reader
from rosbags.rosbag2 import ReaderError
from rosbags.typesys.store import Typestore

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


class BagError(ValueError):
    """A bag that cannot be read or written as asked; the message names where (bag, topic, episode, step)."""

    def __init__(
        self,
        bag: Path | str,
        detail: str,
        topic: str | None = None,
        episode: str | None = None,
        step: int | None = None,
    ) -> None:
        self.bag, self.topic, self.episode, self.step, self.detail = Path(bag), topic, episode, step, detail
        where = [f"bag {str(bag)!r}"]
        if topic is not None:
            where.append(f"topic {topic!r}")
        if episode is not None:
            where.append(f"episode {episode!r}")
        if step is not None:
            where.append(f"step {step}")
        super().__init__(f"{', '.join(where)}: {detail}")


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
    raise ValueError(f"no .msg file for {type_name!r} in {[str(d) for d in _msg_search_dirs(package)]}")


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


def _topic_from_channel(channel: Channel, schema: Schema | None) -> TopicInfo:
    qos_text = channel.metadata.get("offered_qos_profiles", "")
    profiles = yaml.safe_load(qos_text) if qos_text else []
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
            "custom_data": {},
            "ros_distro": ROS_DISTRO,
        }

    def write_metadata(self, directory: Path) -> None:
        text = yaml.safe_dump({"rosbag2_bagfile_information": self.bagfile_information()}, sort_keys=False)
        tmp = directory / (METADATA_FILE + ".tmp")
        tmp.write_text(text)
        tmp.replace(directory / METADATA_FILE)


def _add_rosbag2_metadata_record(writer: Writer, summary: BagSummary) -> None:
    serialized = yaml.safe_dump(summary.bagfile_information(), sort_keys=False)
    writer.add_metadata("rosbag2", {"serialized_metadata": serialized, "ros_distro": ROS_DISTRO})


# --- writing ------------------------------------------------------------------------------------------


def partial_path(path: Path) -> Path:
    """Where a bag lives while it is being written."""
    return path.with_name(path.name + PARTIAL_SUFFIX)


class _McapFile:
    """One open .mcap file of a bag."""

    def __init__(self, path: Path, compression: CompressionType, chunk_bytes: int) -> None:
        self.stream = path.open("wb")
        # We close chunks ourselves (see add_message), so the library never closes one on its own.
        self.writer = Writer(self.stream, chunk_size=2**62, compression=compression)
        self.chunk_bytes = chunk_bytes
        self.writer.start(profile="ros2", library="playseg bag_io")
        self.schema_ids: dict[str, int] = {}
        self.channel_ids: dict[str, int] = {}
        self.open_chunk_bytes = 0

    def add_topic(self, topic: TopicInfo) -> None:
        if topic.type not in self.schema_ids:
            self.schema_ids[topic.type] = self.writer.register_schema(
                topic.type, "ros2msg", topic.definition.encode()
            )
        self.channel_ids[topic.name] = self.writer.register_channel(
            topic.name,
            topic.serialization_format,
            self.schema_ids[topic.type],
            {"offered_qos_profiles": topic.qos_yaml(), "topic_type_hash": topic.type_hash},
        )

    def add_message(
        self, topic: str, data: bytes | memoryview, log_time_ns: int, publish_time_ns: int, sequence: int
    ) -> None:
        self.writer.add_message(self.channel_ids[topic], log_time_ns, data, publish_time_ns, sequence)
        self.open_chunk_bytes += len(data) + 31  # + message record header
        if self.open_chunk_bytes >= self.chunk_bytes:
            self.flush()

    def flush(self) -> None:
        """Close the open chunk and hand the bytes to the OS."""
        self.writer.flush()
        self.open_chunk_bytes = 0

    @property
    def size_estimate(self) -> int:
        return self.stream.tell() + self.open_chunk_bytes

    def finish(self, summary: BagSummary) -> None:
        self.flush()
        _add_rosbag2_metadata_record(self.writer, summary)
        self.writer.finish()
        self.stream.close()


class BagWriter:
    """Writes a rosbag2 MCAP bag from serialized messages.

    ``max_file_bytes`` / ``max_file_duration_ns`` (0: no limit) start a new .mcap file when the current
    one would grow past them. ``chunk_bytes`` bounds a chunk (and what a crash can lose). Use as a
    context manager: leaving it by an exception removes everything written.
    """

    def __init__(
        self,
        path: Path | str,
        *,
        max_file_bytes: int = 0,
        max_file_duration_ns: int = 0,
        chunk_bytes: int = 1 << 20,
        compression: str = "zstd",
    ) -> None:
        if compression not in ("zstd", "none"):
            raise ValueError(f"compression must be 'zstd' or 'none', got {compression!r}")
        self.path = Path(path)
        self.directory = partial_path(self.path)
        for existing in (self.path, self.directory):
            if existing.exists():
                raise FileExistsError(
                    f"bag {str(self.path)!r}: {existing} already exists"
                    + (
                        " (an unfinished bag: run `playseg bag recover`)"
                        if existing == self.directory
                        else ""
                    )
                )
        self.directory.mkdir(parents=True)
        self.max_file_bytes = max_file_bytes
        self.max_file_duration_ns = max_file_duration_ns
        self.chunk_bytes = chunk_bytes
        self._compression = CompressionType.ZSTD if compression == "zstd" else CompressionType.NONE
        self._summary = BagSummary(self.path, [], {})
        self._sequence: dict[str, int] = {}
        self._file: _McapFile | None = None
        self._closed = False

    @property
    def topics(self) -> dict[str, TopicInfo]:
        return dict(self._summary.topics)

    def add_topic(self, topic: TopicInfo) -> None:
        """Declare a topic before writing its first message."""
        if topic.name in self._summary.topics:
            if self._summary.topics[topic.name] != topic:
                raise BagError(self.path, "added twice with different types or definitions", topic.name)
            return
        self._summary.topics[topic.name] = topic
        self._sequence[topic.name] = 0
        if self._file is not None:
            self._file.add_topic(topic)

    def write(
        self, topic: str, data: bytes | memoryview, log_time_ns: int, publish_time_ns: int | None = None
    ) -> None:
        """Append one serialized message (CDR bytes) logged at ``log_time_ns`` (and published then,
        unless ``publish_time_ns`` is given)."""
        if self._closed:
            raise BagError(self.path, "write after close", topic)
        if topic not in self._summary.topics:
            raise BagError(self.path, "topic not added to the bag (call add_topic first)", topic)
        if self._file is None or self._file_full(len(data), log_time_ns):
            self._start_file()
        assert self._file is not None
        publish_time_ns = log_time_ns if publish_time_ns is None else publish_time_ns
        self._file.add_message(topic, data, log_time_ns, publish_time_ns, self._sequence[topic])
        self._sequence[topic] += 1
        self._summary.files[-1].add(topic, log_time_ns)

    def flush(self) -> None:
        """Close the open chunk and hand it to the OS: a crash after this loses none of it."""
        if self._file is not None:
            self._file.flush()

    def _file_full(self, incoming_bytes: int, log_time_ns: int) -> bool:
        assert self._file is not None
        stats = self._summary.files[-1]
        if stats.message_count == 0:
            return False
        too_big = self.max_file_bytes and self._file.size_estimate + incoming_bytes > self.max_file_bytes
        too_long = self.max_file_duration_ns and log_time_ns - stats.start_ns >= self.max_file_duration_ns
        return bool(too_big or too_long)

    def _start_file(self) -> None:
        if self._file is not None:
            self._file.finish(self._summary)
        name = f"{self.path.name}_{len(self._summary.files)}.mcap"
        self._file = _McapFile(self.directory / name, self._compression, self.chunk_bytes)
        self._summary.files.append(FileStats(name))
        for topic in self._summary.topics.values():
            self._file.add_topic(topic)

    def close(self) -> BagSummary:
        """Finish the last file, write metadata.yaml and move the bag to its final path."""
        if self._closed:
            return self._summary
        if self._file is None:
            self._start_file()  # an empty bag still gets one valid .mcap file
        assert self._file is not None
        self._file.finish(self._summary)
        self._summary.write_metadata(self.directory)
        self.directory.rename(self.path)
        self._closed = True
        return self._summary

    def abort(self) -> None:
        """Stop writing and delete everything written so far."""
        if self._file is not None:
            self._file.stream.close()
        self._closed = True
        shutil.rmtree(self.directory, ignore_errors=True)

    def __enter__(self) -> BagWriter:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()


# --- recovery -----------------------------------------------------------------------------------------


@dataclass
class RecoveredFile:
    """What recovery did to one .mcap file."""

    path: str
    messages: int
    rebuilt: bool  # False: the file was already finished and is kept as is
    dropped_bytes: int  # bytes after the last complete record (the open chunk at the crash)


def _file_is_finished(path: Path) -> bool:
    try:
        with path.open("rb") as stream:
            return make_reader(stream).get_summary() is not None
    except (McapError, ValueError, OSError, EOFError):
        return False


def _stats_of_finished(path: Path, topics: dict[str, TopicInfo]) -> FileStats:
    with path.open("rb") as stream:
        summary = make_reader(stream).get_summary()
    assert summary is not None and summary.statistics is not None
    for channel in summary.channels.values():
        topics.setdefault(channel.topic, _topic_from_channel(channel, summary.schemas.get(channel.schema_id)))
    stats = summary.statistics
    return FileStats(
        path=path.name,
        message_count=stats.message_count,
        start_ns=stats.message_start_time,
        end_ns=stats.message_end_time,
        topic_counts={
            summary.channels[cid].topic: count for cid, count in stats.channel_message_counts.items()
        },
    )


def _complete_records(path: Path) -> Iterator[tuple[int, Any]]:
    """(end offset of the complete record it came from, record) of an unfinished file, until it breaks."""
    with path.open("rb") as stream:
        reader = StreamReader(stream, skip_magic=False)
        try:
            for record in reader.records:
                yield stream.tell(), record
                if isinstance(record, Footer):
                    return
        except (McapError, EOFError, ValueError, OSError):
            return  # truncated inside a record: everything before it was yielded


def _rebuild_file(source: Path, target: Path, topics: dict[str, TopicInfo]) -> tuple[FileStats, int]:
    """Copy every complete message of an unfinished ``source`` into a finished ``target``."""
    schemas: dict[int, Schema] = {}
    channel_topics: dict[int, str] = {}
    out = _McapFile(target, CompressionType.ZSTD, chunk_bytes=1 << 20)
    stats = FileStats(source.name)
    last_good = 8  # after the magic
    for end, record in _complete_records(source):
        if isinstance(record, Schema):
            schemas[record.id] = record
        elif isinstance(record, Channel):
            info = _topic_from_channel(record, schemas.get(record.schema_id))
            topics.setdefault(info.name, info)
            channel_topics[record.id] = record.topic
            if record.topic not in out.channel_ids:
                out.add_topic(topics[info.name])
        elif isinstance(record, Message):
            topic = channel_topics[record.channel_id]
            out.add_message(topic, record.data, record.log_time, record.publish_time, record.sequence)
            stats.add(topic, record.log_time)
        last_good = end
    summary = BagSummary(target, [stats], {t: topics[t] for t in out.channel_ids})
    out.finish(summary)
    return stats, source.stat().st_size - last_good


def recover_bag(path: Path | str) -> list[RecoveredFile]:
    """Turn the unfinished bag at ``path`` (or ``path.partial``) into a finished bag at ``path``.

    Finished .mcap files are kept; an unfinished one (no summary/footer, e.g. after SIGKILL) is rebuilt
    from every message up to its last complete chunk. metadata.yaml is written last.
    """
    path = Path(path)
    if path.name.endswith(PARTIAL_SUFFIX):
        path = path.with_name(path.name[: -len(PARTIAL_SUFFIX)])
    directory = partial_path(path)
    if not directory.is_dir():
        if (path / METADATA_FILE).is_file():
            raise BagError(path, "already a finished bag (it has metadata.yaml); nothing to recover")
        if not path.is_dir():
            raise BagError(path, f"neither {path} nor {directory} is a bag directory")
        directory = path  # a bag directory that lost its metadata.yaml
    files = sorted(directory.glob("*.mcap"), key=lambda p: _file_index(p))
    if not files:
        raise BagError(path, f"no .mcap files in {directory}")
    topics: dict[str, TopicInfo] = {}
    all_stats: list[FileStats] = []
    report: list[RecoveredFile] = []
    for file in files:
        if _file_is_finished(file):
            stats = _stats_of_finished(file, topics)
            report.append(RecoveredFile(file.name, stats.message_count, False, 0))
        else:
            rebuilt = file.with_name(file.name + ".recovered")
            stats, dropped = _rebuild_file(file, rebuilt, topics)
            rebuilt.replace(file)
            report.append(RecoveredFile(file.name, stats.message_count, True, dropped))
        all_stats.append(stats)
    BagSummary(path, all_stats, topics).write_metadata(directory)
    if directory != path:
        directory.rename(path)
    return report


def _file_index(path: Path) -> tuple[int, str]:
    match = re.search(r"_(\d+)\.mcap$", path.name)
    return (int(match.group(1)) if match else -1, path.name)


# --- reading ------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class RawMessage:
    """One serialized message read from a bag."""

    topic: str
    type: str
    log_time_ns: int
    data: bytes


class BagReader:
    """Reads a rosbag2 bag (MCAP or sqlite3 storage, one or more files) without rclpy."""

    def __init__(self, path: Path | str) -> None:
        self.path = Path(path)
        if not (self.path / METADATA_FILE).is_file():
            hint = (
                f" (an unfinished recording is at {partial_path(self.path)}: run `playseg bag recover`)"
                if partial_path(self.path).is_dir()
                else ""
            )
            raise BagError(self.path, f"not a rosbag2 bag: no {METADATA_FILE}{hint}")
        self._reader = Rosbag2Reader(self.path)
        try:
            self.metadata: dict[str, Any] = yaml.safe_load((self.path / METADATA_FILE).read_text())[
                "rosbag2_bagfile_information"
            ]
            self._reader.open()
        except (ReaderError, yaml.YAMLError, KeyError, TypeError) as error:
            raise BagError(self.path, f"cannot open: {error!r}") from error

    @property
    def topics(self) -> dict[str, str]:
        """Topic name -> message type."""
        return {c.topic: c.msgtype for c in self._reader.connections}

    @property
    def message_count(self) -> int:
        return self._reader.message_count

    @property
    def files(self) -> list[Path]:
        return [self.path / p for p in self.metadata["relative_file_paths"]]

    def topic_hash(self, topic: str) -> str:
        return next((c.digest for c in self._reader.connections if c.topic == topic), "")

    def messages(self, topics: Sequence[str] | None = None) -> Iterator[RawMessage]:
        """Messages of ``topics`` (all when None) file by file, in time order within a file."""
        connections = [c for c in self._reader.connections if topics is None or c.topic in topics]
        if not connections:
            return
        try:
            for connection, timestamp, data in self._reader.messages(connections=connections):
                yield RawMessage(connection.topic, connection.msgtype, timestamp, data)
        except ReaderError as error:
            raise BagError(self.path, f"cannot read: {error}") from error

    def close(self) -> None:
        self._reader.close()

    def __enter__(self) -> BagReader:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()


def bag_info_text(path: Path | str) -> str:
    """A human-readable description of a bag (for ``playseg bag info``)."""
    with BagReader(path) as reader:
        meta = reader.metadata
        lines = [
            f"bag:        {reader.path}",
            f"storage:    {meta['storage_identifier']} (metadata version {meta['version']}, "
            f"ros_distro {meta.get('ros_distro', '?')})",
            f"start:      {meta['starting_time']['nanoseconds_since_epoch'] / 1e9:.3f} s since epoch",
            f"duration:   {meta['duration']['nanoseconds'] / 1e9:.3f} s",
            f"messages:   {meta['message_count']}",
            "files:",
        ]
        for file in reader.files:
            size = file.stat().st_size if file.exists() else 0
            lines.append(f"  {file.name}  {size / 1e6:.2f} MB{_chunk_compression(file)}")
        lines.append("topics:")
        for entry in meta["topics_with_message_count"]:
            topic = entry["topic_metadata"]
            lines.append(f"  {topic['name']}  {topic['type']}  {entry['message_count']} messages")
    return "\n".join(lines)


def _chunk_compression(file: Path) -> str:
    if file.suffix != ".mcap":
        return ""
    with file.open("rb") as stream:
        summary = make_reader(stream).get_summary()
    if summary is None:
        return ""
    kinds = sorted({index.compression or "none" for index in summary.chunk_indexes})
    return f", {len(summary.chunk_indexes)} chunks, compression {'/'.join(kinds) or 'none'}"
