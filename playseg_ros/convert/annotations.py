"""Instruction labels in time, mapped onto the steps of the converted episodes.

Two sources, used together when both are given: ``playseg_msgs/msg/TimedAnnotation`` messages on a topic
(start, end, instruction), and a sidecar file next to the bag (YAML or JSON)::

    times: from_start        # seconds from the bag's first message (default), or: absolute (epoch seconds)
    annotations:
      - {start: 1.5, end: 4.0, instruction: pick up the red cup}

A label [start, end] becomes the segment [s, e) of the episode holding it, where s is the first step at or
after ``start`` and e the last step at or before ``end`` (the observations o_s..o_e lie inside the label's
time). A label that covers fewer than two steps, overlaps an earlier label, or has no instruction is
dropped and reported; one that runs past its episode's end is cut there and reported.
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal, NotRequired, TypedDict

import numpy as np

from playseg_core.data.episode import Segment
from playseg_ros.convert.errors import ConvertError, MappingError
from playseg_ros.convert.mapping import read_yaml
from playseg_ros.convert.source import TIMED_ANNOTATION, TopicSamples


class SidecarLabelYaml(TypedDict):
    start: float
    end: float
    instruction: str


class SidecarYaml(TypedDict):
    times: NotRequired[Literal["from_start", "absolute"]]
    annotations: list[SidecarLabelYaml]


@dataclass(frozen=True, order=True)
class TimedLabel:
    start_ns: int
    end_ns: int
    instruction: str


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
        if set(entry) != {"start", "end", "instruction"}:
            raise ConvertError(
                bag, f"{where}: expected exactly start, end, instruction; got {_keys(set(entry))}"
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
        instruction = "" if entry["instruction"] is None else entry["instruction"]  # "": dropped, reported
        if not isinstance(instruction, str):
            raise ConvertError(
                bag, f"{where}, key 'instruction': must be text, got {_kind(entry['instruction'])}"
            )
        labels.append(
            TimedLabel(base + round(seconds["start"] * 1e9), base + round(seconds["end"] * 1e9), instruction)
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
    """Each episode's segments (``episode_steps``: each episode's step times, sorted) and notes about the
    labels that were cut or dropped."""
    segments: list[list[Segment]] = [[] for _ in episode_steps]
    notes: list[str] = []
    for label in sorted(labels):
        when = f"annotation {label.instruction!r} [{label.start_ns / 1e9:.3f}, {label.end_ns / 1e9:.3f}]"
        if not label.instruction:
            notes.append(f"{when}: no instruction; dropped")
            continue
        # the episode holding its first step: the first episode that ends at or after the label's start
        index = next((k for k, steps in enumerate(episode_steps) if steps[-1] >= label.start_ns), None)
        if index is None or episode_steps[index][0] > label.end_ns:
            notes.append(f"{when}: no step of any episode in its time; dropped")
            continue
        steps = episode_steps[index]
        start = int(np.searchsorted(steps, label.start_ns, side="left"))
        end = int(np.searchsorted(steps, label.end_ns, side="right")) - 1
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
