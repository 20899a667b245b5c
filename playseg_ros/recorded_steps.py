"""The PlaySteps of a reference-form LabelledSegment, read back from the recorder's bag.

A reference names the recorder's bag directory, the PlayStep topic recorded there, the episode, the step
numbers and the header stamps of its first and last step. The recorder writes ``<bag>.partial/`` while it
records and renames it ``<bag>`` when it finishes, so either may hold the steps; files are read record
by record (bag/mcap_scan.py), so a file still being written (or left by a killed recorder) is read up
to its last complete chunk. Each file is scanned once: a later call reads on from where the last one
stopped (the recorder closes a chunk every ``flush_period_s``). The index keeps where each step is
(file, record, stamp), not the step itself: a few dozen bytes a step whatever the cameras; a segment's
steps are decoded when it is resolved.

Steps that are not (yet) in the bag raise `StepsNotRecorded`, naming the bag, topic, episode and steps:
the caller keeps the segment and asks again later.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from mcap.records import Channel, Message, Schema

from playseg_core.errors import PlaysegError
from playseg_ros.bag.mcap_scan import RecordScan, mcap_files, read_record
from playseg_ros.bag.schema import METADATA_FILE
from playseg_ros.bag.writer import partial_path
from playseg_ros.messages import PLAY_STEP, is_reference, stamp_ns, time_ns
from playseg_ros.typestore import playseg_typestore, typestore_for


class StepsNotRecorded(PlaysegError):
    """The bag does not (yet) hold every step a reference names; the message says which are missing.
    ``recording``: the bag is still being recorded (the steps may come with its next chunk)."""

    def __init__(self, message: str, recording: bool = False) -> None:
        super().__init__(message)
        self.recording = recording


@dataclass(frozen=True)
class _Located:
    """Where one recorded PlayStep is: its file, the record (a chunk) and its place among the chunk's
    records, and its header stamp."""

    file: str
    offset: int
    position: int
    stamp_ns: int


@dataclass
class _FileScan:
    inode: int
    end: int = 0  # the next scan starts here: just past the last complete record
    finished: bool = False  # footer read: nothing more will come
    problem: str | None = None  # why the last scan stopped early (an unfinished file's cut is normal)
    schemas: dict[int, str] = field(default_factory=dict)  # schema id -> type name
    channels: dict[int, tuple[str, str]] = field(default_factory=dict)  # the topic's channels: type, hash
    unreadable: int = 0  # messages of the topic that did not decode as a PlayStep


@dataclass
class StepsReference:
    """What a reference-form LabelledSegment names (steps ``start..end``, end inclusive)."""

    bag: str
    topic: str
    episode_id: str
    start: int
    end: int
    first_stamp_ns: int
    last_stamp_ns: int

    def __str__(self) -> str:
        return f"episode {self.episode_id!r} steps {self.start}..{self.end} on {self.topic} in bag {self.bag}"


def reference_of(msg: Any) -> StepsReference | None:
    """What a reference-form LabelledSegment names; None for one that embeds its steps."""
    if not is_reference(msg):
        return None
    return StepsReference(
        msg.recording_bag, msg.steps_topic, msg.episode_id, int(msg.start_step), int(msg.end_step),
        time_ns(msg.first_step_stamp), time_ns(msg.last_step_stamp),
    )  # fmt: skip


class RecordedSteps:
    """The PlaySteps recorded on ``topic`` in the bag ``bag`` (or ``<bag>.partial`` while recording)."""

    def __init__(self, bag: Path | str, topic: str) -> None:
        self.bag, self.topic = Path(bag), topic
        self._files: dict[str, _FileScan] = {}
        self._where: dict[tuple[str, int], list[_Located]] = {}

    def directory(self) -> Path | None:
        """Where the bag's files are now: the finished bag, else the recording in progress."""
        if (self.bag / METADATA_FILE).is_file():
            return self.bag
        partial = partial_path(self.bag)
        if partial.is_dir():
            return partial
        return self.bag if self.bag.is_dir() else None

    def steps(self, ref: StepsReference) -> list[Any]:
        """The PlaySteps ``ref`` names, in order (rosbags message objects); StepsNotRecorded when some
        are not in the bag (yet)."""
        directory = self.directory()
        if directory is None:
            raise StepsNotRecorded(f"{ref}: no bag at {self.bag} (nor {partial_path(self.bag).name})")
        try:
            self._update(directory)
            located, missing = self._locate(ref)
            if not missing:
                return self._read(directory, located)
        except OSError as error:  # a file renamed or replaced under us (the recording finished): later
            raise StepsNotRecorded(f"{ref}: {error.strerror}: {error.filename}", recording=True) from None
        except Exception as error:  # noqa: BLE001 -- damaged bytes make any decoder error possible
            raise StepsNotRecorded(f"{ref}: cannot read: {type(error).__name__}: {error}") from None
        recording = directory != self.bag
        raise StepsNotRecorded(f"{ref}: {_ranges(missing)} {self._not_there(directory)}", recording)

    def _locate(self, ref: StepsReference) -> tuple[list[_Located], list[int]]:
        located, missing = [], []
        for step in range(ref.start, ref.end + 1):
            found = [
                place
                for place in self._where.get((ref.episode_id, step), [])
                if ref.first_stamp_ns <= place.stamp_ns <= ref.last_stamp_ns
            ]
            if found:
                located.append(found[0])  # a replayed episode with the same stamps: the same step
            else:
                missing.append(step)
        return located, missing

    def _not_there(self, directory: Path) -> str:
        """Why steps are missing, for a message: a recording in progress, or what the finished bag has."""
        unreadable = sum(scan.unreadable for scan in self._files.values())
        notes = [f"{unreadable} messages on the topic are not PlaySteps"] if unreadable else []
        if directory != self.bag:
            return "not recorded yet (the recording in progress, read to its last complete chunk)" + (
                f"; {notes[0]}" if notes else ""
            )
        notes += [f"{name} {scan.problem}" for name, scan in self._files.items() if scan.problem]
        return "not in the bag" + (f" ({'; '.join(notes)})" if notes else "")

    def _update(self, directory: Path) -> None:
        for path in mcap_files(directory):
            try:
                inode = os.stat(path).st_ino
            except OSError:
                continue  # renamed under us (the recording finished): the next call reads it there
            scan = self._files.get(path.name)
            if scan is None or scan.inode != inode:  # new, or rewritten (recovered): read it from the start
                self._forget(path.name)
                scan = self._files[path.name] = _FileScan(inode)
            if not scan.finished:
                self._scan(path, scan)

    def _forget(self, name: str) -> None:
        self._files.pop(name, None)
        for key, places in list(self._where.items()):
            kept = [place for place in places if place.file != name]
            if kept:
                self._where[key] = kept
            else:
                del self._where[key]

    def _scan(self, path: Path, scan: _FileScan) -> None:
        records = RecordScan(path, start=scan.end)
        chunk, position = -1, 0
        for offset, record in records:
            position = position + 1 if offset == chunk else 0
            chunk = offset
            if isinstance(record, Schema):
                scan.schemas[record.id] = record.name
            elif isinstance(record, Channel) and record.topic == self.topic:
                type_name = scan.schemas.get(record.schema_id, PLAY_STEP)
                scan.channels[record.id] = (type_name, record.metadata.get("topic_type_hash", ""))
            elif isinstance(record, Message) and record.channel_id in scan.channels:
                try:
                    msg = _deserialize(record.data, *scan.channels[record.channel_id])
                    key, stamp = (msg.episode_id, int(msg.step)), stamp_ns(msg.header)
                except Exception:  # noqa: BLE001 -- a message that is not a PlayStep: counted, reported
                    scan.unreadable += 1
                    continue
                self._where.setdefault(key, []).append(_Located(path.name, offset, position, stamp))
        scan.end = max(scan.end, records.end)  # a file cut inside its magic (just created) reads as 0
        scan.finished, scan.problem = records.problem is None, records.problem

    def _read(self, directory: Path, located: list[_Located]) -> list[Any]:
        chunks: dict[tuple[str, int], list[Any]] = {}
        steps = []
        for place in located:
            key = (place.file, place.offset)
            if key not in chunks:
                chunks[key] = read_record(directory / place.file, place.offset)
            record = chunks[key][place.position]
            steps.append(_deserialize(record.data, *self._files[place.file].channels[record.channel_id]))
        return steps


def _deserialize(data: bytes, type_name: str, type_hash: str) -> Any:
    store = typestore_for(type_name, type_hash) or playseg_typestore()
    return store.deserialize_cdr(data, type_name)


def _ranges(steps: list[int]) -> str:
    """[3, 4, 5, 9] -> 'steps 3..5, 9'."""
    parts, first = [], steps[0]
    for previous, step in zip(steps, [*steps[1:], None], strict=True):
        if step != previous + 1:
            parts.append(str(first) if first == previous else f"{first}..{previous}")
            first = step
    return f"step{'s' if len(steps) > 1 else ''} {', '.join(parts)}"
