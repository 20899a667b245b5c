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
from playseg_core.data.splits import SplitTargets, assign_splits
from playseg_core.domains.babyai.generate import PRESETS, Preset, generate_dataset, get_preset
from playseg_core.domains.babyai.play import INSTRUCTIONS, PlayConfig, generate_episode
from playseg_ros.cli import main as cli_main

CONFIG = PlayConfig(max_tasks=3)
SPLIT_OF_SEED = {0: "train", 1: "train", 2: "val", 3: "play", 4: "test"}


@pytest.fixture(scope="module")
def episodes() -> dict[int, Episode]:
    return {seed: generate_episode(CONFIG, seed) for seed in SPLIT_OF_SEED}


@pytest.fixture
def written(tmp_path: Path, episodes: dict[int, Episode]) -> Path:
    path = tmp_path / "ds"
    with DatasetWriter(path, INSTRUCTIONS, {"preset": "unit", "seed": 7}) as writer:
        for seed, split in SPLIT_OF_SEED.items():
            writer.add(episodes[seed], split, extra={"seed": seed})
    return path


def test_round_trip_returns_equal_memory_mapped_episodes(written: Path, episodes: dict[int, Episode]) -> None:
    ds = PlayDataset.open(written)
    assert len(ds) == 5 and ds.instructions == INSTRUCTIONS
    assert ds.splits == ("train", "val", "play", "test")
    assert ds.episode_indices("train") == [0, 1] and ds.episode_indices("test") == [4]
    assert isinstance(ds.frames, np.memmap) and isinstance(ds.actions, np.memmap)
    for index, seed in enumerate(SPLIT_OF_SEED):
        original, loaded = episodes[seed], ds.episode(index, truth=True)
        assert loaded.episode_id == original.episode_id
        assert isinstance(loaded.frames, np.memmap)
        assert np.array_equal(loaded.frames, original.frames)
        assert np.array_equal(loaded.states, original.states)
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
    assert info["counts"]["frames"] == steps + len(episodes)
    assert info["counts"]["segments"] == sum(len(e.segments) for e in episodes.values())
    assert info["meta"] == {"preset": "unit", "seed": 7}
    assert (written / "data/frames.bin").stat().st_size == (steps + len(episodes)) * 64 * 64 * 3
    assert (written / "data/actions.bin").stat().st_size == steps * 4
    lines = (written / "meta/episodes.jsonl").read_text().splitlines()
    assert [json.loads(line)["extra"]["seed"] for line in lines] == list(SPLIT_OF_SEED)


def test_pickling_reopens_files_instead_of_copying_arrays(written: Path) -> None:
    ds = PlayDataset.open(written)
    blob = pickle.dumps(ds)
    assert len(blob) < 1000
    again = pickle.loads(blob)
    assert np.array_equal(again.episode(3).frames, ds.episode(3).frames)


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
    with DatasetWriter(tmp_path / "ds", INSTRUCTIONS) as writer:
        writer.add(episodes[0], "train")
        with pytest.raises(ValueError, match="'babyai-0': episode_id already written"):
            writer.add(episodes[0], "train")
        with pytest.raises(ValueError, match="unknown split 'dev'"):
            writer.add(episodes[1], "dev")
        wrong = Episode("odd", np.zeros((2, 32, 32, 3), np.uint8), np.zeros((1, 1), np.float32), None)
        with pytest.raises(ValueError, match="'odd': field 'states' present=False"):
            writer.add(wrong, "train")
        wrong.states = np.zeros((2, 8, 8, 3), np.uint8)
        with pytest.raises(ValueError, match="'odd': field 'frames' is \\(32, 32, 3\\)"):
            writer.add(wrong, "train")
        unknown = Episode(
            "unknown",
            episodes[1].frames,
            episodes[1].actions,
            episodes[1].states,
            [Segment(0, 1, "dance")],
        )
        with pytest.raises(ValueError, match="'unknown': segment \\[0, 1\\) field 'instruction' 'dance'"):
            writer.add(unknown, "train")


def test_missing_file_is_named(written: Path) -> None:
    (written / "data/states.bin").unlink()
    with pytest.raises(FileNotFoundError, match="states.bin: missing .*arrays.states"):
        PlayDataset.open(written)


def test_truncated_array_is_named_with_its_field(written: Path) -> None:
    frames = written / "data/frames.bin"
    frames.write_bytes(frames.read_bytes()[:-100])
    with pytest.raises(DatasetError, match="frames.bin: size .* arrays.frames"):
        PlayDataset.open(written)


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
    record["frame_start"] += 1
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


def test_generation_is_byte_identical_for_any_worker_count(tmp_path: Path) -> None:
    one = generate_dataset(tmp_path / "one", MINI, seed=2, workers=1, progress=False)
    two = generate_dataset(tmp_path / "two", MINI, seed=2, workers=2, progress=False)
    files = sorted(p.relative_to(one.path) for p in one.path.rglob("*") if p.is_file())
    assert files == sorted(p.relative_to(two.path) for p in two.path.rglob("*") if p.is_file())
    for name in files:
        assert (one.path / name).read_bytes() == (two.path / name).read_bytes(), name
    other = generate_dataset(tmp_path / "other", MINI, seed=3, progress=False)
    assert (other.path / "data/actions.bin").read_bytes() != (one.path / "data/actions.bin").read_bytes()


def test_presets_and_annotated_share() -> None:
    paper = PRESETS["paper"].targets
    assert (paper.annotated_segments, paper.play_segments) == (10_000, 90_000)
    assert paper.test_segments == 2000
    quarter = get_preset("paper", annotated_share=0.25).targets
    assert (quarter.annotated_segments, quarter.play_segments) == (25_000, 75_000)
    with pytest.raises(KeyError, match="unknown preset 'huge'"):
        get_preset("huge")


def test_cli_generates_the_tiny_preset(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "tiny"
    assert cli_main(["generate", "--preset", "tiny", "--out", str(out), "--seed", "5", "--quiet"]) == 0
    assert "preset tiny, seed 5" in capsys.readouterr().out
    ds = PlayDataset.open(out)
    assert ds.splits == ("train", "val", "play", "test") and ds.info["meta"]["seed"] == 5
    assert cli_main(["generate", "--preset", "tiny", "--out", str(out), "--quiet"]) == 1
    assert "exists" in capsys.readouterr().err
