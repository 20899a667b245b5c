"""Play data as rosbag2 bags: episodes with their annotations, and bags of labelled segments.

Topics of a play bag:
  /play/steps         playseg_msgs/msg/PlayStep    every observation of every episode, in step order
  /play/annotations   playseg_msgs/msg/Annotation  the human labels of annotated episodes (D_ann)
  /play/ground_truth  playseg_msgs/msg/Annotation  the true segments, for evaluation only
A segment bag has /segments (playseg_msgs/msg/LabelledSegment), one self-contained message per segment.

What the data is travels in metadata.yaml's ``custom_data`` (`DataInfo`): the feature schema
(data/features.py: which camera the PlaySteps' image is, the state's dtype, the action's kind), the domain
and the instruction list. A bag without it reads with `DEFAULT_CAMERA`, float32 states and a continuous
action. Readers validate as they go and raise `BagError` naming the bag, topic, episode and step.
"""

from __future__ import annotations

import importlib
import json
from collections.abc import Callable, Collection, Iterable, Iterator
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from playseg_core.data.dataset import PlayDataset
from playseg_core.data.episode import Episode, Segment, SegmentClip
from playseg_core.data.features import DEFAULT_CAMERA, FeatureError, Features, conform_episode
from playseg_core.errors import PlaysegError
from playseg_ros.bag import BagError, BagReader, BagSummary, BagWriter, topic_info
from playseg_ros.messages import (
    ANNOTATION,
    LABELLED_SEGMENT,
    PLAY_STEP,
    EpisodeBuilder,
    StepError,
    annotation_message,
    clip_from_labelled,
    episode_messages,
    labelled_segment_message,
    segment_from_annotation,
    stamp_ns,
)
from playseg_ros.typestore import playseg_typestore, typestore_for

STEPS_TOPIC = "/play/steps"
ANNOTATIONS_TOPIC = "/play/annotations"
GROUND_TRUTH_TOPIC = "/play/ground_truth"
SEGMENTS_TOPIC = "/segments"
TOPIC_TYPES = {
    STEPS_TOPIC: PLAY_STEP,
    ANNOTATIONS_TOPIC: ANNOTATION,
    GROUND_TRUTH_TOPIC: ANNOTATION,
    SEGMENTS_TOPIC: LABELLED_SEGMENT,
}
DEFAULT_START_NS = 1_700_000_000_000_000_000
DEFAULT_STEP_PERIOD_NS = 100_000_000  # 10 Hz, when nothing declares a step rate


def _serialize(msg: Any, type_name: str) -> bytes:
    return playseg_typestore().serialize_cdr(msg, type_name)


@dataclass(frozen=True)
class DataInfo:
    """What a source declares about its data: the features, the domain, the instruction list.

    A play or segment bag keeps it in metadata.yaml's ``custom_data``; a dataset in its info.json.
    """

    features: Features | None = None
    domain: str | None = None
    instructions: tuple[str, ...] = ()

    @classmethod
    def of_dataset(cls, dataset: PlayDataset) -> DataInfo:
        return cls(dataset.features, dataset.domain, dataset.instructions)

    def custom_data(self) -> dict[str, str]:
        data = {}
        if self.features is not None:
            data["playseg.features"] = json.dumps(self.features.to_json(), sort_keys=True)
        if self.domain:
            data["playseg.domain"] = self.domain
        if self.instructions:
            data["playseg.instructions"] = json.dumps(list(self.instructions))
        return data

    @classmethod
    def of_bag(cls, reader: BagReader) -> DataInfo:
        data = reader.custom_data
        try:
            features = (
                Features.from_json(json.loads(data["playseg.features"]))
                if "playseg.features" in data
                else None
            )
            instructions = tuple(json.loads(data.get("playseg.instructions", "[]")))
        except (json.JSONDecodeError, FeatureError, TypeError) as error:
            raise BagError(reader.path, f"metadata.yaml custom_data: {error}") from None
        return cls(features, data.get("playseg.domain") or None, instructions)

    @property
    def camera(self) -> str:
        """The feature name of a PlayStep's image when the step names none (one camera: the first declared)."""
        return self.features.cameras[0] if self.features and self.features.cameras else DEFAULT_CAMERA

    def conform(self, episode: Episode, bag: Path) -> Episode:
        """``episode`` as the declared features say (state dtype), checked against them; BagError naming
        the bag and episode when it does not fit."""
        if self.features is None:
            return episode
        episode = conform_episode(episode, self.features)
        try:
            self.features.check_episode(episode)
        except FeatureError as error:
            raise BagError(bag, str(error), STEPS_TOPIC, episode.episode_id) from None
        return episode


def read_play_bag_info(path: Path | str) -> DataInfo:
    """The data a bag declares (features, domain, instructions), without reading its messages."""
    with BagReader(path) as reader:
        return DataInfo.of_bag(reader)


def write_play_bag(
    path: Path | str,
    episodes: Iterable[Episode],
    annotated: bool | Collection[str],
    *,
    ground_truth: bool = True,
    start_ns: int = DEFAULT_START_NS,
    step_period_ns: int | None = None,
    frame_id: str = "play",
    info: DataInfo | None = None,
    **writer_options: Any,
) -> BagSummary:
    """Write episodes as a play bag at ``path`` (a new directory).

    ``annotated``: True (every episode), False (none) or the ids of the annotated episodes; their
    segments go to /play/annotations. With ``ground_truth`` every episode's segments also go to
    /play/ground_truth. Step t of the k-th episode is stamped ``step_period_ns`` after the previous
    step (default: the declared step rate, else 10 Hz); an episode's annotations are stamped with its
    last step. Episodes must fit the declared features (BagError naming the episode otherwise). ``writer_options`` go to
    `BagWriter` (max_file_bytes, max_file_duration_ns, chunk_bytes, compression). ``info`` (features,
    domain, instructions) goes to metadata.yaml's custom_data. If writing fails, nothing is left at
    ``path``.
    """
    custom_data = info.custom_data() if info else {}
    fps = info.features.fps if info and info.features else None
    if step_period_ns is None:
        step_period_ns = round(1e9 / fps) if fps else DEFAULT_STEP_PERIOD_NS
    with BagWriter(path, custom_data=custom_data, **writer_options) as writer:
        writer.add_topic(topic_info(STEPS_TOPIC, PLAY_STEP))
        if annotated:
            writer.add_topic(topic_info(ANNOTATIONS_TOPIC, ANNOTATION))
        if ground_truth:
            writer.add_topic(topic_info(GROUND_TRUTH_TOPIC, ANNOTATION))
        now = start_ns
        for episode in episodes:
            if info is not None:
                episode = info.conform(episode, Path(path))
            stamps = now + step_period_ns * np.arange(episode.num_steps + 1, dtype=np.int64)
            for msg in episode_messages(episode, stamps.tolist(), frame_id):
                writer.write(STEPS_TOPIC, _serialize(msg, PLAY_STEP), stamp_ns(msg.header))
            end_stamp = int(stamps[-1])
            is_annotated = annotated is True or (
                not isinstance(annotated, bool) and episode.episode_id in annotated
            )
            topics = ([ANNOTATIONS_TOPIC] if is_annotated else []) + (
                [GROUND_TRUTH_TOPIC] if ground_truth else []
            )
            for topic in topics:
                for segment in episode.segments:
                    msg = annotation_message(episode.episode_id, segment, end_stamp, frame_id)
                    writer.write(topic, _serialize(msg, ANNOTATION), end_stamp)
            now = end_stamp + step_period_ns
    return writer.close()


def _check_topics(reader: BagReader, required: Collection[str]) -> None:
    present = reader.topics
    for topic in required:
        if topic not in present:
            raise BagError(reader.path, f"topic missing (the bag has {sorted(present)})", topic)
    for topic, actual in present.items():
        expected = TOPIC_TYPES.get(topic)
        if expected is None:
            continue
        if actual != expected:
            raise BagError(reader.path, f"message type is {actual!r}, expected {expected!r}", topic)
        digest = reader.topic_hash(topic)
        if typestore_for(expected, digest) is None:
            raise BagError(
                reader.path, f"{expected} in the bag has an unknown definition (type hash {digest})", topic
            )


def _deserialize(reader: BagReader, data: bytes, topic: str) -> Any:
    """One message, decoded with the definition the bag recorded (today's or an earlier one)."""
    store = typestore_for(TOPIC_TYPES[topic], reader.topic_hash(topic)) or playseg_typestore()
    try:
        return store.deserialize_cdr(data, TOPIC_TYPES[topic])
    except Exception as error:  # rosbags raises assorted errors for malformed CDR
        raise BagError(reader.path, f"cannot deserialize message: {error}", topic) from error


def _located(reader: BagReader, topic: str, error: StepError) -> BagError:
    """A message's StepError with the bag and topic it came from."""
    return BagError(reader.path, error.detail, topic, error.episode, error.step)


def _read_annotations(reader: BagReader, topic: str) -> dict[str, list[Segment]]:
    by_episode: dict[str, list[Segment]] = {}
    for raw in reader.messages([topic]):
        msg = _deserialize(reader, raw.data, topic)
        try:
            segment = segment_from_annotation(msg)
        except StepError as error:
            raise _located(reader, topic, error) from None
        by_episode.setdefault(msg.episode_id, []).append(segment)
    return by_episode


def _fit_segments(
    reader: BagReader, topic: str, episode_id: str, segments: list[Segment], num_steps: int
) -> list[Segment]:
    """The annotations of one episode, sorted, each checked against the episode's length."""
    previous_end = 0
    for segment in sorted(segments):
        if segment.end > num_steps:
            raise BagError(
                reader.path,
                f"annotation [{segment.start}, {segment.end}) ends after the episode's last step {num_steps}",
                topic,
                episode_id,
                segment.end,
            )
        if segment.start < previous_end:
            raise BagError(
                reader.path,
                f"annotation [{segment.start}, {segment.end}) overlaps the previous one (ends at {previous_end})",
                topic,
                episode_id,
                segment.start,
            )
        previous_end = segment.end
    return sorted(segments)


INCOMPLETE_EPISODES = ("error", "drop", "keep")
"""What `iter_play_bag` does with an episode the bag cuts off before its ``episode_end``."""


def iter_play_bag(
    path: Path | str,
    truth: bool = False,
    incomplete: str = "error",
    camera: str | None = None,
    on_incomplete: Callable[[str, int], None] | None = None,
) -> Iterator[Episode]:
    """Episodes of a play bag, each as soon as its last step is read.

    The PlaySteps' image is the declared camera; in a bag that declares none, ``camera`` (the feature a
    model reads, as the live segmenter does) or `DEFAULT_CAMERA`.

    Each episode's ``source`` is the bag (path, the topics read, its first message time) and its
    ``timestamps`` are its PlaySteps' header stamps, in seconds from that time (`_recorded`).

    Segments come from /play/annotations (episodes without annotations get none) or, with ``truth``,
    from /play/ground_truth. An episode whose stream stops before ``episode_end`` (e.g. a recovered
    recording) is a BagError with ``incomplete="error"``; with "drop" it is skipped, with "keep" it ends at
    its last observation (segments that end later are dropped); either way ``on_incomplete(episode_id,
    last_step)`` is told.
    """
    if incomplete not in INCOMPLETE_EPISODES:
        raise PlaysegError(f"incomplete must be one of {INCOMPLETE_EPISODES}, got {incomplete!r}")
    segment_topic = GROUND_TRUTH_TOPIC if truth else ANNOTATIONS_TOPIC
    with BagReader(path) as reader:
        info = DataInfo.of_bag(reader)
        image = info.camera if info.features is not None or camera is None else camera
        _check_topics(reader, [STEPS_TOPIC, GROUND_TRUTH_TOPIC] if truth else [STEPS_TOPIC])
        segments = _read_annotations(reader, segment_topic) if segment_topic in reader.topics else {}
        topics = [STEPS_TOPIC] + ([segment_topic] if segment_topic in reader.topics else [])
        source = {"bag": str(reader.path), "topics": topics, "start_ns": reader.start_time}
        open_episodes: dict[str, EpisodeBuilder] = {}
        finished: set[str] = set()
        for raw in reader.messages([STEPS_TOPIC]):
            msg = _deserialize(reader, raw.data, STEPS_TOPIC)
            episode_id = msg.episode_id
            if episode_id in finished:
                raise BagError(
                    reader.path,
                    "step of an episode that already ended",
                    STEPS_TOPIC,
                    episode_id,
                    int(msg.step),
                )
            builder = open_episodes.setdefault(episode_id, EpisodeBuilder(episode_id, camera=image))
            try:
                builder.add(msg)
            except StepError as error:
                raise _located(reader, STEPS_TOPIC, error) from None
            if builder.finished:
                del open_episodes[episode_id]
                finished.add(episode_id)
                num_steps = len(builder.actions)
                episode_segments = _fit_segments(
                    reader, segment_topic, episode_id, segments.pop(episode_id, []), num_steps
                )
                try:
                    episode = builder.build(episode_segments)
                except StepError as error:
                    raise _located(reader, STEPS_TOPIC, error) from None
                yield info.conform(_recorded(episode, builder, reader, source), reader.path)
        if open_episodes and incomplete == "error":
            episode_id, builder = next(iter(open_episodes.items()))
            raise BagError(
                reader.path,
                "the bag ends before this episode's episode_end (a recovered recording? skip or keep it: "
                "incomplete='drop'/'keep', `playseg segment --keep-incomplete`)",
                STEPS_TOPIC,
                episode_id,
                builder.next_step - 1,
            )
        for episode_id, builder in open_episodes.items():
            if on_incomplete is not None:
                on_incomplete(episode_id, builder.next_step - 1)
            if incomplete == "keep" and builder.num_observations > 1:
                last = builder.num_observations - 1
                kept = [s for s in segments.get(episode_id, []) if s.end <= last]
                episode = builder.build(
                    _fit_segments(reader, segment_topic, episode_id, kept, last), truncated=True
                )
                yield info.conform(_recorded(episode, builder, reader, source), reader.path)
        for episode_id, orphans in segments.items():
            if episode_id not in open_episodes:
                raise BagError(
                    reader.path,
                    f"annotation [{orphans[0].start}, {orphans[0].end}) of an episode with no steps in the bag",
                    segment_topic,
                    episode_id,
                    orphans[0].start,
                )


def _recorded(
    episode: Episode, builder: EpisodeBuilder, reader: BagReader, source: dict[str, Any]
) -> Episode:
    """``episode`` with its bag as ``source`` and its PlaySteps' header stamps as timestamps, in seconds
    from the bag's first message (as `playseg convert` counts a robot bag's times). Stamps that are all
    zero (a publisher that does not stamp) are no clock: step / fps. A stamp earlier than the previous
    step's is a BagError naming the step."""
    stamps = np.asarray(builder.stamps[: episode.num_steps + 1], dtype=np.int64)
    back = np.flatnonzero(np.diff(stamps) < 0)
    if len(back):
        step = int(back[0]) + 1
        raise BagError(
            reader.path,
            f"header stamp {stamps[step]} ns is earlier than the previous step's ({stamps[step - 1]} ns)",
            STEPS_TOPIC,
            episode.episode_id,
            builder.first_step + step,
        )
    times = (stamps - int(source["start_ns"])) / 1e9 if stamps.any() else None
    return replace(episode, timestamps=times, source=source)


def read_play_bag(path: Path | str, truth: bool = False, incomplete: str = "error") -> list[Episode]:
    """All episodes of a play bag (see `iter_play_bag`)."""
    return list(iter_play_bag(path, truth=truth, incomplete=incomplete))


def write_segment_bag(
    path: Path | str,
    clips: Iterable[SegmentClip],
    *,
    start_ns: int = DEFAULT_START_NS,
    period_ns: int = DEFAULT_STEP_PERIOD_NS,
    frame_id: str = "play",
    info: DataInfo | None = None,
    **writer_options: Any,
) -> BagSummary:
    """Write labelled segments to /segments, one LabelledSegment each, ``period_ns`` apart."""
    with BagWriter(path, custom_data=info.custom_data() if info else {}, **writer_options) as writer:
        writer.add_topic(topic_info(SEGMENTS_TOPIC, LABELLED_SEGMENT))
        for i, clip in enumerate(clips):
            stamp = start_ns + i * period_ns
            msg = labelled_segment_message(clip, stamp, frame_id=frame_id)
            writer.write(SEGMENTS_TOPIC, _serialize(msg, LABELLED_SEGMENT), stamp)
    return writer.close()


def iter_segment_bag(path: Path | str) -> Iterator[SegmentClip]:
    """The labelled segments of a segment bag, in order."""
    with BagReader(path) as reader:
        info = DataInfo.of_bag(reader)
        _check_topics(reader, [SEGMENTS_TOPIC])
        for raw in reader.messages([SEGMENTS_TOPIC]):
            msg = _deserialize(reader, raw.data, SEGMENTS_TOPIC)
            try:
                clip = clip_from_labelled(msg, info.camera)
            except StepError as error:
                raise _located(reader, SEGMENTS_TOPIC, error) from None
            yield clip


def read_segment_bag(path: Path | str) -> list[SegmentClip]:
    return list(iter_segment_bag(path))


DATASET_BAGS: dict[str, tuple[tuple[str, ...], bool]] = {
    "annotated": (("train", "val"), True),
    "play": (("play",), False),
    "test": (("test",), False),
}
"""Bags written from a dataset: name -> (dataset splits, in dataset order; with /play/annotations)."""


def dataset_bag_episodes(dataset: PlayDataset, name: str) -> Iterator[Episode]:
    """The episodes of the dataset bag ``name`` (see DATASET_BAGS), in dataset order, with true segments."""
    if name not in DATASET_BAGS:
        raise KeyError(f"unknown dataset bag {name!r} (expected one of {sorted(DATASET_BAGS)})")
    splits, _ = DATASET_BAGS[name]
    indices = sorted(index for split in splits for index in dataset.episode_indices(split))
    for index in indices:
        yield dataset.episode(index, truth=True)


def write_dataset_bags(
    dataset_dir: Path | str, out_dir: Path | str, **writer_options: Any
) -> dict[str, BagSummary]:
    """Write a dataset's episodes as three play bags under ``out_dir``.

    ``annotated/``: the train+val episodes, labelled on /play/annotations and /play/ground_truth;
    ``play/``: the unannotated play episodes, /play/ground_truth only; ``test/``: the held-out test
    episodes, /play/ground_truth only. A split without episodes gives a bag without episodes.
    Episodes are streamed from the memory-mapped dataset, one at a time.
    """
    dataset = PlayDataset.open(dataset_dir)
    out = Path(out_dir)
    for name in DATASET_BAGS:  # refuse before writing anything, so no half set of bags is left
        if (out / name).exists():
            raise FileExistsError(f"bag {str(out / name)!r}: already exists (remove it to write new bags)")
    info = DataInfo.of_dataset(dataset)
    summaries: dict[str, BagSummary] = {}
    for name, (_, annotated) in DATASET_BAGS.items():
        summaries[name] = write_play_bag(
            out / name, dataset_bag_episodes(dataset, name), annotated, info=info, **writer_options
        )
    return summaries


GENERATED_BAGS_HOOK = "write_generated_bags"
"""What a domain's ROS package (``playseg_ros.<domain>``) may define to write its own bags for
`playseg generate --bag`: ``(dataset_dir, out_dir, images=..., workers=...) -> summary lines``."""


def write_generated_bags(
    domain: str | None, dataset_dir: Path | str, out_dir: Path | str, images: str = "raw", workers: int = 1
) -> list[str]:
    """`playseg generate --bag`: the bags of the domain's ROS package when it has the hook
    (`GENERATED_BAGS_HOOK`, e.g. standard-message robot bags), else play bags (`write_dataset_bags`:
    PlayStep messages with raw frames). Returns one summary line per bag or bag directory written."""
    hook = None
    if domain:
        try:
            package = importlib.import_module(f"playseg_ros.{domain}")
        except ModuleNotFoundError as error:
            if error.name != f"playseg_ros.{domain}":
                raise
        else:
            hook = getattr(package, GENERATED_BAGS_HOOK, None)
    if hook is not None:
        return list(hook(dataset_dir, out_dir, images=images, workers=workers))
    if images != "raw":
        raise PlaysegError(f"--images {images}: play bags (playseg_msgs/PlayStep) hold raw frames only")
    lines = []
    for name, bag in write_dataset_bags(dataset_dir, out_dir).items():
        size = sum(f.stat().st_size for f in bag.path.rglob("*") if f.is_file())
        lines.append(f"{bag.path}: {name} bag, {bag.message_count} messages, {size / 1e6:.2f} MB")
    return lines


@dataclass
class AnnotatedData:
    """Annotated episodes with what their source declares about them."""

    episodes: list[Episode]
    info: DataInfo


def load_annotated(path: Path | str) -> AnnotatedData:
    """Annotated episodes from a play bag (its /play/annotations) or a playseg dataset (its 'train' split)."""
    path = Path(path)
    if (path / "metadata.yaml").is_file():
        info = read_play_bag_info(path)
        return AnnotatedData([episode for episode in iter_play_bag(path) if episode.segments], info)
    dataset = PlayDataset.open(path)
    return AnnotatedData(list(dataset.episodes("train")), DataInfo.of_dataset(dataset))
