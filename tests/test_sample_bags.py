"""The sample bags committed in bags/: readable, the expected topics, and reproducible by `make bags`.

`make bags` runs `playseg generate --preset sample --seed 0 --bag`. Regenerating all 310 episodes takes
~20 s on one core, so the test regenerates the first and last episodes of every bag from their seeds
and checks that the split of every episode follows from the preset's targets.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from playseg_core.data.episode import Episode
from playseg_core.data.splits import assign_splits
from playseg_core.domains.babyai.generate import PRESETS, episode_seed
from playseg_core.domains.babyai.play import episode_id_for_seed, generate_episode
from playseg_core.domains.babyai.spec import CAMERA, INSTRUCTIONS
from playseg_ros.bag import BagReader
from playseg_ros.play_bags import (
    ANNOTATIONS_TOPIC,
    GROUND_TRUTH_TOPIC,
    STEPS_TOPIC,
    read_play_bag,
    read_play_bag_info,
)

pytestmark = pytest.mark.slow  # every test regenerates or reads the sample preset's play

BAGS = Path(__file__).resolve().parent.parent / "bags"
PRESET = PRESETS["sample"]
SEED = 0
# Generation fills the splits in this order; the annotated bag is train + val.
BAG_OF_SPLIT = {"test": "test", "train": "annotated", "val": "annotated", "play": "play"}
REGENERATED_PER_BAG = 2  # the first two and the last episode of each bag


@pytest.fixture(scope="module")
def sample() -> dict[str, list[Episode]]:
    return {name: read_play_bag(BAGS / name, truth=True) for name in ("annotated", "play", "test")}


def test_bags_declare_the_babyai_features() -> None:
    for name in ("annotated", "play", "test"):
        info = read_play_bag_info(BAGS / name)
        assert info.features == PRESET.play.features and info.domain == "babyai", name
        assert info.instructions == INSTRUCTIONS and info.camera == CAMERA, name


def test_bags_have_the_expected_topics() -> None:
    for name in ("annotated", "play", "test"):
        with BagReader(BAGS / name) as reader:
            topics = set(reader.topics)
        expected = {STEPS_TOPIC, GROUND_TRUTH_TOPIC} | ({ANNOTATIONS_TOPIC} if name == "annotated" else set())
        assert topics == expected, name


def test_sizes_match_the_sample_preset(sample: dict[str, list[Episode]]) -> None:
    targets = PRESET.targets
    max_tasks = PRESET.play.max_tasks
    for name, target in (
        ("annotated", targets.annotated_segments),
        ("play", targets.play_segments),
        ("test", targets.test_segments),
    ):
        segments = sum(len(e.segments) for e in sample[name])
        assert target <= segments < target + max_tasks, (name, segments)
    size = sum(f.stat().st_size for f in BAGS.rglob("*.mcap"))
    # BabyAI's 1.9 MB and the tabletop's 7.2 MB: the demo's robot half replays 30 tasks of camera play
    # (bags/README.md), which JPEG frames at 10 Hz make 5.5 MB of the total
    assert size < 10_000_000, f"sample bags are {size / 1e6:.1f} MB; they must stay small"


def test_annotations_equal_ground_truth_in_the_annotated_bag(sample: dict[str, list[Episode]]) -> None:
    annotated = read_play_bag(BAGS / "annotated")
    assert [e.segments for e in annotated] == [e.segments for e in sample["annotated"]]
    assert all(e.segments == [] for e in read_play_bag(BAGS / "play"))


def test_episodes_are_the_seeded_stream_split_by_the_preset(sample: dict[str, list[Episode]]) -> None:
    """Episode i of the run has seed episode_seed(0, i); the splits follow from the segment counts."""
    by_id = {e.episode_id: (name, e) for name, episodes in sample.items() for e in episodes}
    seeds = [episode_seed(SEED, i) for i in range(len(by_id))]
    ids = [episode_id_for_seed(seed) for seed in seeds]
    assert set(ids) == set(by_id), "the bags do not hold episodes 0..N-1 of the seed-0 run"
    counts = [len(by_id[i][1].segments) for i in ids]
    splits = assign_splits(counts, PRESET.targets)
    assert [BAG_OF_SPLIT[s] for s in splits if s is not None] == [by_id[i][0] for i in ids]
    for name, episodes in sample.items():  # each bag in generation order
        order = [ids.index(e.episode_id) for e in episodes]
        assert order == sorted(order), name


def test_regenerating_gives_the_same_messages(sample: dict[str, list[Episode]]) -> None:
    for name, episodes in sample.items():
        chosen = [*episodes[:REGENERATED_PER_BAG], episodes[-1]]
        for recorded in chosen:
            seed = int(recorded.episode_id.removeprefix("babyai-"))
            fresh = generate_episode(PRESET.play, seed)
            assert fresh.episode_id == recorded.episode_id
            assert np.array_equal(recorded.images[CAMERA], fresh.images[CAMERA]), (name, seed)
            assert fresh.state is not None and recorded.state is not None
            assert recorded.state.dtype == fresh.state.dtype, (name, seed)
            assert np.array_equal(recorded.state, fresh.state), (name, seed)
            assert np.array_equal(recorded.actions, fresh.actions), (name, seed)
            assert recorded.segments == fresh.segments, (name, seed)
