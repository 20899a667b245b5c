"""Reading rosbag2 bags (MCAP or sqlite3 storage, one or more files) without rclpy, through rosbags."""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml
from rosbags.rosbag2 import Reader as Rosbag2Reader
from rosbags.rosbag2 import ReaderError

from playseg_ros.bag.errors import BagError
from playseg_ros.bag.schema import METADATA_FILE
from playseg_ros.bag.writer import partial_path


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
    def custom_data(self) -> dict[str, str]:
        """metadata.yaml's ``custom_data`` (empty when the bag has none)."""
        return {str(k): str(v) for k, v in (self.metadata.get("custom_data") or {}).items()}

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
