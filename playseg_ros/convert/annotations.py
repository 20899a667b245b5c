"""Instruction labels in time, mapped onto the steps of the converted episodes.

Two sources, used together when both are given: ``playseg_msgs/msg/TimedAnnotation`` messages on a topic
(start, end, instruction), and a sidecar file next to the bag (YAML or JSON)::

    times: from_start        # seconds from the bag's first message (default), or: absolute (epoch seconds)
    annotations:
      - {start: 1.5, end: 4.0, instruction: pick up the red cup}

A label [start, end] becomes the segment [s, e) of the episode holding it, where s is the first step at or
after ``start`` and e the last step at or before ``end`` (the observations o_s..o_e lie inside the label's
time). Stamps may repeat (two observations recorded at one time): ``start_skip: n`` leaves out the first n
observations stamped exactly ``start``, ``end_skip: n`` the last n stamped exactly ``end`` (both 0 when
absent; at most all but one of them), so every segment has times that name it exactly (`EpisodeTimes`).
A label that covers fewer than two steps, overlaps an earlier label, or has no instruction is dropped and
reported; one that runs past its episode's end is cut there and reported.

An entry may also carry ``provenance`` (who made it: ``human``, ``model:<checkpoint digest>``, ``edited``),
``confidence`` (the model's label probability) and ``reviewer``; conversion ignores them. `write_sidecar`
writes the format (`playseg segment --labels-out`, `playseg review`).
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal, NotRequired, TypedDict

import numpy as np

from playseg_core.data.dataset import PlayDataset
from playseg_core.data.episode import Segment
from playseg_ros.convert.errors import ConvertError, MappingError
from playseg_ros.convert.mapping import read_yaml
from playseg_ros.convert.source import TIMED_ANNOTATION, TopicSamples


class SidecarLabelYaml(TypedDict):
    start: float
    end: float
    instruction: str
    start_skip: NotRequired[int]
    end_skip: NotRequired[int]
    provenance: NotRequired[str]
    confidence: NotRequired[float]
    reviewer: NotRequired[str]


LABEL_KEYS = frozenset({"start", "end", "instruction"})
OPTIONAL_LABEL_KEYS = frozenset({"start_skip", "end_skip", "provenance", "confidence", "reviewer"})
SKIP_KEYS = ("start_skip", "end_skip")


class SidecarYaml(TypedDict):
    times: NotRequired[Literal["from_start", "absolute"]]
    annotations: list[SidecarLabelYaml]


@dataclass(frozen=True, order=True)
class TimedLabel:
    start_ns: int
    end_ns: int
    instruction: str
    start_skip: int = 0  # observations stamped exactly start_ns the label leaves out at its start
    end_skip: int = 0  # and stamped exactly end_ns at its end


class EpisodeTimes:
    """The observation times (int64 ns, one array per episode) of the episodes one labels file covers (a
    bag's), in time order: which observations a label's times and skips name, and the skips that name a
    segment's observations exactly where stamps repeat. Repeats are counted across episodes as well, so a
    run of equal stamps that spans an episode boundary still names one observation each."""

    def __init__(self, episodes: Sequence[np.ndarray]) -> None:
        self.episodes = [np.asarray(times, dtype=np.int64) for times in episodes]
        self.offsets = np.cumsum([0] + [len(times) for times in self.episodes])
        self.all = np.concatenate(self.episodes) if self.episodes else np.zeros(0, np.int64)

    def first(self, time_ns: int, skip: int = 0) -> int:
        """The first observation (an index over all episodes) at or after ``time_ns``, ``skip`` further
        among those stamped exactly ``time_ns``; ``len(self.all)`` when none is."""
        low, high = self._stamped(time_ns)
        return low + min(skip, max(high - low - 1, 0))

    def last(self, time_ns: int, skip: int = 0) -> int:
        """The last observation at or before ``time_ns``, ``skip`` earlier among those stamped exactly
        ``time_ns``; -1 when none is."""
        low, high = self._stamped(time_ns)
        return high - 1 - min(skip, max(high - low - 1, 0))

    def _stamped(self, time_ns: int) -> tuple[int, int]:
        """The observations [low, high) stamped exactly ``time_ns`` (empty at where it would go)."""
        return int(np.searchsorted(self.all, time_ns, "left")), int(
            np.searchsorted(self.all, time_ns, "right")
        )

    def episode_of(self, observation: int) -> int:
        """The episode holding ``observation`` (an index over all episodes)."""
        return int(np.searchsorted(self.offsets, observation, "right")) - 1

    def skips(self, episode: int, start: int, end: int) -> dict[str, int]:
        """The skips that make the times of o_start and o_end of ``episode`` name exactly these two
        observations (`first` and `last` give them back); none where a stamp does not repeat."""
        s, e = int(self.offsets[episode]) + start, int(self.offsets[episode]) + end
        skips = {
            "start_skip": s - self._stamped(self.all[s])[0],
            "end_skip": self._stamped(self.all[e])[1] - 1 - e,
        }
        return {key: n for key, n in skips.items() if n}


def label_of(msg: Any) -> TimedLabel:
    """The label a TimedAnnotation message carries (the caller checked its type: `check_label_type`)."""
    start = int(msg.start.sec) * 1_000_000_000 + int(msg.start.nanosec)
    end = int(msg.end.sec) * 1_000_000_000 + int(msg.end.nanosec)
    return TimedLabel(start, end, str(msg.instruction))


def check_label_type(bag: Path | str, topic: str, msgtype: str) -> None:
    """ConvertError naming the topic unless its messages are TimedAnnotations."""
    if msgtype != TIMED_ANNOTATION:
        raise ConvertError(bag, f"message type is {msgtype!r}, expected {TIMED_ANNOTATION!r}", topic)


def labels_from_topic(bag: Path, samples: TopicSamples) -> list[TimedLabel]:
    check_label_type(bag, samples.topic, samples.msgtype)
    return [label_of(msg) for msg in samples.messages]


def sidecar_path(bag: Path, pattern: str, outside_bag: bool = False) -> Path:
    """Where the sidecar file of ``bag`` lies: ``pattern`` with ``{name}`` replaced by the bag's name (without
    suffix), relative to the bag directory (a bag file: the directory holding it) unless absolute.

    A relative pattern that leads out of that directory (``../other_bag/labels.yaml``) would give this
    bag another bag's labels without a word: a ConvertError unless ``outside_bag`` (the mapping's
    ``annotations.allow_outside_bag``). The check is on the path as written (no symlink is followed)."""
    name = bag.name if bag.is_dir() else bag.stem
    relative = Path(pattern.replace("{name}", name))
    if relative.is_absolute():
        return relative
    home = bag if bag.is_dir() else bag.parent
    if not outside_bag and os.path.normpath(relative).split(os.sep)[0] == os.pardir:
        raise ConvertError(
            bag,
            f"annotations file {str(relative)!r} lies outside the bag's directory {str(home)!r}: give an "
            "absolute path, or allow_outside_bag: true under the mapping's annotations",
        )
    return home / relative


MAX_SECONDS = 4e9
"""The largest sidecar time in seconds, either way (absolute times are epoch seconds: 4e9 is the year
2096); with the bag's start added it is still an int64 count of nanoseconds."""

MAX_SKIP = 2**31 - 1
"""The largest ``start_skip``/``end_skip`` a sidecar may give."""


def labels_from_file(bag: Path, file: Path, bag_start_ns: int) -> list[TimedLabel]:
    """The labels of a sidecar file; ConvertError naming the bag, the file and the entry when malformed.
    Messages quote keys at most, never values: a path given by mistake may point at any file."""
    try:
        raw: Any = read_yaml(file, "annotations file")
    except MappingError as error:
        raise ConvertError(bag, str(error)) from None
    what = f"annotations file {str(file)!r}"
    entries: Any = raw
    base = bag_start_ns
    if isinstance(raw, Mapping):
        unknown = set(raw) - {"times", "annotations"}
        if unknown:
            raise ConvertError(bag, f"{what}: unknown key(s) {_keys(unknown)} (expected times, annotations)")
        times = raw.get("times", "from_start")
        if times not in ("from_start", "absolute"):
            raise ConvertError(bag, f"{what}, key 'times': must be from_start or absolute")
        base = 0 if times == "absolute" else bag_start_ns
        entries = raw.get("annotations", [])
    if not isinstance(entries, Sequence) or isinstance(entries, str):
        raise ConvertError(bag, f"{what}: expected a list of annotations, got {_kind(entries)}")
    labels = []
    for i, entry in enumerate(entries):
        where = f"{what}, annotations[{i}]"
        if not isinstance(entry, Mapping):
            raise ConvertError(
                bag, f"{where}: expected a mapping of start, end, instruction; got {_kind(entry)}"
            )
        if not LABEL_KEYS <= set(entry) <= LABEL_KEYS | OPTIONAL_LABEL_KEYS:
            raise ConvertError(
                bag,
                f"{where}: expected start, end, instruction (and optionally start_skip, end_skip, "
                f"provenance, confidence, reviewer); got {_keys(set(entry))}",
            )
        seconds = {}
        for key in ("start", "end"):
            value = entry[key]
            if isinstance(value, bool) or not isinstance(value, int | float):
                raise ConvertError(
                    bag, f"{where}, key {key!r}: must be a number (seconds), got {_kind(value)}"
                )
            if (
                not (isinstance(value, int) or math.isfinite(value))
                or not -MAX_SECONDS <= value <= MAX_SECONDS
            ):
                # NaN and inf would become no integer time at all, 1e300 one past any clock
                raise ConvertError(
                    bag, f"{where}, key {key!r}: must be a finite number of seconds within +-{MAX_SECONDS:g}"
                )
            seconds[key] = value
        if seconds["end"] < seconds["start"]:
            raise ConvertError(bag, f"{where}: end is before start")
        skips = {}
        for key in SKIP_KEYS:
            value = entry.get(key, 0)
            if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value <= MAX_SKIP:
                raise ConvertError(
                    bag, f"{where}, key {key!r}: must be a whole number of observations in 0..{MAX_SKIP}"
                )
            skips[key] = value
        instruction = "" if entry["instruction"] is None else entry["instruction"]  # "": dropped, reported
        if not isinstance(instruction, str):
            raise ConvertError(
                bag, f"{where}, key 'instruction': must be text, got {_kind(entry['instruction'])}"
            )
        labels.append(
            TimedLabel(
                base + round(seconds["start"] * 1e9), base + round(seconds["end"] * 1e9), instruction, **skips
            )
        )
    return labels


def _kind(value: Any) -> str:
    """What a wrong value is, without quoting it."""
    return "nothing" if value is None else f"a {type(value).__name__}"


def _keys(keys: set[Any]) -> str:
    """Keys for a message, each cut short (a stray file parsed as YAML may have whole lines as keys)."""
    names = sorted(str(k) if len(str(k)) <= 40 else str(k)[:37] + "..." for k in keys)
    return "[" + ", ".join(repr(n) for n in names[:5]) + (", ...]" if len(names) > 5 else "]")


def segments_of_episodes(
    episode_steps: Sequence[np.ndarray], labels: Sequence[TimedLabel]
) -> tuple[list[list[Segment]], list[str]]:
    """Each episode's segments (``episode_steps``: each episode's step times, sorted, the episodes in time
    order) and notes about the labels that were cut or dropped."""
    times = EpisodeTimes(episode_steps)
    segments: list[list[Segment]] = [[] for _ in episode_steps]
    notes: list[str] = []
    for label in sorted(labels, key=_in_time_order):
        when = f"annotation {label.instruction!r} [{label.start_ns / 1e9:.3f}, {label.end_ns / 1e9:.3f}]"
        if not label.instruction:
            notes.append(f"{when}: no instruction; dropped")
            continue
        # the episode holding its first step
        first = times.first(label.start_ns, label.start_skip)
        if first == len(times.all) or times.all[first] > label.end_ns:
            notes.append(f"{when}: no step of any episode in its time; dropped")
            continue
        index = times.episode_of(first)
        steps, offset = episode_steps[index], int(times.offsets[index])
        start = first - offset
        end = min(times.last(label.end_ns, label.end_skip) - offset, len(steps) - 1)
        if (
            label.end_ns > steps[-1]
            and index + 1 < len(episode_steps)
            and episode_steps[index + 1][0] <= label.end_ns
        ):
            notes.append(f"{when}: runs past the end of its episode; cut at step {end}")
        if end - start < 1:
            notes.append(f"{when}: covers {max(end - start + 1, 0)} step(s), a segment needs 2; dropped")
            continue
        previous = segments[index][-1] if segments[index] else None
        if previous is not None and start < previous.end:
            notes.append(
                f"{when}: overlaps the previous annotation (steps {previous.start}-{previous.end}); dropped"
            )
            continue
        segments[index].append(Segment(start, end, label.instruction))
    return segments, notes


def _in_time_order(label: TimedLabel) -> tuple[int, int, int, int, str]:
    """Labels sorted by the observations they name: a skip moves a boundary within its stamp."""
    return label.start_ns, label.start_skip, label.end_ns, -label.end_skip, label.instruction


def times_ns(seconds: np.ndarray) -> np.ndarray:
    """Observation times in seconds (a dataset's ``timestamp``) as the int64 nanoseconds a sidecar's
    seconds read as."""
    return np.round(np.asarray(seconds, dtype=np.float64) * 1e9).astype(np.int64)


def sidecar_entries(
    segments: Sequence[Segment],
    timestamps: np.ndarray,
    provenance: str,
    times: EpisodeTimes | None = None,
    episode: int = 0,
) -> list[SidecarLabelYaml]:
    """``segments`` as sidecar labels: [s, e) becomes [time of o_s, time of o_e], with the skips that
    `segments_of_episodes` needs to map it back onto [s, e) where stamps repeat (``times``: the episodes
    of the labels file, ``episode`` this one's position among them; default: this episode alone).
    Unlabelled segments have no entry."""
    times = EpisodeTimes([times_ns(timestamps)]) if times is None else times
    entries: list[SidecarLabelYaml] = []
    for seg in segments:
        if not seg.instruction:
            continue
        entry: SidecarLabelYaml = {
            "start": float(timestamps[seg.start]),
            "end": float(timestamps[seg.end]),
            "instruction": seg.instruction,
        }
        entry.update(times.skips(episode, seg.start, seg.end))  # type: ignore[typeddict-item]
        entry["provenance"] = provenance
        entry["confidence"] = round(float(seg.confidence), 6)
        entries.append(entry)
    return entries


def episodes_by_file(dataset: PlayDataset) -> dict[str, list[int]]:
    """The episodes that share each sidecar file (`sidecar_name`), in time order (first timestamp)."""
    groups: dict[str, list[int]] = {}
    for index, record in enumerate(dataset.records):
        groups.setdefault(sidecar_name(record.episode_id, record.source), []).append(index)
    for indices in groups.values():
        indices.sort(key=lambda i: (float(dataset.timestamps(i)[0]), i))
    return groups


def sidecar_name(episode_id: str, source: Mapping[str, Any] | None) -> str:
    """The sidecar file name (without suffix) of an episode: its bag's name (all episodes of a bag share one
    file, times from the bag's start), else its id with path separators replaced."""
    bag = source.get("bag") if source else None
    if isinstance(bag, str) and bag:
        path = Path(bag)
        return path.name if path.suffix == "" else path.stem
    return "".join(c if c.isalnum() or c in "-_.:" else "_" for c in episode_id).lstrip(".") or "episode"


def write_sidecar(path: Path, labels: Sequence[SidecarLabelYaml]) -> None:
    """Write ``labels`` as a sidecar file (times from_start), atomically: a reader sees the old file or the
    new one, never a part."""
    import yaml

    text = yaml.safe_dump(
        {"times": "from_start", "annotations": [dict(label) for label in sorted(labels, key=_start_of)]},
        sort_keys=False,
        allow_unicode=True,
        width=200,
    )
    path.parent.mkdir(parents=True, exist_ok=True)
    staging = path.with_name(f".{path.name}.partial-{os.getpid()}")
    staging.write_text(text, encoding="utf-8")
    os.replace(staging, path)


def _start_of(label: SidecarLabelYaml) -> tuple[float, int]:
    return label["start"], label.get("start_skip", 0)


def write_labels_out(
    dataset: PlayDataset, out_dir: Path, keeps: Callable[[Segment], bool], provenance: Callable[[int], str]
) -> list[Path]:
    """Every episode's segments that ``keeps`` accepts as sidecar files in ``out_dir``, one per source
    (`sidecar_name`), times from the source's start (`PlayDataset.timestamps`), each entry's
    ``provenance(episode index)``: what `convert` reads back as the same segments. Returns the files."""
    files = []
    for name, indices in sorted(episodes_by_file(dataset).items()):
        times = EpisodeTimes([times_ns(dataset.timestamps(i)) for i in indices])
        labels: list[SidecarLabelYaml] = []
        for position, index in enumerate(indices):
            kept = [s for s in dataset.segments(index, truth=True) if keeps(s)]
            labels += sidecar_entries(kept, dataset.timestamps(index), provenance(index), times, position)
        files.append(out_dir / f"{name}.yaml")
        write_sidecar(files[-1], labels)
    return files


def model_provenance(checkpoint: str | os.PathLike[str]) -> str:
    """``model:<digest>``: the first 12 hex digits of the checkpoint file's SHA-256."""
    import hashlib

    digest = hashlib.sha256(Path(checkpoint).read_bytes()).hexdigest()[:12]
    return f"model:{digest}"


def write_output_labels(dataset_dir: Path, out_dir: Path, model: str | None) -> list[Path]:
    """``--labels-out`` of `playseg segment` and `playseg convert --segment`: the segments of the dataset
    they wrote, as sidecar files. `segment`'s dataset holds every segment: those its keep rule (recorded in
    its meta) keeps are written; `convert` kept only those already. Annotated episodes' segments are
    ``human``, the others ``model:<digest of model>``."""
    from playseg_core.data.splits import ANNOTATED_SPLITS
    from playseg_core.ps.labelling import KeepRule

    dataset = PlayDataset.open(dataset_dir)
    keep = dataset.info.get("meta", {}).get("keep")
    rule = KeepRule("all")
    if isinstance(keep, dict):
        threshold = keep.get("threshold")
        rule = KeepRule(str(keep.get("rule")), math.inf if threshold is None else float(threshold))
    by_model = model_provenance(model) if model else "model"
    return write_labels_out(
        dataset,
        out_dir,
        rule.keeps,
        lambda index: "human" if dataset.records[index].split in ANNOTATED_SPLITS else by_model,
    )
