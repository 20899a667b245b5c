"""`playseg generate --bag`: the dataset's splits as three play bags that read back to the same episodes."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from playseg_core.data.dataset import PlayDataset
from playseg_core.data.episode import Episode
from playseg_core.domains.babyai.spec import CAMERA
from playseg_ros.bag import BagReader
from playseg_ros.cli import main as cli_main
from playseg_ros.play_bags import (
    ANNOTATIONS_TOPIC,
    GROUND_TRUTH_TOPIC,
    STEPS_TOPIC,
    read_play_bag,
    read_play_bag_info,
    write_dataset_bags,
)

pytestmark = pytest.mark.slow  # the module's bags are generated play

SPLITS_OF_BAG = {"annotated": ("train", "val"), "play": ("play",), "test": ("test",)}


@pytest.fixture(scope="module")
def generated(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("gen") / "tiny"
    assert cli_main(["generate", "--preset", "tiny", "--out", str(out), "--quiet", "--bag"]) == 0
    return out


def split_episodes(dataset: PlayDataset, splits: tuple[str, ...]) -> list[Episode]:
    indices = sorted(i for split in splits for i in dataset.episode_indices(split))
    return [dataset.episode(i, truth=True) for i in indices]


def assert_same_episodes(got: list[Episode], want: list[Episode]) -> None:
    assert [e.episode_id for e in got] == [e.episode_id for e in want]
    for g, w in zip(got, want, strict=True):
        assert np.array_equal(g.images[CAMERA], w.images[CAMERA]), g.episode_id
        assert g.state is not None and w.state is not None
        # the bag declares the dataset's features: the state reads back in its declared dtype
        assert g.state.dtype == w.state.dtype and np.array_equal(g.state, w.state), g.episode_id
        assert np.array_equal(g.actions, w.actions), g.episode_id
        assert g.segments == w.segments, g.episode_id


@pytest.mark.parametrize("name", list(SPLITS_OF_BAG))
def test_each_bag_holds_the_episodes_of_its_splits(generated: Path, name: str) -> None:
    dataset = PlayDataset.open(generated)
    want = split_episodes(dataset, SPLITS_OF_BAG[name])
    assert want, f"the tiny preset has no episodes for the {name} bag"
    got = read_play_bag(generated / "bags" / name, truth=True)
    assert_same_episodes(got, want)
    info = read_play_bag_info(generated / "bags" / name)
    assert info.features == dataset.features and info.domain == "babyai"
    assert info.instructions == dataset.instructions


def test_only_the_annotated_bag_has_annotations(generated: Path) -> None:
    dataset = PlayDataset.open(generated)
    for name in SPLITS_OF_BAG:
        with BagReader(generated / "bags" / name) as reader:
            topics = set(reader.topics)
        expected = {STEPS_TOPIC, GROUND_TRUTH_TOPIC} | ({ANNOTATIONS_TOPIC} if name == "annotated" else set())
        assert topics == expected, name
    # Read without truth, the annotated bag gives the train+val labels, the play bag none at all.
    annotated = read_play_bag(generated / "bags" / "annotated")
    assert [e.segments for e in annotated] == [
        e.segments for e in split_episodes(dataset, SPLITS_OF_BAG["annotated"])
    ]
    play = read_play_bag(generated / "bags" / "play")
    assert play and all(e.segments == [] for e in play)


def test_existing_bags_are_not_overwritten(generated: Path, tmp_path: Path) -> None:
    out = tmp_path / "bags"
    (out / "play").mkdir(parents=True)
    with pytest.raises(FileExistsError, match="play"):
        write_dataset_bags(generated, out)
    assert sorted(p.name for p in out.iterdir()) == ["play"]  # nothing written before the refusal


def test_a_missing_dataset_is_named(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError, match="nowhere"):
        write_dataset_bags(tmp_path / "nowhere", tmp_path / "bags")
