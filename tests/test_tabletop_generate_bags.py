"""`playseg generate --domain tabletop --bag`: the dataset's splits as standard-message robot bags, which
`playseg convert` with the written mapping turns back into the dataset's episodes."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from rosbags.highlevel import AnyReader

from playseg_core.data.dataset import PlayDataset
from playseg_core.data.episode import Episode
from playseg_core.domains.tabletop.play import PlayConfig
from playseg_core.domains.tabletop.robot_log import dataset_play_config, replay_dataset_episode
from playseg_core.domains.tabletop.spec import CAMERA
from playseg_ros.cli import main as cli_main
from playseg_ros.play_bags import DATASET_BAGS, write_generated_bags
from playseg_ros.tabletop.bags import (
    ANNOTATION_TOPIC,
    CAMERA_TOPIC,
    COMMAND_TOPIC,
    JOINT_TOPIC,
    TRUTH_FILE,
    typestore,
)

pytestmark = pytest.mark.slow  # the module's robot bags are generated play


@pytest.fixture(scope="module")
def generated(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("ttgen") / "tiny"
    argv = ["generate", "--domain", "tabletop", "--preset", "tiny", "--out", str(out), "--quiet", "--bag"]
    assert cli_main([*argv, "--workers", "2"]) == 0
    return out


def episodes_of(dataset: PlayDataset, name: str, truth: bool) -> dict[str, Episode]:
    splits, _ = DATASET_BAGS[name]
    indices = sorted(i for split in splits for i in dataset.episode_indices(split))
    return {dataset.records[i].episode_id: dataset.episode(i, truth=truth) for i in indices}


def spans(episode: Episode) -> list[tuple[int, int, str]]:
    return [(s.start, s.end, s.instruction) for s in episode.segments]


@pytest.mark.parametrize("name", list(DATASET_BAGS))
def test_convert_gives_back_the_dataset_episodes(generated: Path, tmp_path: Path, name: str) -> None:
    dataset = PlayDataset.open(generated)
    bags = generated / "bags"
    for mapping, truth in (("mapping.yaml", False), ("mapping_truth.yaml", True)):
        if truth and name == "annotated":
            continue  # its annotations are the ground truth already
        out = tmp_path / mapping
        argv = ["convert", str(bags / name), "--out", str(out), "--mapping", str(bags / mapping), "--quiet"]
        assert cli_main(argv) == 0
        want = episodes_of(dataset, name, truth)
        assert want, f"the tiny preset has no episodes for the {name} bags"
        converted = PlayDataset.open(out)
        assert converted.domain == dataset.domain == "tabletop"  # the mapping names it: its encoders train
        got = {Path(r.extra["bag"]).name: converted.episode(r.index, truth=True) for r in converted.records}
        assert sorted(got) == sorted(want)
        for episode_id, episode in got.items():
            expected = want[episode_id]
            np.testing.assert_array_equal(episode.images[CAMERA], expected.images[CAMERA])
            np.testing.assert_array_equal(episode.actions, expected.actions)
            assert episode.state is not None and episode.state.dtype == np.float32
            np.testing.assert_array_equal(episode.state, expected.state)
            assert spans(episode) == spans(expected), (name, mapping, episode_id)
        # annotated episodes carry their labels; the others only with the ground-truth mapping
        assert any(spans(e) for e in got.values()) == (name == "annotated" or truth)


def test_bags_hold_standard_messages_and_the_ground_truth(generated: Path) -> None:
    dataset = PlayDataset.open(generated)
    for name, (_, annotated) in DATASET_BAGS.items():
        for episode_id, episode in episodes_of(dataset, name, truth=True).items():
            bag = generated / "bags" / name / episode_id
            with AnyReader([bag], default_typestore=typestore()) as reader:
                topics = {c.topic: c.msgtype for c in reader.connections}
            expected = {
                CAMERA_TOPIC: "sensor_msgs/msg/Image",
                JOINT_TOPIC: "sensor_msgs/msg/JointState",
                COMMAND_TOPIC: "geometry_msgs/msg/Twist",
            }
            if annotated:
                expected[ANNOTATION_TOPIC] = "playseg_msgs/msg/TimedAnnotation"
            assert topics == expected, bag
            truth = json.loads((bag / TRUTH_FILE).read_text())["annotations"]
            assert [a["instruction"] for a in truth] == [s.instruction for s in episode.segments]
            assert [round(a["end"] * 10) for a in truth] == [s.end for s in episode.segments]  # 10 Hz


def test_the_bags_follow_one_another_in_the_datasets_order(generated: Path) -> None:
    dataset = PlayDataset.open(generated)
    where = {}
    for name in DATASET_BAGS:
        where.update(
            {
                episode_id: generated / "bags" / name / episode_id
                for episode_id in episodes_of(dataset, name, True)
            }
        )
    spans = []
    for record in dataset.records:
        with AnyReader([where[record.episode_id]], default_typestore=typestore()) as reader:
            spans.append((reader.start_time, reader.end_time))
    assert all(end < next_start for (_, end), (next_start, _) in zip(spans, spans[1:], strict=False))


def test_bad_requests_are_refused_before_writing(generated: Path, tmp_path: Path) -> None:
    with pytest.raises(FileExistsError, match="bags/annotated: already exists"):
        write_generated_bags("tabletop", generated, generated / "bags")
    with pytest.raises(ValueError, match="images must be one of raw, jpeg, both"):
        write_generated_bags("tabletop", generated, tmp_path / "x", images="png")
    with pytest.raises(ValueError, match="workers must be >= 1"):
        write_generated_bags("tabletop", generated, tmp_path / "x", workers=0)
    assert not (tmp_path / "x").exists()
    # A domain without its own bag writer gets play bags, which hold raw frames only.
    with pytest.raises(ValueError, match="--images jpeg: play bags .* raw frames only"):
        write_generated_bags("babyai", generated, tmp_path / "y", images="jpeg")
    assert not (tmp_path / "y").exists()
    argv = ["generate", "--domain", "tabletop", "--preset", "tiny", "--out", str(tmp_path / "z")]
    assert cli_main([*argv, "--images", "jpeg", "--quiet"]) == 1  # --images without --bag
    assert not (tmp_path / "z").exists()


def test_a_replay_that_differs_from_the_dataset_is_refused(generated: Path, tmp_path: Path) -> None:
    dataset = PlayDataset.open(generated)
    log = replay_dataset_episode(dataset, 0)
    assert log.episode_id == dataset.records[0].episode_id
    dataset.records[0].extra["seed"] = dataset.records[1].extra["seed"]
    with pytest.raises(
        ValueError, match=f"episode {dataset.records[0].episode_id}: replaying seed .* id, actions"
    ):
        replay_dataset_episode(dataset, 0)


def test_the_dataset_records_its_play_config(generated: Path) -> None:
    dataset = PlayDataset.open(generated)
    config = dataset_play_config(dataset)
    assert config == PlayConfig(tasks_per_episode=(3, 6))  # the tiny preset's
    with pytest.raises(ValueError, match="meta.play_config: unknown field 'speed'"):
        PlayConfig.from_json({"speed": 1}, "meta.play_config")
    with pytest.raises(ValueError, match="meta.play_config.teleop: unknown field 'x'"):
        PlayConfig.from_json({"teleop": {"x": 1}}, "meta.play_config")
