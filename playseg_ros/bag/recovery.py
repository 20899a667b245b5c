"""Recovery of a bag whose writing did not finish (SIGKILL, power loss, a full disk) or whose files were cut
short later (an interrupted copy): every complete message is kept.

`recover_bag` accepts ``<path>.partial`` (a writer died) and a finished-looking ``<path>`` whose .mcap
files are truncated or whose metadata.yaml is missing or does not match its files. Finished files are
kept; an unfinished one is rebuilt from its complete records (mcap_scan.py), so whatever offset a file
was cut at, recovery keeps every message before the cut and never fails on the cut itself. A file whose
scan stopped at damaged bytes rather than at a cut may hold messages past them: its original is kept
beside the rebuilt one (``<name>.mcap.damaged``), and a file that is not MCAP at all (no magic at its
start) is refused, never rebuilt into an empty one. metadata.yaml
is written last, keeping the bag's custom_data from its old metadata.yaml or, failing that, from a
metadata record inside one of its files. A bag whose writer is still alive (its lock is held) is refused.
"""

from __future__ import annotations

import contextlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml
from mcap.reader import make_reader
from mcap.records import Channel, DataEnd, Message, Metadata, Schema
from mcap.writer import CompressionType

from playseg_ros.bag.errors import BagError
from playseg_ros.bag.lock import BagLock
from playseg_ros.bag.mcap_scan import MAGIC, RecordScan, mcap_files
from playseg_ros.bag.schema import (
    METADATA_FILE,
    PARTIAL_SUFFIX,
    BagSummary,
    FileStats,
    TopicInfo,
    topic_from_channel,
)
from playseg_ros.bag.writer import CUSTOM_DATA_RECORD, McapFile, partial_path

TEMP_SUFFIX = ".recovered"
DAMAGED_SUFFIX = ".damaged"


@dataclass
class RecoveredFile:
    """What recovery did to one .mcap file."""

    path: str
    messages: int
    rebuilt: bool  # False: the file was already finished and is kept as is
    dropped_bytes: int  # bytes after the last complete record (the open chunk at the crash)
    kept_original: str | None = None  # the damaged original, kept beside the rebuilt file


def recover_bag(path: Path | str) -> list[RecoveredFile]:
    """Turn the unfinished or truncated bag at ``path`` (or ``path.partial``) into a finished bag at
    ``path``; a BagError when there is nothing to recover, when the bag is still being written, or when
    a rebuilt file cannot be written (then nothing is changed and no temporary file is left)."""
    path = Path(path)
    if path.name.endswith(PARTIAL_SUFFIX):
        path = path.with_name(path.name[: -len(PARTIAL_SUFFIX)])
    directory = partial_path(path)
    if directory.is_dir():
        if path.exists():
            raise BagError(path, f"both {path} and {directory} exist: move one of them away first")
    elif path.is_dir():
        directory = path  # a finished-looking bag: recover it in place if its files need it
    else:
        raise BagError(path, f"neither {path} nor {directory} is a bag directory")
    lock = BagLock.acquire(path, directory)
    try:
        return _recover_locked(path, directory)
    except OSError as error:  # e.g. metadata.yaml or the rename on a full or read-only disk
        raise BagError(path, f"cannot recover: {error.strerror}: {error.filename}") from None
    finally:
        with contextlib.suppress(OSError):
            lock.moved_to(path if not directory.exists() else directory)
            lock.release()


def _recover_locked(path: Path, directory: Path) -> list[RecoveredFile]:
    for stale in directory.glob(f"*{TEMP_SUFFIX}"):  # left by a recovery that was killed half-way
        stale.unlink()
    files = mcap_files(directory)
    old = _old_metadata(directory)
    if not files:
        storage = (old or {}).get("storage_identifier", "")
        kind = (
            f" (storage {storage!r}; only MCAP bags can be recovered)" if storage not in ("", "mcap") else ""
        )
        raise BagError(path, f"no .mcap files in {directory}{kind}")
    finished = {file: _finished_stats(file) for file in files}
    if directory == path and old is not None and _metadata_matches(old, finished):
        raise BagError(
            path, "already a finished bag (its files and metadata.yaml are complete); nothing to recover"
        )
    topics: dict[str, TopicInfo] = {}
    custom_data = _custom_data_of(old)
    all_stats: list[FileStats] = []
    report: list[RecoveredFile] = []
    for file in files:
        stats = finished[file]
        if stats is not None:
            _collect_finished(file, topics)
            report.append(RecoveredFile(file.name, stats.message_count, False, 0))
            custom_data = custom_data if custom_data is not None else _custom_data_in_summary(file)
        else:
            stats, dropped, found, kept = _rebuild(path, file, topics, custom_data)
            report.append(RecoveredFile(file.name, stats.message_count, True, dropped, kept))
            custom_data = custom_data if custom_data is not None else found
        all_stats.append(stats)
    BagSummary(path, all_stats, topics, custom_data or {}).write_metadata(directory)
    if directory != path:
        directory.rename(path)
    return report


# --- finished files -----------------------------------------------------------------------------------


def _finished_stats(path: Path) -> FileStats | None:
    """The statistics of a finished file (summary and statistics readable), None for an unfinished one."""
    try:
        with path.open("rb") as stream:
            summary = make_reader(stream).get_summary()
        if summary is None or summary.statistics is None:
            return None
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
    except Exception:  # noqa: BLE001 -- an unreadable summary (any parser error) means: rebuild the file
        return None


def _collect_finished(path: Path, topics: dict[str, TopicInfo]) -> None:
    with path.open("rb") as stream:
        summary = make_reader(stream).get_summary()
    assert summary is not None  # checked by _finished_stats
    for channel in summary.channels.values():
        topics.setdefault(channel.topic, topic_from_channel(channel, summary.schemas.get(channel.schema_id)))


def _custom_data_in_summary(path: Path) -> dict[str, str] | None:
    """custom_data from a finished file's metadata records (ours, or rosbag2's serialized metadata)."""
    with contextlib.suppress(Exception), path.open("rb") as stream:
        found = [_custom_data_of_record(r) for r in make_reader(stream).iter_metadata()]
        return next((c for c in found if c is not None), None)
    return None


# --- unfinished files ---------------------------------------------------------------------------------


def _rebuild(
    bag: Path, source: Path, topics: dict[str, TopicInfo], custom_data: dict[str, str] | None
) -> tuple[FileStats, int, dict[str, str] | None, str | None]:
    """Copy every complete message of an unfinished ``source`` into a finished file that replaces it.

    Returns its statistics, the bytes dropped after the last complete record, the custom_data found in
    its metadata records (None if none) and the name the original is kept under when damaged bytes, not
    a cut, ended the scan (None: replaced). The new file carries ``custom_data`` (what is known of the
    bag so far; when None, what the file itself holds). The copy goes to a temporary file first: if
    writing fails (a full disk), the source is untouched and the temporary file removed.
    """
    with source.open("rb") as stream:
        head = stream.read(len(MAGIC))
    if len(head) == len(MAGIC) and head != MAGIC:
        raise BagError(
            bag, "not an MCAP file (no MCAP magic at its start): nothing recovered, the file is left as it is",
            file=source.name,
        )  # fmt: skip
    target = source.with_name(source.name + TEMP_SUFFIX)
    kept = None
    try:
        stats, dropped, found, damaged = _copy_complete(source, target, topics, custom_data)
        if damaged:
            kept = source.name + DAMAGED_SUFFIX
            source.replace(source.with_name(kept))
        target.replace(source)
    except OSError as error:
        raise BagError(bag, f"cannot write the recovered file: {error}", file=source.name) from None
    finally:
        target.unlink(missing_ok=True)
    return stats, dropped, found, kept


def _copy_complete(
    source: Path, target: Path, topics: dict[str, TopicInfo], known: dict[str, str] | None
) -> tuple[FileStats, int, dict[str, str] | None, bool]:
    """`_rebuild`'s copy; the last value says whether damaged bytes (not a cut) ended the scan."""
    schemas: dict[int, Schema] = {}
    channel_topics: dict[int, str] = {}
    found: dict[str, str] | None = None
    stats = FileStats(source.name)
    scan = RecordScan(source)
    out: McapFile | None = None
    data_complete = False

    def opened() -> McapFile:
        # Opened at the first schema, after the leading metadata record, so that it can carry custom_data.
        nonlocal out
        if out is None:
            out = McapFile(target, CompressionType.ZSTD, 1 << 20, known if known is not None else found)
        return out

    try:
        for _, record in scan:
            if isinstance(record, DataEnd):
                data_complete = True  # what follows (the summary) repeats what came before
                break
            if isinstance(record, Metadata):
                found = found if found is not None else _custom_data_of_record(record)
            elif isinstance(record, Schema):
                schemas.setdefault(record.id, record)
            elif isinstance(record, Channel) and record.id not in channel_topics:
                info = _topic_of(record, schemas.get(record.schema_id))
                if info is None:
                    continue  # its schema was lost or its metadata is unreadable: its messages cannot be typed
                topics.setdefault(info.name, info)
                channel_topics[record.id] = info.name
                if info.name not in opened().channel_ids:
                    opened().add_topic(topics[info.name])
            elif isinstance(record, Message) and record.channel_id in channel_topics:
                topic = channel_topics[record.channel_id]
                opened().add_message(
                    topic, record.data, record.log_time, record.publish_time, record.sequence
                )
                stats.add(topic, record.log_time)
        custom_data = known if known is not None else found
        file = opened()
        file.finish(BagSummary(target, [stats], {t: topics[t] for t in file.channel_ids}, custom_data or {}))
    except BaseException:
        if out is not None:
            out.close_unfinished()
        raise
    dropped = 0 if data_complete or scan.problem is None else source.stat().st_size - scan.end
    return stats, dropped, found, not data_complete and scan.damaged


def _topic_of(channel: Channel, schema: Schema | None) -> TopicInfo | None:
    """The channel's topic, None when it cannot be typed (no schema; channel metadata not readable)."""
    try:
        info = topic_from_channel(channel, schema)
    except (yaml.YAMLError, ValueError, TypeError, AttributeError):  # metadata outside a CRC'd chunk
        return None
    return info if info.type else None


# --- metadata -----------------------------------------------------------------------------------------


def _old_metadata(directory: Path) -> dict[str, Any] | None:
    """The bag's metadata.yaml as a mapping, None when missing or unreadable."""
    try:
        info = yaml.safe_load((directory / METADATA_FILE).read_text())["rosbag2_bagfile_information"]
    except (OSError, yaml.YAMLError, KeyError, TypeError):
        return None
    return info if isinstance(info, dict) else None


def _metadata_matches(old: dict[str, Any], finished: dict[Path, FileStats | None]) -> bool:
    """Whether metadata.yaml describes exactly these files, all finished, with their message counts."""
    if any(stats is None for stats in finished.values()):
        return False
    try:
        listed = sorted(Path(p).name for p in old["relative_file_paths"])
        count = int(old["message_count"])
    except (KeyError, TypeError, ValueError):
        return False
    present = sorted(file.name for file in finished)
    return listed == present and count == sum(s.message_count for s in finished.values() if s is not None)


def _custom_data_of(old: dict[str, Any] | None) -> dict[str, str] | None:
    if old is None or not isinstance(old.get("custom_data"), dict):
        return None
    return {str(k): str(v) for k, v in old["custom_data"].items()}


def _custom_data_of_record(record: Metadata) -> dict[str, str] | None:
    """custom_data carried by a metadata record: ours at a file's start, or rosbag2's at its end."""
    if record.name == CUSTOM_DATA_RECORD:
        return dict(record.metadata)
    if record.name == "rosbag2" and "serialized_metadata" in record.metadata:
        with contextlib.suppress(yaml.YAMLError, KeyError, TypeError, AttributeError):
            info = yaml.safe_load(record.metadata["serialized_metadata"])
            info = info.get("rosbag2_bagfile_information", info)
            if isinstance(info.get("custom_data"), dict):
                return {str(k): str(v) for k, v in info["custom_data"].items()}
    return None
