"""Writing rosbag2-compatible MCAP bags from serialized messages, without rclpy.

A bag is a directory holding ``metadata.yaml`` and one or more ``<bag name>_<i>.mcap`` files, as
rosbag2 writes them: MCAP profile ``ros2``, schemas in ``ros2msg`` encoding, ``cdr`` messages, channel
metadata ``offered_qos_profiles`` and ``topic_type_hash``, a ``rosbag2`` metadata record per file and
zstd-compressed chunks.

While a bag is being written it lives in ``<path>.partial`` and is renamed to ``<path>`` when closed, so
an interrupted write never leaves something that looks like a finished bag (recovery.py finishes one).
The writer holds the directory's lock (lock.py) until then, so recovery cannot finish a bag still being
written. A bag with ``custom_data`` also carries it in a ``playseg.custom_data`` metadata record at the
start of every file, so that recovery can restore it from any file that survived.
"""

from __future__ import annotations

import contextlib
import shutil
from pathlib import Path
from types import TracebackType

import yaml
from mcap.writer import CompressionType, Writer

from playseg_core.errors import PlaysegError
from playseg_ros.bag.errors import BagError
from playseg_ros.bag.lock import BagLock, holder, is_locked
from playseg_ros.bag.schema import PARTIAL_SUFFIX, ROS_DISTRO, BagSummary, FileStats, TopicInfo


def _add_rosbag2_metadata_record(writer: Writer, summary: BagSummary) -> None:
    serialized = yaml.safe_dump(summary.bagfile_information(), sort_keys=False)
    writer.add_metadata("rosbag2", {"serialized_metadata": serialized, "ros_distro": ROS_DISTRO})


CUSTOM_DATA_RECORD = "playseg.custom_data"
"""Name of the MCAP metadata record that repeats metadata.yaml's custom_data at the start of each file."""


def partial_path(path: Path) -> Path:
    """Where a bag lives while it is being written."""
    return path.with_name(path.name + PARTIAL_SUFFIX)


class McapFile:
    """One open .mcap file of a bag."""

    def __init__(
        self,
        path: Path,
        compression: CompressionType,
        chunk_bytes: int,
        custom_data: dict[str, str] | None = None,
    ) -> None:
        self.stream = path.open("wb")
        # We close chunks ourselves (see add_message), so the library never closes one on its own.
        self.writer = Writer(self.stream, chunk_size=2**62, compression=compression)
        self.chunk_bytes = chunk_bytes
        self.writer.start(profile="ros2", library="playseg bag_io")
        if custom_data:
            self.writer.add_metadata(CUSTOM_DATA_RECORD, dict(custom_data))
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

    def close_unfinished(self) -> None:
        """Close the stream without finishing the file (what was flushed stays recoverable)."""
        with contextlib.suppress(OSError):  # flushing the buffer fails again on a full disk
            self.stream.close()


class BagWriter:
    """Writes a rosbag2 MCAP bag from serialized messages.

    ``max_file_bytes`` / ``max_file_duration_ns`` (0: no limit) start a new .mcap file when the current
    one would grow past them. ``chunk_bytes`` bounds a chunk (and what a crash can lose).
    ``custom_data`` goes to metadata.yaml's ``custom_data`` (strings only, as rosbag2 stores it). Use as
    a context manager: leaving it by an exception (or a failing close) removes everything written.
    While open, the writer holds the bag directory's lock; `close`, `abort` and `abandon` release it.
    """

    def __init__(
        self,
        path: Path | str,
        *,
        max_file_bytes: int = 0,
        max_file_duration_ns: int = 0,
        chunk_bytes: int = 1 << 20,
        compression: str = "zstd",
        custom_data: dict[str, str] | None = None,
    ) -> None:
        if compression not in ("zstd", "none"):
            raise PlaysegError(f"compression must be 'zstd' or 'none', got {compression!r}")
        self.path = Path(path)
        self.directory = partial_path(self.path)
        for existing in (self.path, self.directory):
            if existing.exists():
                raise FileExistsError(f"bag {str(self.path)!r}: {existing} already exists{_why(existing)}")
        self.directory.mkdir(parents=True)
        self._lock = BagLock.acquire(self.path, self.directory)
        self.max_file_bytes = max_file_bytes
        self.max_file_duration_ns = max_file_duration_ns
        self.chunk_bytes = chunk_bytes
        self._compression = CompressionType.ZSTD if compression == "zstd" else CompressionType.NONE
        self._summary = BagSummary(
            self.path, [], {}, {str(k): str(v) for k, v in (custom_data or {}).items()}
        )
        self._sequence: dict[str, int] = {}
        self._file: McapFile | None = None
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
        self._file = McapFile(
            self.directory / name, self._compression, self.chunk_bytes, self._summary.custom_data
        )
        self._summary.files.append(FileStats(name))
        for topic in self._summary.topics.values():
            self._file.add_topic(topic)

    def close(self) -> BagSummary:
        """Finish the last file, write metadata.yaml and move the bag to its final path.

        If this fails (a full disk), the bag stays in ``<path>.partial`` and the writer stays open: call
        `abandon` to keep what was flushed for `recover_bag`, or `abort` to delete it.
        """
        if self._closed:
            return self._summary
        if self._file is None:
            self._start_file()  # an empty bag still gets one valid .mcap file
        assert self._file is not None
        self._file.finish(self._summary)
        self._summary.write_metadata(self.directory)
        # Renamed while still locked: recovery never sees an unlocked half-finished directory.
        self.directory.rename(self.path)
        self._lock.moved_to(self.path)
        self._closed = True
        self._lock.release()
        return self._summary

    def abandon(self) -> None:
        """Stop writing, keep everything flushed so far in ``<path>.partial`` for `recover_bag`."""
        if self._file is not None:
            self._file.close_unfinished()
        self._closed = True
        self._lock.release()

    def abort(self) -> None:
        """Stop writing and delete everything written so far."""
        if self._file is not None:
            self._file.close_unfinished()
        self._closed = True
        self._lock.release()
        shutil.rmtree(self.directory, ignore_errors=True)

    def __enter__(self) -> BagWriter:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        if exc_type is not None:
            self.abort()
            return
        try:
            self.close()
        except BaseException:
            self.abort()  # a conversion that could not finish leaves nothing half-written behind
            raise


def _why(existing: Path) -> str:
    """Why an existing ``<path>.partial`` is there, for the refusal to write over it."""
    if not existing.name.endswith(PARTIAL_SUFFIX):
        return ""
    if is_locked(existing):
        return f" (a bag being written by {holder(existing) or 'another process'})"
    return " (an unfinished bag: run `playseg bag recover`)"
