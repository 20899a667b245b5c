"""One robot bag through a mapping: the step clock, aligned features, episodes and their segments.

Steps follow the primary feature's clock: its samples are thinned to the mapping's fps (a sample is taken
when at least one period, less half the primary's own typical interval, has passed since the last one
taken), so step times are real primary message times and never drift from them. A gap in the primary
longer than a period and a half counts the steps it should have held as dropped. Every other feature is
aligned onto the step times (alignment.py); a step where any feature has no sample within its tolerance
is dropped, never filled in, and reported once per feature (count and first time).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from playseg_core.data.episode import Episode, Segment
from playseg_core.data.features import ACTION, STATE, Feature, Features
from playseg_ros.convert.alignment import Alignment, align
from playseg_ros.convert.annotations import (
    TimedLabel,
    labels_from_file,
    labels_from_topic,
    segments_of_episodes,
    sidecar_path,
)
from playseg_ros.convert.decode import IMAGE_TYPES, DecodeError, NumericDecoder, decode_image
from playseg_ros.convert.errors import ConvertError
from playseg_ros.convert.mapping import ConvertMapping, DerivedAction, TopicFeature
from playseg_ros.convert.source import TopicSamples, open_bag, read_topics


@dataclass
class BagEpisodes:
    """What one bag gives: its episodes (with segments where labelled), their schema, and notes."""

    episodes: list[Episode]
    features: Features
    dropped_steps: int = 0
    notes: list[str] = field(default_factory=list)


def step_times(
    primary: np.ndarray, period_ns: int, episode_gap_ns: int | None = None
) -> tuple[np.ndarray, int, list[str]]:
    """The primary's sample indices taken as steps, the number of steps its gaps miss (a gap longer than
    ``episode_gap_ns`` ends an episode and misses nothing), and notes."""
    if len(primary) == 0:
        return np.zeros(0, dtype=np.int64), 0, []
    intervals = np.diff(primary)
    typical = int(np.median(intervals)) if len(intervals) else period_ns
    slack = min(typical // 2, period_ns // 2)
    taken = [0]
    missing = 0
    first_gap: int | None = None
    for i in range(1, len(primary)):
        since = int(primary[i] - primary[taken[-1]])
        if since >= period_ns - slack:
            if since > period_ns + period_ns // 2 and (episode_gap_ns is None or since <= episode_gap_ns):
                missing += round(since / period_ns) - 1
                first_gap = first_gap if first_gap is not None else int(primary[taken[-1]])
            taken.append(i)
    notes = []
    if missing:
        notes.append(f"primary clock: {missing} step(s) missing in gaps, first after {first_gap / 1e9:.3f}")
    return np.asarray(taken, dtype=np.int64), missing, notes


def episode_starts(step_ns: np.ndarray, mapping: ConvertMapping, markers: np.ndarray | None) -> list[int]:
    """Indices of the steps that begin an episode."""
    starts = [0]
    if mapping.split == "gap" and mapping.gap_ns is not None:
        starts += [int(i) + 1 for i in np.flatnonzero(np.diff(step_ns) > mapping.gap_ns)]
    elif mapping.split == "marker" and markers is not None and len(markers):
        cut = np.searchsorted(step_ns, markers, side="left")  # a marker starts an episode at the next step
        starts += [int(i) for i in cut if 0 < i < len(step_ns)]
    return sorted(set(starts))


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
    notes: list[str] = []
    primary = mapping.features[mapping.primary]
    primary_samples = samples[primary.topic]
    episode_gap = mapping.gap_ns if mapping.split == "gap" else None
    taken, dropped, clock_notes = step_times(primary_samples.stamps, mapping.period_ns, episode_gap)
    notes += clock_notes
    steps = primary_samples.stamps[taken]
    # every feature's sample index (or pair) per step; the primary reads its own samples
    alignments: dict[str, Alignment] = {}
    keep = np.ones(len(steps), dtype=bool)
    for feature in mapping.topic_features:
        if feature.name == primary.name:
            zeros = np.zeros(len(steps))
            alignments[feature.name] = Alignment(taken, taken, zeros, np.ones(len(steps), dtype=bool))
            continue
        topic = samples[feature.topic]
        alignment = align(steps, topic.stamps, feature.align, feature.tolerance_ns)
        unmatched = ~alignment.matched
        if unmatched.any():
            first = int(steps[np.flatnonzero(unmatched)[0]])
            notes.append(
                f"{feature.name} ({feature.topic}): {int(unmatched.sum())} step(s) without a sample within "
                f"{feature.tolerance_ns / 1e6:g} ms ({feature.align}); dropped, first at {first / 1e9:.3f}"
            )
        alignments[feature.name] = alignment
        keep &= alignment.matched
    dropped += int((~keep).sum())
    kept = np.flatnonzero(keep)
    steps = steps[kept]
    alignments = {
        name: Alignment(a.lo[kept], a.hi[kept], a.weight[kept], a.matched[kept])
        for name, a in alignments.items()
    }
    # decoded rows of every kept step
    rows: dict[str, np.ndarray] = {}
    features: list[Feature] = []
    for feature in mapping.topic_features:
        array, schema = _feature_rows(bag, feature, samples[feature.topic], alignments[feature.name])
        rows[feature.name] = array
        features.append(schema)
    derived = mapping.action if isinstance(mapping.action, DerivedAction) else None
    if derived is not None:
        source = next(f for f in features if f.name == derived.of)
        features.append(
            Feature(
                ACTION, "action", "float32", source.shape, source.names, low=derived.low, high=derived.high
            )
        )
    schema = Features.of(features, mapping.fps)
    # episodes
    markers = samples[mapping.marker_topic].stamps if mapping.marker_topic else None
    starts = episode_starts(steps, mapping, markers)
    bounds = list(zip(starts, [*starts[1:], len(steps)], strict=True))
    short = [
        (a, b) for a, b in bounds if b - a - 1 < mapping.min_steps
    ]  # b - a observations, one action less
    if short:
        dropped += sum(b - a for a, b in short)
        notes.append(f"{len(short)} episode(s) with fewer than {mapping.min_steps} steps; dropped")
        bounds = [(a, b) for a, b in bounds if b - a - 1 >= mapping.min_steps]
    labels, label_notes = _labels(bag, mapping, samples, bag_start_ns)
    notes += label_notes
    segments, label_notes = segments_of_episodes([steps[a:b] for a, b in bounds], labels)
    notes += label_notes
    episodes = []
    name = bag.name if bag.is_dir() else bag.stem
    for k, ((a, b), episode_segments) in enumerate(zip(bounds, segments, strict=True)):
        episodes.append(_episode(f"{name}:{k}", rows, a, b, mapping, episode_segments))
    return BagEpisodes(episodes, schema, dropped, notes)


def _episode(
    episode_id: str,
    rows: dict[str, np.ndarray],
    a: int,
    b: int,
    mapping: ConvertMapping,
    segments: list[Segment],
) -> Episode:
    """Steps a..b-1 as an episode: b-a observations, b-a-1 actions (the last observation has none)."""
    if isinstance(mapping.action, DerivedAction):
        source = rows[mapping.action.of][a:b]
        actions = source[1:] - source[:-1] if mapping.action.derive == "delta" else source[1:]
    else:
        actions = rows[ACTION][a : b - 1]
    images = {name: rows[name][a:b] for name in mapping.features if mapping.features[name].is_image}
    state = rows[STATE][a:b] if STATE in mapping.features else None
    return Episode(episode_id, np.ascontiguousarray(actions, dtype=np.float32), images, state, segments)


def _feature_rows(
    bag: Path, feature: TopicFeature, topic: TopicSamples, alignment: Alignment
) -> tuple[np.ndarray, Feature]:
    """The feature's row at every step (decoding only the samples the steps read) and its schema."""
    if feature.is_image:
        if topic.msgtype not in IMAGE_TYPES:
            raise ConvertError(
                bag, f"type {topic.msgtype} is not an image ({' or '.join(IMAGE_TYPES)})", topic.topic
            )
        frames: list[np.ndarray] = []
        for i in alignment.lo.tolist():
            image = _decoded(bag, topic, i, lambda m: decode_image(m, topic.msgtype, feature.resize))
            if frames and image.shape != frames[0].shape:
                raise ConvertError(
                    bag,
                    f"image of {image.shape[1]}x{image.shape[0]}, earlier ones {frames[0].shape[1]}x"
                    f"{frames[0].shape[0]} (resize to one size: 'resize')",
                    topic.topic,
                    time_ns=int(topic.stamps[i]),
                )
            frames.append(image)
        if not frames:
            shape: tuple[int, ...] = (*(feature.resize[::-1] if feature.resize else (0, 0)), 3)
            return np.zeros((0, *shape), np.uint8), Feature(feature.name, "image", "uint8", shape)
        array = np.stack(frames)
        return array, Feature(feature.name, "image", "uint8", tuple(array.shape[1:]))
    if not topic.messages:
        raise ConvertError(bag, "no messages", topic.topic)
    decoder = _decoded(
        bag,
        topic,
        0,
        lambda m: NumericDecoder.of_first(m, topic.msgtype, feature.fields, feature.joints),
    )
    needed = sorted(set(alignment.lo.tolist()) | set(alignment.hi.tolist()))
    values = np.zeros((len(topic.messages), decoder.size), dtype=np.float32)
    for i in needed:
        values[i] = _decoded(bag, topic, i, decoder.decode)
    array = alignment.take(values) if len(alignment.lo) else np.zeros((0, decoder.size), np.float32)
    kind = "action" if feature.name == ACTION else "state"
    for bound, key in ((feature.low, "low"), (feature.high, "high")):
        if bound is not None and len(bound) != decoder.size:
            raise ConvertError(
                bag, f"mapping gives {len(bound)} {key} bounds for {decoder.size} values", topic.topic
            )
    return array, Feature(
        feature.name, kind, "float32", (decoder.size,), decoder.names, low=feature.low, high=feature.high
    )


def _decoded(bag: Path, topic: TopicSamples, i: int, decode: Callable[[Any], Any]) -> Any:
    try:
        return decode(topic.messages[i])
    except DecodeError as error:
        raise ConvertError(bag, str(error), topic.topic, error.field, int(topic.stamps[i])) from None


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
        file = sidecar_path(bag, mapping.annotation_file)
        if file.is_file():
            labels += labels_from_file(bag, file, bag_start_ns)
        else:
            notes.append(f"no annotations file {str(file)!r}")
    if mapping.annotation_topic and not samples[mapping.annotation_topic].messages:
        notes.append(f"no annotations on {mapping.annotation_topic}")
    return labels, notes
