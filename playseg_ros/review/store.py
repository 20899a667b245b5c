"""The reviewed labels on disk: sidecar files in the format `playseg convert` reads (one per source bag,
times from the bag's start; convert/annotations.py), plus the review state (which episodes are reviewed,
which proposals were rejected) in ``review.json`` beside them.

A label [t_s, t_e] covers the steps convert gives it: s the first step at or after t_s, e the last at or
before t_e, with its skips where stamps repeat (`EpisodeTimes`, over the episodes that share the file).
Every save replaces its file atomically and only when the file is still the version the
page loaded (its digest): two tabs editing one episode never overwrite each other silently.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import threading
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import yaml

from playseg_core.data.dataset import PlayDataset
from playseg_core.data.episode import Segment
from playseg_core.data.splits import ANNOTATED_SPLITS
from playseg_core.errors import PlaysegError
from playseg_ros.convert.annotations import (
    EpisodeTimes,
    SidecarLabelYaml,
    episodes_by_file,
    labels_from_file,
    sidecar_entries,
    sidecar_name,
    times_ns,
    write_sidecar,
)

HUMAN = "human"
EDITED = "edited"
NO_FILE = "none"
"""The version of a labels file that does not exist yet."""


class LabelFileError(PlaysegError):
    """A labels file that cannot be read: one line naming the file and the line of the bad entry."""


class VersionConflict(PlaysegError):
    """The labels file changed since the page loaded it (another tab or another reviewer saved)."""


@dataclass
class Label:
    """A segment [start, end) of an episode's steps with its instruction and where it came from:
    ``human``, ``model:<checkpoint digest>`` (accepted as proposed) or ``edited`` (a proposal changed)."""

    start: int
    end: int
    instruction: str
    provenance: str = HUMAN
    confidence: float = 1.0
    reviewer: str | None = None

    def to_json(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_json(cls, raw: Any, num_steps: int, where: str) -> Label:
        """A label the page sent; PlaysegError naming ``where`` when it does not fit the episode."""
        try:
            label = cls(
                int(raw["start"]),
                int(raw["end"]),
                str(raw["instruction"]).strip(),
                str(raw.get("provenance") or HUMAN),
                float(raw.get("confidence", 1.0)),
                None if raw.get("reviewer") in (None, "") else str(raw["reviewer"]),
            )
        except (KeyError, TypeError, ValueError) as error:
            raise PlaysegError(f"{where}: malformed label ({type(error).__name__})") from None
        if not 0 <= label.start < label.end <= num_steps:
            raise PlaysegError(
                f"{where}: [{label.start}, {label.end}) lies outside the episode's {num_steps} steps"
            )
        if not label.instruction:
            raise PlaysegError(f"{where}: no instruction")
        if not 0.0 <= label.confidence <= 1.0:  # NaN too: JSON and YAML both spell it
            raise PlaysegError(f"{where}: confidence {label.confidence} is not in [0, 1]")
        return label


def _entry_lines(text: str) -> list[int]:
    """The line (from 1) of each annotations entry of a sidecar's text."""
    try:
        root = yaml.compose(text, Loader=yaml.SafeLoader)
    except yaml.YAMLError:
        return []
    entries = root
    if isinstance(root, yaml.MappingNode):
        entries = next((v for k, v in root.value if getattr(k, "value", None) == "annotations"), None)
    if not isinstance(entries, yaml.SequenceNode):
        return []
    return [item.start_mark.line + 1 for item in entries.value]


def read_labels_file(path: Path) -> list[SidecarLabelYaml]:
    """The entries of a sidecar file, checked as `playseg convert` checks them; LabelFileError naming the
    file and the line of the first bad entry."""
    try:
        labels_from_file(path, path, 0)
    except PlaysegError as error:
        message = str(error)
        found = re.search(r"annotations\[(\d+)\](.*)", message)
        lines = _entry_lines(path.read_text(encoding="utf-8", errors="replace")) if found else []
        if found and int(found.group(1)) < len(lines):
            detail = found.group(2).lstrip(",: ")
            raise LabelFileError(
                f"labels file {str(path)!r}, line {lines[int(found.group(1))]}: {detail}"
            ) from None
        # convert names the bag first; here the labels file is the whole story
        raise LabelFileError(
            re.sub(r"^bag '[^']*'[,:] ", "", message).replace("annotations file", "labels file", 1)
        ) from None
    raw = yaml.safe_load(path.read_text(encoding="utf-8"))
    entries = raw.get("annotations", []) if isinstance(raw, dict) else raw
    return [dict(entry) for entry in entries or []]  # type: ignore[misc]


class LabelStore:
    """The labels and review state of one dataset's episodes, kept in ``directory``."""

    def __init__(self, dataset: PlayDataset, directory: Path) -> None:
        self.dataset = dataset
        self.directory = directory
        self._lock = threading.Lock()
        # per episode: the times of the episodes sharing its file, and its position among them
        self._times: dict[int, tuple[EpisodeTimes, int]] = {}
        for indices in episodes_by_file(dataset).values():
            times = EpisodeTimes([times_ns(dataset.timestamps(i)) for i in indices])
            self._times.update({index: (times, position) for position, index in enumerate(indices)})
        self.state_file = directory / "review.json"

    def file_of(self, index: int) -> Path:
        record = self.dataset.records[index]
        return self.directory / f"{sidecar_name(record.episode_id, record.source)}.yaml"

    def version(self, index: int) -> str:
        """The version of the episode's labels: a digest of its file's entries that fall in the episode
        (`NO_FILE` without any). A file holds every episode of one bag: saves to its other episodes do
        not change this one's version."""
        path = self.file_of(index)
        mine = [e for e in read_labels_file(path) if self._covers(index, e)] if path.is_file() else []
        if not mine:
            return NO_FILE
        return hashlib.sha256(json.dumps(mine, sort_keys=True).encode()).hexdigest()[:16]

    def check_files(self) -> None:
        """LabelFileError for the first labels file that does not read."""
        for path in sorted({self.file_of(i) for i in range(len(self.dataset))}):
            if path.is_file():
                read_labels_file(path)

    def _steps(self, index: int, entry: SidecarLabelYaml) -> tuple[int, int] | None:
        """The observations [s, e] of this episode an entry names, as convert maps it (the episode holding
        its first observation; cut at the episode's end); None when it starts in another episode."""
        times, position = self._times[index]
        first = times.first(round(float(entry["start"]) * 1e9), int(entry.get("start_skip", 0)))
        if first == len(times.all) or times.episode_of(first) != position:
            return None
        offset = int(times.offsets[position])
        last = times.last(round(float(entry["end"]) * 1e9), int(entry.get("end_skip", 0)))
        return first - offset, min(last - offset, len(times.episodes[position]) - 1)

    def _covers(self, index: int, entry: SidecarLabelYaml) -> bool:
        return self._steps(index, entry) is not None

    def labels(self, index: int) -> list[Label] | None:
        """The episode's labels from its file; None when its file does not exist yet (the dataset's own
        annotations are then the labels: `initial_labels`)."""
        path = self.file_of(index)
        if not path.is_file():
            return None
        labels = []
        for entry in read_labels_file(path):
            steps = self._steps(index, entry)
            if steps is None or not entry["instruction"]:
                continue
            start, end = steps
            if end - start < 1:
                continue
            confidence = entry.get("confidence", 1.0)
            labels.append(
                Label(
                    start,
                    end,
                    str(entry["instruction"]),
                    str(entry.get("provenance") or HUMAN),
                    float(confidence) if isinstance(confidence, int | float) else 1.0,
                    None if entry.get("reviewer") is None else str(entry.get("reviewer")),
                )
            )
        return sorted(labels, key=lambda label: label.start)

    def initial_labels(self, index: int) -> list[Label]:
        """The labels as the page first shows them: the file's, else the dataset's annotations."""
        labels = self.labels(index)
        if labels is not None:
            return labels
        if self.dataset.records[index].split not in ANNOTATED_SPLITS:
            return []
        return [Label(s.start, s.end, s.instruction) for s in self.dataset.segments(index) if s.instruction]

    def save(self, index: int, labels: list[Label], version: str) -> str:
        """Replace the episode's labels in its file (other episodes' entries in the same file stay);
        VersionConflict when the episode's labels are no longer ``version``. Returns the new version."""
        path = self.file_of(index)
        timestamps = self.dataset.timestamps(index)
        with self._lock:
            current = self.version(index)
            if current != version:
                raise VersionConflict(
                    f"{path}: changed since this page loaded it (another tab or reviewer saved); reload the "
                    "episode to see their labels, then make your changes again"
                )
            others = (
                [e for e in read_labels_file(path) if not self._covers(index, e)] if path.is_file() else []
            )
            times, position = self._times[index]
            entries: list[SidecarLabelYaml] = []
            for label in labels:
                segment = Segment(label.start, label.end, label.instruction, label.confidence)
                (entry,) = sidecar_entries([segment], timestamps, label.provenance, times, position)
                if label.reviewer:
                    entry["reviewer"] = label.reviewer
                entries.append(entry)
            write_sidecar(path, others + entries)
            return self.version(index)

    def state(self) -> dict[str, dict[str, Any]]:
        """Per episode id: ``reviewed`` (bool) and ``rejected`` ([start, end, instruction] proposals)."""
        try:
            raw = json.loads(self.state_file.read_text(encoding="utf-8"))
        except FileNotFoundError:
            return {}
        except (OSError, ValueError) as error:
            raise PlaysegError(f"{self.state_file}: unreadable review state ({error})") from None
        return raw if isinstance(raw, dict) else {}

    def save_state(self, episode_id: str, reviewed: bool, rejected: list[list[Any]]) -> None:
        with self._lock:
            state = self.state()
            state[episode_id] = {"reviewed": reviewed, "rejected": rejected}
            self.directory.mkdir(parents=True, exist_ok=True)
            staging = self.state_file.with_name(f".{self.state_file.name}.partial-{os.getpid()}")
            staging.write_text(json.dumps(state, indent=1, sort_keys=True) + "\n", encoding="utf-8")
            os.replace(staging, self.state_file)
