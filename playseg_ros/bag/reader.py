"""Reading rosbag2 bags (MCAP or sqlite3 storage, one or more files) without rclpy, through rosbags.

Whatever goes wrong while opening or reading (a truncated file, a corrupted chunk, a damaged database)
comes out as one `BagError` naming the bag and the file and, where the damage can be located, the byte
offset and topic, never as the storage library's own exception.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from rosbags.interfaces import Connection
from rosbags.rosbag2 import Reader as Rosbag2Reader

from playseg_core.yaml_io import YamlFileError, load_yaml
from playseg_ros.bag.errors import BagError
from playseg_ros.bag.mcap_scan import damage_of
from playseg_ros.bag.schema import METADATA_FILE
from playseg_ros.bag.writer import partial_path

try:  # the zstd module rosbags uses for per-message compression
    from compression import zstd  # type: ignore[import-not-found]
except ImportError:
    from backports import zstd


@dataclass(frozen=True)
class RawMessage:
    """One serialized message read from a bag."""

    topic: str
    type: str
    log_time_ns: int
    data: bytes


def _one_line(error: BaseException) -> str:
    return f"{type(error).__name__}: {error}"


class BagReader:
    """Reads a rosbag2 bag (MCAP or sqlite3 storage, one or more files) without rclpy."""

    def __init__(self, path: Path | str) -> None:
        self.path = Path(path)
        if not self.path.is_dir() and not partial_path(self.path).is_dir():
            raise BagError(self.path, "no such bag directory")
        if not (self.path / METADATA_FILE).is_file():
            hint = (
                f" (an unfinished recording is at {partial_path(self.path)}: run `playseg bag recover`)"
                if partial_path(self.path).is_dir()
                else ""
            )
            raise BagError(self.path, f"not a rosbag2 bag: no {METADATA_FILE}{hint}")
        try:
            loaded = load_yaml(self.path / METADATA_FILE, METADATA_FILE)
        except YamlFileError as error:  # too large, binary, an alias bomb, a syntax error: the loader says
            entry = f", key {error.key!r}" if error.key else ""
            raise BagError(self.path, f"cannot read {METADATA_FILE}{entry}: {error.detail}") from None
        try:
            if not isinstance(loaded, dict) or not isinstance(
                loaded.get("rosbag2_bagfile_information"), dict
            ):
                raise BagError(self.path, f"{METADATA_FILE} holds no rosbag2_bagfile_information mapping")
            self.metadata: dict[str, Any] = loaded["rosbag2_bagfile_information"]
            self._files = [self.path / Path(p).name for p in self.metadata["relative_file_paths"]]
        except (KeyError, TypeError) as error:
            raise BagError(self.path, f"cannot read {METADATA_FILE}: {_one_line(error)}") from None
        try:
            self._reader = Rosbag2Reader(self.path)
            self._reader.open()
        except Exception as error:  # noqa: BLE001 -- a damaged file can make rosbags raise anything
            raise self._located(error, None) from None

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
    def start_time(self) -> int:
        """The bag's first message time in nanoseconds (from metadata.yaml), as `playseg convert` counts
        a bag's times from it."""
        return int(self._reader.start_time)

    @property
    def files(self) -> list[Path]:
        return list(self._files)

    def topic_hash(self, topic: str) -> str:
        return next((c.digest for c in self._reader.connections if c.topic == topic), "")

    def messages(self, topics: Sequence[str] | None = None) -> Iterator[RawMessage]:
        """Messages of ``topics`` (all when None) file by file, in time order within a file.

        A file that turns out damaged ends the iteration with a BagError after its last good message.
        """
        wanted = [c for c in self._reader.connections if topics is None or c.topic in topics]
        if not wanted:
            return
        compressed = self._reader.compression_mode == "message"
        # rosbags' own loop over the files (its directory reader's storages, one per file, in order),
        # kept here so that an error names the file it came from.
        storages = self._reader.storage.storages  # type: ignore[attr-defined]
        for file, storage in zip(self.files, storages, strict=True):
            by_id = _matching_connections(storage.connections, wanted)
            if not by_id:
                continue
            found = storage.messages([c for c in storage.connections if c.id in by_id])
            count = 0
            while True:
                try:
                    connection, timestamp, data = next(found)
                    if compressed:
                        data = zstd.decompress(data)
                except StopIteration:
                    break
                except Exception as error:  # noqa: BLE001 -- a damaged file can make rosbags raise anything
                    raise self._located(error, file, count) from None
                count += 1
                target = by_id[connection.id]
                yield RawMessage(target.topic, target.msgtype, timestamp, data)

    def _located(self, error: Exception, file: Path | None, read: int | None = None) -> BagError:
        """A BagError for ``error``, naming the damaged file (found by checking each file when the error
        came from opening the bag) and, where it can be located, the offset and topic."""
        candidates = [file] if file is not None else self.files
        after = f" (after {read} good messages of this file)" if read else ""
        for candidate in candidates:
            detail, topic = damage_of(candidate) if candidate.suffix == ".mcap" else ("", None)
            if not detail and not candidate.exists():
                detail = "file is missing"
            if detail:
                return BagError(self.path, f"{detail}{after}", topic, file=candidate.name)
        name = file.name if file is not None else None
        return BagError(self.path, f"cannot read: {_one_line(error)}{after}", file=name)

    def close(self) -> None:
        self._reader.close()

    def __enter__(self) -> BagReader:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()


def _matching_connections(
    in_file: Sequence[Connection], wanted: Sequence[Connection]
) -> dict[int, Connection]:
    """A file's connection id -> the bag-level connection it belongs to (as rosbags matches them)."""
    matches = {}
    for connection in in_file:
        for target in wanted:
            if (
                target.topic == connection.topic
                and target.msgtype == connection.msgtype
                and target.ext == connection.ext
                and (not connection.digest or not target.digest or target.digest == connection.digest)
            ):
                matches[connection.id] = target
                break
    return matches
