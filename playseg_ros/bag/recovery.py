"""Recovery of a bag whose writer died (SIGKILL, power loss): every message up to the last complete chunk.

A writer killed mid-way leaves ``<path>.partial`` behind; `recover_bag` turns it into a finished bag.
"""

from __future__ import annotations

import re
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from mcap.exceptions import McapError
from mcap.reader import make_reader
from mcap.records import Channel, Footer, Message, Schema
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType

from playseg_ros.bag.errors import BagError
from playseg_ros.bag.schema import (
    METADATA_FILE,
    PARTIAL_SUFFIX,
    BagSummary,
    FileStats,
    TopicInfo,
    topic_from_channel,
)
from playseg_ros.bag.writer import McapFile, partial_path


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
        topics.setdefault(channel.topic, topic_from_channel(channel, summary.schemas.get(channel.schema_id)))
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
    out = McapFile(target, CompressionType.ZSTD, chunk_bytes=1 << 20)
    stats = FileStats(source.name)
    last_good = 8  # after the magic
    for end, record in _complete_records(source):
        if isinstance(record, Schema):
            schemas[record.id] = record
        elif isinstance(record, Channel):
            info = topic_from_channel(record, schemas.get(record.schema_id))
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
