"""The dataset format: round trip, memory mapping, atomic writing, corrupt input, splits without leakage."""

from __future__ import annotations

import json
import pickle
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from playseg_core.data.dataset import (
    FORMAT_VERSION,
    DatasetError,
    DatasetWriter,
    PlayDataset,
)
from playseg_core.data.episode import Episode, Segment
from playseg_core.data.features import ACTION, DEFAULT_CAMERA, STATE, Feature, Features
from playseg_core.data.splits import SplitTargets, assign_splits
from playseg_core.domains.babyai.generate import PRESETS, Preset, generate_dataset, get_preset
from playseg_core.domains.babyai.play import PlayConfig, generate_episode
from playseg_core.domains.babyai.spec import CAMERA, INSTRUCTIONS
from playseg_ros.cli import main as cli_main

CONFIG = PlayConfig(max_tasks=3)
SPLIT_OF_SEED = {0: "train", 1: "train", 2: "val", 3: "play", 4: "test"}


@pytest.fixture(scope="module")
def episodes() -> dict[int, Episode]:
    return {seed: generate_episode(CONFIG, seed) for seed in SPLIT_OF_SEED}


@pytest.fixture
def written(tmp_path: Path, episodes: dict[int, Episode]) -> Path:
    path = tmp_path / "ds"
    meta = {"preset": "unit", "seed": 7}
    with DatasetWriter(path, INSTRUCTIONS, meta, features=CONFIG.features, domain="babyai") as writer:
        for seed, split in SPLIT_OF_SEED.items():
            writer.add(episodes[seed], split, extra={"seed": seed})
    return path


def test_round_trip_returns_equal_memory_mapped_episodes(written: Path, episodes: dict[int, Episode]) -> None:
    ds = PlayDataset.open(written)
    assert len(ds) == 5 and ds.instructions == INSTRUCTIONS
    assert ds.splits == ("train", "val", "play", "test")
    assert ds.episode_indices("train") == [0, 1] and ds.episode_indices("test") == [4]
    assert isinstance(ds.array(CAMERA), np.memmap) and isinstance(ds.array(ACTION), np.memmap)
    assert ds.features == CONFIG.features and ds.domain == "babyai"
    for index, seed in enumerate(SPLIT_OF_SEED):
        original, loaded = episodes[seed], ds.episode(index, truth=True)
        assert loaded.episode_id == original.episode_id
        assert isinstance(loaded.images[CAMERA], np.memmap)
        assert np.array_equal(loaded.images[CAMERA], original.images[CAMERA])
        assert np.array_equal(loaded.state, original.state)
        assert np.array_equal(loaded.actions, original.actions)
        assert loaded.segments == original.segments


def test_segments_are_revealed_only_for_annotated_splits(written: Path, episodes: dict[int, Episode]) -> None:
    ds = PlayDataset.open(written)
    assert [e.segments for e in ds.episodes("val")] == [episodes[2].segments]
    assert [e.segments for e in ds.episodes("play")] == [[]]
    assert [e.segments for e in ds.episodes("test")] == [[]]
    assert [e.segments for e in ds.episodes("test", truth=True)] == [episodes[4].segments]
    with pytest.raises(KeyError, match="unknown split 'dev'"):
        ds.episode_indices("dev")


def test_boundary_frames_are_stored_once_and_metadata_counts_match(
    written: Path, episodes: dict[int, Episode]
) -> None:
    info = json.loads((written / "meta/info.json").read_text())
    steps = sum(e.num_steps for e in episodes.values())
    assert info["format_version"] == FORMAT_VERSION
    assert info["counts"]["observations"] == steps + len(episodes)
    assert info["counts"]["segments"] == sum(len(e.segments) for e in episodes.values())
    assert info["meta"] == {"preset": "unit", "seed": 7}
    assert info["fps"] == 10.0 and info["domain"] == "babyai"
    assert info["features"][ACTION] == {
        "kind": "action",
        "dtype": "float32",
        "shape": [1],
        "action_type": "discrete",
        "num_values": 7,
    }
    assert info["features"][CAMERA] == {"kind": "image", "dtype": "uint8", "shape": [64, 64, 3]}
    camera_file = written / f"data/{CAMERA}.bin"
    assert camera_file.stat().st_size == (steps + len(episodes)) * 64 * 64 * 3
    assert (written / "data/action.bin").stat().st_size == steps * 4
    lines = (written / "meta/episodes.jsonl").read_text().splitlines()
    assert [json.loads(line)["extra"]["seed"] for line in lines] == list(SPLIT_OF_SEED)


def test_pickling_reopens_files_instead_of_copying_arrays(written: Path) -> None:
    ds = PlayDataset.open(written)
    blob = pickle.dumps(ds)
    assert len(blob) < 1000
    again = pickle.loads(blob)
    assert np.array_equal(again.episode(3).images[CAMERA], ds.episode(3).images[CAMERA])


def test_failed_writing_leaves_nothing_behind(tmp_path: Path, episodes: dict[int, Episode]) -> None:
    path = tmp_path / "ds"
    with pytest.raises(RuntimeError, match="boom"), DatasetWriter(path, INSTRUCTIONS) as writer:
        writer.add(episodes[0], "train")
        raise RuntimeError("boom")
    assert list(tmp_path.iterdir()) == []


def test_existing_dataset_is_kept_unless_overwrite(written: Path, episodes: dict[int, Episode]) -> None:
    with pytest.raises(FileExistsError, match="exists"):
        DatasetWriter(written, INSTRUCTIONS)
    with DatasetWriter(written, INSTRUCTIONS, overwrite=True) as writer:
        writer.add(episodes[3], "play")
    assert len(PlayDataset.open(written)) == 1
    assert sorted(p.name for p in written.parent.iterdir()) == ["ds"]


def test_writer_rejects_bad_episodes_naming_episode_and_field(
    tmp_path: Path, episodes: dict[int, Episode]
) -> None:
    with DatasetWriter(tmp_path / "ds", INSTRUCTIONS, features=CONFIG.features) as writer:
        writer.add(episodes[0], "train")
        with pytest.raises(ValueError, match="'babyai-0': episode_id already written"):
            writer.add(episodes[0], "train")
        with pytest.raises(ValueError, match="unknown split 'dev'"):
            writer.add(episodes[1], "dev")
        wrong = Episode("odd", np.zeros((1, 1), np.float32), {CAMERA: np.zeros((2, 32, 32, 3), np.uint8)})
        with pytest.raises(ValueError, match="'odd': has no extra features, lacks \\['observation.state'\\]"):
            writer.add(wrong, "train")
        wrong.state = np.zeros((2, 8, 8, 3), np.uint8)
        with pytest.raises(ValueError, match=f"'odd': feature '{CAMERA}' must be \\(2, 64, 64, 3\\) uint8"):
            writer.add(wrong, "train")
        wrong.images[CAMERA] = np.zeros((2, 64, 64, 3), np.uint8)
        wrong.actions[:] = 9
        with pytest.raises(
            ValueError, match="'odd' action\\[0\\] = 9.0: not a discrete action index in 0..6"
        ):
            writer.add(wrong, "train")
        one = episodes[1]
        unknown = Episode("unknown", one.actions, one.images, one.state, [Segment(0, 1, "dance")])
        with pytest.raises(ValueError, match="'unknown': segment \\[0, 1\\) field 'instruction' 'dance'"):
            writer.add(unknown, "train")


def test_missing_file_is_named(written: Path) -> None:
    (written / "data/observation.state.bin").unlink()
    with pytest.raises(
        FileNotFoundError, match="observation.state.bin: missing .*features.observation.state"
    ):
        PlayDataset.open(written)


def test_truncated_array_is_named_with_its_field(written: Path) -> None:
    frames = written / f"data/{CAMERA}.bin"
    frames.write_bytes(frames.read_bytes()[:-100])
    with pytest.raises(DatasetError, match=f"{CAMERA}.bin: size .* features.{CAMERA}"):
        PlayDataset.open(written)


def test_malformed_feature_schema_is_named(written: Path) -> None:
    info_file = written / "meta/info.json"
    info = json.loads(info_file.read_text())
    info["features"]["observation.depth"] = {"kind": "image", "dtype": "uint8", "shape": [4, 4, 1]}
    info_file.write_text(json.dumps(info))
    with pytest.raises(DatasetError, match="info.json: feature 'observation.depth': unknown name"):
        PlayDataset.open(written)


def test_a_version_1_dataset_opens() -> None:
    """tests/data/dataset_v1 was written by playseg before format version 2 (see tests/data/README.md)."""
    ds = PlayDataset.open(Path(__file__).parent / "data" / "dataset_v1")
    assert ds.format_version == 1 and ds.domain is None and ds.instructions == ("go left", "go right")
    assert ds.features.cameras == [DEFAULT_CAMERA]
    assert ds.features.state.shape == (4, 4, 3) and ds.features.state.dtype == "uint8"
    assert ds.features.action.num_values == 3  # whole numbers 0..2: read as discrete
    assert ds.splits == ("train", "val", "play", "test")
    episode = ds.episode(3, truth=True)
    assert episode.num_steps == 8 and episode.images[DEFAULT_CAMERA].shape == (9, 16, 16, 3)
    assert episode.state.shape == (9, 4, 4, 3)
    assert [(s.start, s.end, s.instruction) for s in episode.segments] == [
        (0, 2, "go left"),
        (2, 8, "go right"),
    ]
    ds.features.check_episode(episode)


@pytest.mark.parametrize("layout", ["two cameras, no state", "no camera, a state"])
def test_any_number_of_cameras_and_an_optional_state_round_trip(tmp_path: Path, layout: str) -> None:
    rng = np.random.default_rng(1)
    front, wrist = "observation.images.front", "observation.images.wrist"
    joints = [f"joint_{i}" for i in range(7)]
    if layout == "two cameras, no state":
        features = [
            Feature(front, "image", "uint8", (12, 16, 3)),
            Feature(wrist, "image", "uint8", (8, 8, 3)),
            Feature(ACTION, "action", "float32", (2,), names=("v", "w"), low=(-1.0, -2.0), high=(1.0, 2.0)),
        ]
    else:
        features = [
            Feature(STATE, "state", "float32", (7,), names=tuple(joints)),
            Feature(ACTION, "action", "float32", (7,)),
        ]
    schema = Features.of(features, fps=30.0)
    episodes = []
    for i, num_steps in enumerate([4, 7]):
        images = {
            name: rng.integers(0, 256, size=(num_steps + 1, *schema[name].shape), dtype=np.uint8)
            for name in schema.cameras
        }
        state = None if schema.state is None else rng.normal(size=(num_steps + 1, 7)).astype(np.float32)
        actions = rng.uniform(-1, 1, size=(num_steps, schema.action.size)).astype(np.float32)
        episodes.append(Episode(f"robot-{i}", actions, images, state, [Segment(0, num_steps, "wave")]))
    with DatasetWriter(tmp_path / "ds", ["wave"], features=schema) as writer:
        for episode in episodes:
            writer.add(episode, "train")
    ds = PlayDataset.open(tmp_path / "ds")
    assert ds.features == schema
    for index, original in enumerate(episodes):
        loaded = ds.episode(index)
        assert sorted(loaded.images) == sorted(original.images)
        for name, frames in original.images.items():
            np.testing.assert_array_equal(loaded.images[name], frames)
        if original.state is None:
            assert loaded.state is None
        else:
            np.testing.assert_array_equal(loaded.state, original.state)
        np.testing.assert_array_equal(loaded.actions, original.actions)
        assert loaded.segments == original.segments
    info = json.loads((tmp_path / "ds/meta/info.json").read_text())
    if schema.state is not None:
        assert info["features"][STATE]["names"] == joints
    else:
        assert (
            info["features"][ACTION]["low"] == [-1.0, -2.0]
            and not (tmp_path / "ds/data/observation.state.bin").exists()
        )


def test_wrong_version_is_named(written: Path) -> None:
    info_file = written / "meta/info.json"
    info = json.loads(info_file.read_text())
    info["format_version"] = 99
    info_file.write_text(json.dumps(info))
    with pytest.raises(DatasetError, match="info.json: field 'format_version' is 99"):
        PlayDataset.open(written)


def test_inconsistent_episode_table_is_named(written: Path) -> None:
    table = written / "meta/episodes.jsonl"
    lines = table.read_text().splitlines()
    record = json.loads(lines[2])
    record["observation_start"] += 1
    lines[2] = json.dumps(record)
    table.write_text("\n".join(lines) + "\n")
    with pytest.raises(DatasetError, match="episodes.jsonl: line 3 \\(episode 'babyai-2'\\)"):
        PlayDataset.open(written)
    table.write_text("not json\n")
    with pytest.raises(DatasetError, match="episodes.jsonl: line 1: bad episode record"):
        PlayDataset.open(written)


def test_segment_outside_its_episode_is_named(written: Path) -> None:
    file = written / "data/segments.npy"
    table = np.load(file)
    table["end"][0] = 10_000
    np.save(file, table)
    with pytest.raises(DatasetError, match="segments.npy: episode 'babyai-0' .*outside"):
        PlayDataset.open(written)


@settings(max_examples=60, deadline=None)
@given(
    counts=st.lists(st.integers(1, 12), min_size=1, max_size=80),
    test=st.integers(0, 60),
    annotated=st.integers(0, 150),
    play=st.integers(0, 150),
)
def test_split_assignment_meets_targets_in_order(
    counts: list[int], test: int, annotated: int, play: int
) -> None:
    targets = SplitTargets(test, annotated, play)
    splits = assign_splits(counts, targets)
    totals = {name: sum(c for c, s in zip(counts, splits, strict=True) if s == name) for name in splits}
    got_annotated = totals.get("train", 0) + totals.get("val", 0)
    # Each split reaches its target unless the episodes ran out, and overshoots by less than one episode.
    if None in splits:
        assert totals.get("test", 0) >= test and got_annotated >= annotated and totals.get("play", 0) >= play
        first_unused = splits.index(None)
        assert all(s is None for s in splits[first_unused:])
    assert totals.get("test", 0) < test + 12 and got_annotated < annotated + 12
    order = {"test": 0, "train": 1, "val": 1, "play": 2, None: 3}
    assert [order[s] for s in splits] == sorted(order[s] for s in splits)
    annotated_episodes = [s for s in splits if s in ("train", "val")]
    assert annotated_episodes.count("val") == len(annotated_episodes) // 5


MINI = Preset(
    "mini", "unit test", PlayConfig(), SplitTargets(test_segments=20, annotated_segments=50, play_segments=30)
)


def test_generated_splits_never_leak(tmp_path: Path) -> None:
    summary = generate_dataset(tmp_path / "ds", MINI, seed=1, progress=False)
    ds = PlayDataset.open(summary.path)
    ids = {split: {ds.records[i].episode_id for i in ds.episode_indices(split)} for split in ds.splits}
    assert set(ids) == {"train", "val", "play", "test"}
    assert not ids["val"] & ids["train"] and not ids["test"] & ids["train"]
    assert sum(len(v) for v in ids.values()) == len(set().union(*ids.values())) == len(ds)
    info = ds.info
    assert info["meta"]["preset"] == "mini" and info["meta"]["seed"] == 1
    annotated = summary.segments_per_split["train"] + summary.segments_per_split["val"]
    assert 50 <= annotated < 50 + MINI.play.max_tasks  # whole episodes: overshoot < one episode
    assert summary.segments_per_split["test"] >= 20 and summary.segments_per_split["play"] >= 30


def test_generated_episodes_name_their_generator_as_source(tmp_path: Path) -> None:
    from playseg_core.domains.babyai.generate import SOURCE

    summary = generate_dataset(tmp_path / "ds", MINI, seed=1, progress=False)
    ds = PlayDataset.open(summary.path)
    for record in ds.records:
        assert record.source == {
            "generator": "babyai", "preset": "mini", "seed": 1, "episode_seed": record.extra["seed"]
        }  # fmt: skip
    # the source is enough to make the episode again
    record = ds.records[-1]
    assert record.source is not None
    again = SOURCE.episode_of(SOURCE.generate(MINI.play, record.source["episode_seed"]))
    np.testing.assert_array_equal(again.actions, ds.episode(record.index).actions)


@pytest.mark.slow
def test_generation_is_byte_identical_for_any_worker_count(tmp_path: Path) -> None:
    one = generate_dataset(tmp_path / "one", MINI, seed=2, workers=1, progress=False)
    two = generate_dataset(tmp_path / "two", MINI, seed=2, workers=2, progress=False)
    files = sorted(p.relative_to(one.path) for p in one.path.rglob("*") if p.is_file())
    assert files == sorted(p.relative_to(two.path) for p in two.path.rglob("*") if p.is_file())
    for name in files:
        assert (one.path / name).read_bytes() == (two.path / name).read_bytes(), name
    other = generate_dataset(tmp_path / "other", MINI, seed=3, progress=False)
    assert (other.path / "data/action.bin").read_bytes() != (one.path / "data/action.bin").read_bytes()


def test_presets_and_annotated_share() -> None:
    paper = PRESETS["paper"].targets
    assert (paper.annotated_segments, paper.play_segments) == (10_000, 90_000)
    assert paper.test_segments == 2000
    quarter = get_preset("paper", annotated_share=0.25).targets
    assert (quarter.annotated_segments, quarter.play_segments) == (25_000, 75_000)
    with pytest.raises(KeyError, match="unknown preset 'huge'"):
        get_preset("huge")


@pytest.mark.slow
def test_cli_generates_the_tiny_preset(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "tiny"
    assert cli_main(["generate", "--preset", "tiny", "--out", str(out), "--seed", "5", "--quiet"]) == 0
    assert "preset tiny, seed 5" in capsys.readouterr().out
    ds = PlayDataset.open(out)
    assert ds.splits == ("train", "val", "play", "test") and ds.info["meta"]["seed"] == 5
    assert cli_main(["generate", "--preset", "tiny", "--out", str(out), "--quiet"]) == 1
    assert "exists" in capsys.readouterr().err
