"""Recovery of a bag whose writing did not finish (SIGKILL, power loss, a full disk) or whose files were cut
short later (an interrupted copy): every complete message is kept.

`recover_bag` accepts ``<path>.partial`` (a writer died) and a finished-looking ``<path>`` whose .mcap
files are truncated or whose metadata.yaml is missing or does not match its files. Finished files are
kept; an unfinished one is rebuilt from its complete records (mcap_scan.py), so whatever offset a file
was cut at, recovery keeps every message before the cut and never fails on the cut itself. A damaged
record (a flipped bit in a length, garbage over a chunk) is skipped: the scan resynchronises at the next
intact chunk, so complete messages after it are kept too. A file that is not MCAP at all (no magic at its
start) is refused, never rebuilt into an empty one. metadata.yaml is written last, keeping the bag's
custom_data from its old metadata.yaml or, failing that, from a metadata record inside one of its files.
A bag whose writer is still alive (its lock is held) is refused.

Recovery never hides a loss. Losing the open chunk at a cut (a clean tail) is what a crash costs; anything
more (damaged bytes skipped or ending a file, a file metadata.yaml lists that is gone) is a *loss*: each
`RecoveredFile` says what it cost (bytes; messages where the old metadata.yaml counted them), the damaged
original is kept beside the rebuilt file (``<name>.mcap.damaged``), the old metadata.yaml is kept as
``metadata.yaml.orig``, and the new metadata.yaml carries a note (custom_data ``LOSS_KEY``) that later
recoveries keep and `playseg bag info` prints.
"""

from __future__ import annotations

import contextlib
import shutil
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml
from mcap.reader import make_reader
from mcap.records import Channel, DataEnd, Message, Metadata, Schema
from mcap.writer import CompressionType

from playseg_core.yaml_io import YamlFileError, load_yaml, parse_yaml
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
ORIGINAL_METADATA = METADATA_FILE + ".orig"
LOSS_KEY = "playseg.recovery_losses"
"""custom_data key of the note a lossy recovery leaves in metadata.yaml (one line per recovery)."""


@dataclass
class RecoveredFile:
    """What recovery did to one .mcap file (or found missing)."""

    path: str
    messages: int
    rebuilt: bool  # False: the file was already finished and is kept as is (or is missing)
    dropped_bytes: int  # bytes after the last complete record (the open chunk at the crash, or damage)
    kept_original: str | None = None  # the damaged original, kept beside the rebuilt file
    skipped_bytes: int = 0  # damaged bytes passed over inside the file (complete records after them kept)
    damage: list[str] = field(default_factory=list)  # what was damaged, where
    expected_messages: int | None = None  # what the old metadata.yaml said the file held (None: unknown)
    missing: bool = False  # listed by the old metadata.yaml, not on disk
    untyped_messages: int = 0  # complete messages dropped: their channel was defined in damaged bytes

    @property
    def lost_messages(self) -> int | None:
        """Messages the old metadata.yaml counted that are not kept (None: no count to compare with)."""
        if self.expected_messages is None:
            return None
        return max(0, self.expected_messages - self.messages)

    @property
    def lossy(self) -> bool:
        """Lost more than a crash's clean tail: damaged bytes, the whole file, or messages the old
        metadata.yaml counted (a finished file cut short later, as by an interrupted copy)."""
        return self.missing or bool(self.damage) or bool(self.lost_messages)

    def summary(self) -> str:
        """One line: what was kept and what could not be."""
        if self.missing:
            counted = "" if self.expected_messages is None else f" ({self.expected_messages} messages)"
            return f"{self.path}: MISSING: listed in metadata.yaml{counted}, not on disk; nothing of it kept"
        if not self.rebuilt:
            return f"{self.path}: {self.messages} messages (finished, kept)"
        parts = [f"rebuilt, {self.dropped_bytes} trailing bytes dropped"]
        if self.damage:
            parts.append(
                f"damaged in {len(self.damage)} place(s), {self.skipped_bytes} damaged bytes skipped"
            )
        lost = self.lost_messages
        if lost:
            parts.append(f"{lost} of the {self.expected_messages} messages metadata.yaml counted lost")
        if self.kept_original:
            parts.append(f"original kept as {self.kept_original}")
        return f"{self.path}: {self.messages} messages ({'; '.join(parts)})"

    def loss(self) -> str:
        """What could not be kept, for the metadata note ('' when only a clean tail was dropped)."""
        if not self.lossy:
            return ""
        if self.missing:
            counted = "" if self.expected_messages is None else f", {self.expected_messages} messages"
            return f"{self.path} missing{counted}"
        lost = "" if self.lost_messages is None else f", {self.lost_messages} messages lost"
        if self.untyped_messages:
            lost += f", {self.untyped_messages} complete messages without their channel dropped"
        how = "damaged" if self.damage else "cut short"
        return f"{self.path} {how} ({self.skipped_bytes + self.dropped_bytes} bytes dropped{lost})"


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
    # the files a bag had: its metadata.yaml's list, or the one a lossy recovery kept (metadata.yaml lost)
    counted = _listed_counts(old if old is not None else _old_metadata(directory, ORIGINAL_METADATA))
    for file in files:
        stats = finished[file]
        if stats is not None:
            _collect_finished(file, topics)
            report.append(RecoveredFile(file.name, stats.message_count, False, 0))
            custom_data = custom_data if custom_data is not None else _custom_data_in_summary(file)
        else:
            stats, dropped, found, kept, scan, untyped = _rebuild(path, file, topics, custom_data)
            damage = [f"bytes {a}-{b}: {why}" for a, b, why in scan.skipped]
            if scan.ended_damaged:
                damage.append(f"from byte {scan.end} to the end: {scan.problem}")
            if untyped:
                damage.append(
                    f"{untyped} complete messages dropped: their channel was defined in damaged bytes"
                )
            report.append(
                RecoveredFile(
                    file.name, stats.message_count, True, dropped, kept, scan.skipped_bytes, damage,
                    counted.get(file.name), untyped_messages=untyped,
                )
            )  # fmt: skip
            custom_data = custom_data if custom_data is not None else found
        all_stats.append(stats)
    present = {file.name for file in files}
    report += [
        RecoveredFile(name, 0, False, 0, expected_messages=count, missing=True)
        for name, count in counted.items()
        if name not in present
    ]
    losses = [item.loss() for item in report if item.lossy]
    custom_data = dict(custom_data or {})
    if losses:
        # the loss stays visible after this metadata.yaml replaces the one that listed it
        if (directory / METADATA_FILE).is_file() and not (directory / ORIGINAL_METADATA).exists():
            shutil.copy2(directory / METADATA_FILE, directory / ORIGINAL_METADATA)
        note = "bag recover: " + "; ".join(losses)
        earlier = custom_data.get(LOSS_KEY)
        custom_data[LOSS_KEY] = f"{earlier} | {note}" if earlier and note not in earlier else note
    BagSummary(path, all_stats, topics, custom_data).write_metadata(directory)
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
) -> tuple[FileStats, int, dict[str, str] | None, str | None, RecordScan, int]:
    """Copy every complete message of an unfinished ``source`` into a finished file that replaces it.

    Returns its statistics, the bytes dropped after the last complete record, the custom_data found in
    its metadata records (None if none), the name the original is kept under when damaged bytes were met
    (skipped, or ending the scan; None: replaced), the scan (what it skipped) and the complete messages
    dropped for want of their channel (defined in damaged bytes). The new file carries ``custom_data`` (what is known of the
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
        stats, dropped, found, scan, untyped = _copy_complete(source, target, topics, custom_data)
        if scan.damaged or untyped:
            kept = source.name + DAMAGED_SUFFIX
            source.replace(source.with_name(kept))
        target.replace(source)
    except OSError as error:
        raise BagError(bag, f"cannot write the recovered file: {error}", file=source.name) from None
    finally:
        target.unlink(missing_ok=True)
    return stats, dropped, found, kept, scan, untyped


def _copy_complete(
    source: Path, target: Path, topics: dict[str, TopicInfo], known: dict[str, str] | None
) -> tuple[FileStats, int, dict[str, str] | None, RecordScan, int]:
    """`_rebuild`'s copy; then the scan (whether damaged bytes were met, what it skipped) and the number of
    complete messages dropped because their channel could not be typed."""
    schemas: dict[int, Schema] = {}
    channel_topics: dict[int, str] = {}
    found: dict[str, str] | None = None
    stats = FileStats(source.name)
    scan = RecordScan(source, resync=True)
    untyped = 0
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
            elif isinstance(record, Message) and record.channel_id not in channel_topics:
                untyped += 1  # its channel record was in damaged bytes (or unreadable): cannot be typed
            elif isinstance(record, Message):
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
    return stats, dropped, found, scan, untyped


def _topic_of(channel: Channel, schema: Schema | None) -> TopicInfo | None:
    """The channel's topic, None when it cannot be typed (no schema; channel metadata not readable)."""
    try:
        info = topic_from_channel(channel, schema)
    except (yaml.YAMLError, ValueError, TypeError, AttributeError):  # metadata outside a CRC'd chunk
        return None
    return info if info.type else None


# --- metadata -----------------------------------------------------------------------------------------


def _old_metadata(directory: Path, name: str = METADATA_FILE) -> dict[str, Any] | None:
    """The bag's metadata.yaml (or ``name``) as a mapping, None when missing or unreadable."""
    try:
        info = load_yaml(directory / name, "bag metadata")["rosbag2_bagfile_information"]
    except (YamlFileError, KeyError, TypeError):
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


def _listed_counts(old: dict[str, Any] | None) -> dict[str, int | None]:
    """File name -> message count, as the old metadata.yaml lists them (None: a count it lacks)."""
    if old is None:
        return {}
    counts: dict[str, int | None] = {}
    with contextlib.suppress(KeyError, TypeError, ValueError, AttributeError):
        for listed in old.get("relative_file_paths") or []:
            counts[Path(str(listed)).name] = None
        for entry in old.get("files") or []:
            with contextlib.suppress(KeyError, TypeError, ValueError, AttributeError):
                counts[Path(str(entry["path"])).name] = int(entry["message_count"])
    return counts


def _custom_data_of(old: dict[str, Any] | None) -> dict[str, str] | None:
    if old is None or not isinstance(old.get("custom_data"), dict):
        return None
    return {str(k): str(v) for k, v in old["custom_data"].items()}


def _custom_data_of_record(record: Metadata) -> dict[str, str] | None:
    """custom_data carried by a metadata record: ours at a file's start, or rosbag2's at its end."""
    if record.name == CUSTOM_DATA_RECORD:
        return dict(record.metadata)
    if record.name == "rosbag2" and "serialized_metadata" in record.metadata:
        with contextlib.suppress(YamlFileError, KeyError, TypeError, AttributeError):
            info = parse_yaml(record.metadata["serialized_metadata"], record.name, "bag metadata record")
            info = info.get("rosbag2_bagfile_information", info)
            if isinstance(info.get("custom_data"), dict):
                return {str(k): str(v) for k, v in info["custom_data"].items()}
    return None
