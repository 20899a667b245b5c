"""One robot bag through a mapping: its steps (stepping.py, the code the live adapter runs too), grouped
into episodes with their labels.

Steps follow the primary feature's clock (real primary message times, thinned to fps); every other feature
is aligned onto them (alignment.py); a step where any feature has no sample within its tolerance is
dropped, never filled in, and reported once per feature (count and first time). See stepping.py.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from playseg_core.data.episode import Episode, Segment
from playseg_core.data.features import STATE, Features
from playseg_ros.convert.annotations import (
    TimedLabel,
    labels_from_file,
    labels_from_topic,
    segments_of_episodes,
    sidecar_path,
)
from playseg_ros.convert.mapping import ConvertMapping
from playseg_ros.convert.source import TopicSamples, open_bag, read_topics
from playseg_ros.convert.stepping import BuiltStep, StepBuilder


@dataclass
class BagEpisodes:
    """What one bag gives: its episodes (with segments where labelled), their schema, and notes."""

    episodes: list[Episode]
    features: Features | None  # None when no episode is left
    dropped_steps: int = 0
    notes: list[str] = field(default_factory=list)


def convert_bag(bag: Path, mapping: ConvertMapping) -> BagEpisodes:
    """The episodes of ``bag`` under ``mapping``; ConvertError naming the bag, topic, field and time when
    the bag does not fit the mapping."""
    with open_bag(bag) as reader:
        optional = [t for t in (mapping.annotation_topic, mapping.marker_topic) if t]
        samples = read_topics(bag, reader, mapping.topics, mapping.clock == "header", optional)
        bag_start = reader.start_time
    return episodes_of(bag, mapping, samples, bag_start)


def episodes_of(
    bag: Path, mapping: ConvertMapping, samples: dict[str, TopicSamples], bag_start_ns: int
) -> BagEpisodes:
    """The bag's steps through `StepBuilder` (the code the live adapter runs), as episodes with labels."""
    builder = StepBuilder(mapping, bag)
    topics = {f.topic for f in mapping.topic_features} | (
        {mapping.marker_topic} if mapping.marker_topic else set()
    )
    for topic in sorted(topics):
        sample = samples[topic]
        # arrival order: the stamp-outlier filter sees a bag's samples as the live adapter saw them
        builder.add_sorted(topic, sample.stamps.tolist(), sample.messages, sample.msgtype, sample.arrival)
    steps = builder.finish()
    notes = builder.notes()
    grouped: list[list[BuiltStep]] = []
    for step in steps:
        if step.step == 0:
            grouped.append([])
        grouped[-1].append(step)
    if not grouped:
        return BagEpisodes([], None, builder.dropped_steps, notes)
    labels, label_notes = _labels(bag, mapping, samples, bag_start_ns)
    notes += label_notes
    times = [np.array([s.time_ns for s in episode], dtype=np.int64) for episode in grouped]
    segments, label_notes = segments_of_episodes(times, labels)
    notes += label_notes
    name = bag.name if bag.is_dir() else bag.stem
    source = {"bag": str(bag), "topics": mapping.topics, "start_ns": bag_start_ns}
    episodes = [
        replace(
            _episode(f"{name}:{k}", episode, mapping, episode_segments),
            timestamps=(episode_times - bag_start_ns)
            / 1e9,  # seconds from the bag's start, as sidecars count
            source=source,
        )
        for k, (episode, episode_times, episode_segments) in enumerate(
            zip(grouped, times, segments, strict=True)
        )
    ]
    return BagEpisodes(episodes, builder.schema(), builder.dropped_steps, notes)


def _episode(
    episode_id: str, steps: list[BuiltStep], mapping: ConvertMapping, segments: list[Segment]
) -> Episode:
    """Built steps as an episode: N observations, N-1 actions (the last observation has none)."""
    actions = np.stack([s.action for s in steps[:-1] if s.action is not None]).astype(np.float32, copy=False)
    images = {
        name: np.stack([s.observation[name] for s in steps])
        for name, feature in mapping.features.items()
        if feature.is_image
    }
    state = np.stack([s.observation[STATE] for s in steps]) if STATE in mapping.features else None
    return Episode(episode_id, np.ascontiguousarray(actions), images, state, segments)


def _labels(
    bag: Path, mapping: ConvertMapping, samples: dict[str, TopicSamples], bag_start_ns: int
) -> tuple[list[TimedLabel], list[str]]:
    """The bag's labels from the topic and the sidecar file; a missing source is a note, not an error
    (a bag nobody annotated is unannotated play)."""
    labels: list[TimedLabel] = []
    notes: list[str] = []
    if mapping.annotation_topic and samples[mapping.annotation_topic].messages:
        labels += labels_from_topic(bag, samples[mapping.annotation_topic])
    if mapping.annotation_file:
        file = sidecar_path(bag, mapping.annotation_file, mapping.annotation_file_outside_bag)
        if file.is_file():
            from_file = labels_from_file(bag, file, bag_start_ns)
            labels += from_file
            notes.append(f"{len(from_file)} label(s) from annotations file {str(file)!r}")
        else:
            notes.append(f"no annotations file {str(file)!r}")
    if mapping.annotation_topic and not samples[mapping.annotation_topic].messages:
        notes.append(f"no annotations on {mapping.annotation_topic}")
    return labels, notes
