# ruff: noqa: F811 (the tests take the imported fixture `bags` as an argument)
"""Times everywhere: converted episodes keep each step's recording time and their bag; `--labels-out` of
`convert --segment` and `segment` writes segments as sidecar labels that `convert` reads back as the same
segments (proposals round-trip to the bags)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml
from test_convert import T0, write_mapping
from test_convert_segment import (
    bags,  # noqa: F401 (the fixture: two bags and their mapping)
    convert_cli,
    untrained_model,
)

from playseg_core.data.dataset import DatasetWriter, PlayDataset
from playseg_core.data.episode import Episode, Segment
from playseg_ros.cli import main


def spans(dataset: PlayDataset, index: int) -> list[tuple[int, int, str]]:
    return [(s.start, s.end, s.instruction) for s in dataset.segments(index, truth=True) if s.instruction]


MAPPING_TOPICS = ["/annotations", "/camera/image_raw", "/cmd_vel", "/joint_states"]
"""Every topic the test mapping reads, as an episode's source lists them."""


def mapping_reading(labels: Path, path: Path) -> Path:
    """The test mapping with its labels from ``labels/<bag name>.yaml`` instead of its topic."""
    return write_mapping(path, annotations={"file": str(labels / "{name}.yaml")})


def test_converted_episodes_keep_their_times_and_bag(bags: dict[str, Path], tmp_path: Path) -> None:
    assert convert_cli([bags["annotated"]], tmp_path / "data", bags["mapping"]) == 0
    dataset = PlayDataset.open(tmp_path / "data")
    record = dataset.records[0]
    assert record.source == {"bag": str(bags["annotated"]), "topics": MAPPING_TOPICS, "start_ns": T0}
    times = dataset.timestamps(0)
    assert times.shape == (record.num_steps + 1,) and times.dtype == np.float64
    # steps are the camera frames thinned to 10 Hz, from the bag's first message
    np.testing.assert_allclose(np.diff(times), 0.1, atol=1e-6)
    assert dataset.episode(0).timestamps is not None
    np.testing.assert_array_equal(dataset.episode(0).timestamps, times)


def test_convert_segment_labels_out_round_trips_to_the_same_segments(
    bags: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert convert_cli([bags["play"]], tmp_path / "plain", bags["mapping"]) == 0
    plain = PlayDataset.open(tmp_path / "plain")
    model = untrained_model(tmp_path / "ps.pt", plain.features, plain.episode(0, truth=True))
    labels = tmp_path / "labels"
    both = [bags["play"], bags["annotated"]]
    code = convert_cli(
        both, tmp_path / "data", bags["mapping"], "--segment", str(model), "--labels-out", str(labels)
    )
    assert code == 0, capsys.readouterr().err
    assert sorted(p.name for p in labels.iterdir()) == ["annotated.yaml", "play.yaml"]
    proposed = yaml.safe_load((labels / "play.yaml").read_text())
    assert proposed["times"] == "from_start" and len(proposed["annotations"]) >= 2
    entry = proposed["annotations"][0]
    assert entry["provenance"].startswith("model:") and 0.0 < entry["confidence"] <= 1.0
    human = yaml.safe_load((labels / "annotated.yaml").read_text())["annotations"]
    assert [e["provenance"] for e in human] == ["human", "human"]

    # The labels, read back by convert from the sidecars, are the same segments.
    assert convert_cli(both, tmp_path / "again", mapping_reading(labels, tmp_path / "m.yaml")) == 0
    first, again = PlayDataset.open(tmp_path / "data"), PlayDataset.open(tmp_path / "again")
    ids = {r.episode_id: i for i, r in enumerate(first.records)}
    for i, record in enumerate(again.records):
        assert spans(again, i) == spans(first, ids[record.episode_id]), record.episode_id
        assert record.split in ("train", "val")  # labels now: annotated episodes


def test_segment_labels_out_writes_what_the_keep_rule_keeps(bags: dict[str, Path], tmp_path: Path) -> None:
    assert convert_cli([bags["play"]], tmp_path / "plain", bags["mapping"]) == 0
    plain = PlayDataset.open(tmp_path / "plain")
    episode = plain.episode(0, truth=True)
    probe = untrained_model(tmp_path / "probe.pt", plain.features, episode)
    assert main(["segment", "--model", str(probe), "--input", str(tmp_path / "plain"), "--splits", "play",
                 "--out", str(tmp_path / "all"), "--keep", "all"]) == 0  # fmt: skip
    confidences = sorted(s.confidence for s in PlayDataset.open(tmp_path / "all").segments(0, truth=True))
    threshold = float(np.median(confidences))
    model = untrained_model(tmp_path / "ps.pt", plain.features, episode, threshold)
    labels = tmp_path / "labels"
    assert main(["segment", "--model", str(model), "--input", str(tmp_path / "plain"), "--splits", "play",
                 "--out", str(tmp_path / "seg"), "--labels-out", str(labels)]) == 0  # fmt: skip
    segmented = PlayDataset.open(tmp_path / "seg")
    assert segmented.records[0].source == plain.records[0].source  # the bag is remembered
    np.testing.assert_array_equal(segmented.timestamps(0), plain.timestamps(0))
    kept = [(s.start, s.end, s.instruction) for s in segmented.segments(0, truth=True)
            if s.confidence >= threshold and s.instruction]  # fmt: skip
    assert 0 < len(kept) < len(confidences)
    assert convert_cli([bags["play"]], tmp_path / "back", mapping_reading(labels, tmp_path / "m.yaml")) == 0
    assert spans(PlayDataset.open(tmp_path / "back"), 0) == kept


def test_datasets_without_recorded_times_count_steps_at_their_rate(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    timed = Episode("timed", rng.random((5, 2), np.float32), timestamps=np.array([0, 0.5, 0.5, 2, 3, 7.5]))
    untimed = Episode("untimed", rng.random((3, 2), np.float32), segments=[Segment(0, 3, "a")])
    with DatasetWriter(tmp_path / "d", ["a"]) as writer:
        writer.add(timed, "train")
        writer.add(untimed, "train")
    dataset = PlayDataset.open(tmp_path / "d")
    np.testing.assert_array_equal(dataset.timestamps(0), [0, 0.5, 0.5, 2, 3, 7.5])
    np.testing.assert_array_equal(dataset.timestamps(1), [0, 1, 2, 3])  # no fps: one step a second
    with pytest.raises(ValueError, match="timestamps must be"):
        Episode("bad", rng.random((2, 2), np.float32), timestamps=np.array([0.0, 2.0, 1.0]))


REPEATED_STAMPS = [
    [0.0, 0.1, 0.2, 0.2, 0.3, 0.4, 0.4, 0.4, 0.5, 0.6, 0.7, 0.7],  # o2/o3 and o5..o7 recorded at once
    [0.7, 0.8, 0.9, 0.9, 1.0, 1.1],  # the bag's next episode starts on its predecessor's last stamp
]
"""Two episodes of one bag whose stamps repeat, inside an episode and across the two."""

SPANS_ON_REPEATS = [
    [(0, 3, "a"), (3, 6, "b"), (6, 7, "a"), (7, 11, "b")],  # every boundary on a repeated stamp
    [(0, 2, "b"), (3, 5, "a")],
]


def test_segments_round_trip_exactly_where_stamps_repeat(tmp_path: Path) -> None:
    """Segments -> sidecar times -> steps gives the same steps when consecutive observations share a
    stamp, both as `convert` maps a sidecar (labels_from_file, segments_of_episodes) and as the review
    page's store reads and saves it."""
    from playseg_ros.convert.annotations import labels_from_file, segments_of_episodes, write_labels_out
    from playseg_ros.review.store import Label, LabelStore

    rng = np.random.default_rng(0)
    source = {"bag": "/bags/run_01", "topics": ["/camera"], "start_ns": T0}
    with DatasetWriter(tmp_path / "d", ["a", "b"]) as writer:
        for k, (stamps, spans_k) in enumerate(zip(REPEATED_STAMPS, SPANS_ON_REPEATS, strict=True)):
            episode = Episode(
                f"run_01:{k}",
                rng.random((len(stamps) - 1, 2), np.float32),
                segments=[Segment(s, e, text) for s, e, text in spans_k],
                timestamps=np.array(stamps),
                source=source,
            )
            writer.add(episode, "train")
    dataset = PlayDataset.open(tmp_path / "d")

    labels_dir = tmp_path / "labels"
    (file,) = write_labels_out(dataset, labels_dir, lambda s: True, lambda i: "human")
    assert file.name == "run_01.yaml"
    # convert's reading: the file's times from the bag's start, over the bag's step times
    steps = [T0 + np.round(np.array(stamps) * 1e9).astype(np.int64) for stamps in REPEATED_STAMPS]
    segments, notes = segments_of_episodes(steps, labels_from_file(Path("/bags/run_01"), file, T0))
    assert notes == []
    assert [[(s.start, s.end, s.instruction) for s in ep] for ep in segments] == SPANS_ON_REPEATS

    # the review page's reading of the same file, and a save read back
    store = LabelStore(dataset, labels_dir)
    for index, spans_k in enumerate(SPANS_ON_REPEATS):
        labels = store.labels(index)
        assert labels is not None
        assert [(label.start, label.end, label.instruction) for label in labels] == spans_k
    moved = [Label(0, 2, "b"), Label(2, 5, "a"), Label(5, 7, "b"), Label(7, 10, "a")]
    store.save(0, moved, store.version(0))
    assert [(la.start, la.end, la.instruction) for la in store.labels(0) or []] == [
        (la.start, la.end, la.instruction) for la in moved
    ]
    second = store.labels(1)  # the other episode's labels in the shared file are untouched
    assert [(la.start, la.end) for la in second or []] == [(s, e) for s, e, _ in SPANS_ON_REPEATS[1]]


@pytest.mark.parametrize("value", [-1, 1.5, True, "2"])
def test_a_bad_skip_is_one_line_naming_its_key(tmp_path: Path, value: object) -> None:
    from playseg_ros.convert.annotations import labels_from_file
    from playseg_ros.convert.errors import ConvertError

    file = tmp_path / "run.yaml"
    file.write_text(yaml.safe_dump([{"start": 0.2, "end": 0.4, "instruction": "a", "end_skip": value}]))
    with pytest.raises(ConvertError, match=r"annotations\[0\], key 'end_skip': must be a whole number"):
        labels_from_file(tmp_path, file, T0)


def write_stamped_play_bag(path: Path, stamps: list[list[int]], log_delay_ns: int) -> list[Episode]:
    """A play bag (PlaySteps as a recorder writes them: each logged in arrival order, ``log_delay_ns``
    after its header stamp) of one episode per entry of ``stamps``; the first is annotated."""
    from dataclasses import replace

    from playseg_core.data.features import infer_features
    from playseg_ros.bag import BagWriter, topic_info
    from playseg_ros.messages import ANNOTATION, PLAY_STEP, annotation_message, episode_messages
    from playseg_ros.play_bags import ANNOTATIONS_TOPIC, STEPS_TOPIC, DataInfo
    from playseg_ros.typestore import playseg_typestore

    rng = np.random.default_rng(1)
    episodes = [
        Episode(
            f"play-{k}",
            rng.random((len(times) - 1, 2), np.float32),
            images={"observation.images.top": rng.integers(0, 255, (len(times), 8, 8, 3), np.uint8)},
            segments=[Segment(0, 2, "a"), Segment(2, len(times) - 1, "b")] if k == 0 else [],
        )
        for k, times in enumerate(stamps)
    ]
    info = DataInfo(replace(infer_features(episodes[0]), fps=10.0), None, ("a", "b"))
    store = playseg_typestore()
    with BagWriter(path, custom_data=info.custom_data()) as writer:
        writer.add_topic(topic_info(STEPS_TOPIC, PLAY_STEP))
        writer.add_topic(topic_info(ANNOTATIONS_TOPIC, ANNOTATION))
        for episode, times in zip(episodes, stamps, strict=True):
            for msg, arrival in zip(
                episode_messages(episode, times), np.maximum.accumulate(times), strict=True
            ):
                writer.write(STEPS_TOPIC, store.serialize_cdr(msg, PLAY_STEP), int(arrival) + log_delay_ns)
            for segment in episode.segments:
                msg = annotation_message(episode.episode_id, segment, times[-1])
                writer.write(
                    ANNOTATIONS_TOPIC, store.serialize_cdr(msg, ANNOTATION), times[-1] + log_delay_ns
                )
    return episodes


def test_play_bags_convert_with_their_header_stamps(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """playseg's own play bags (PlayStep) convert with each step's header stamp, not step / fps: irregular
    steps, a repeated stamp and a pause keep their times, counted from the bag's first message."""
    ms = 1_000_000
    stamps = [
        [T0 + t * ms for t in (0, 100, 100, 350, 400, 520)],
        [T0 + t * ms for t in (2000, 2100, 2200, 2200)],
    ]
    bag = tmp_path / "recorded"
    write_stamped_play_bag(bag, stamps, log_delay_ns=5 * ms)
    assert main(["convert", str(bag), "--out", str(tmp_path / "data"), "--quiet"]) == 0, capsys.readouterr()
    dataset = PlayDataset.open(tmp_path / "data")
    start = T0 + 5 * ms  # the bag's first message: its log time
    by_id = {record.episode_id: i for i, record in enumerate(dataset.records)}
    for k, times in enumerate(stamps):
        index = by_id[f"play-{k}"]
        np.testing.assert_allclose(dataset.timestamps(index), (np.array(times) - start) / 1e9, atol=1e-9)
        assert dataset.records[index].source == {
            "bag": str(bag), "topics": ["/play/steps", "/play/annotations"], "start_ns": start
        }  # fmt: skip
    assert spans(dataset, by_id["play-0"]) == [(0, 2, "a"), (2, 5, "b")]

    # a stamp that goes back in time: the bag fails with one line naming the episode and step
    write_stamped_play_bag(tmp_path / "backwards", [[T0, T0 + 100 * ms, T0 + 50 * ms, T0 + 150 * ms]], 0)
    capsys.readouterr()
    assert main(["convert", str(tmp_path / "backwards"), "--out", str(tmp_path / "bad"), "--quiet"]) == 1
    err = capsys.readouterr().err
    assert "header stamp" in err and "'play-0'" in err and "step 2" in err, err
