"""Tabletop dataset generation: the same seed gives the same bytes for any worker count, the presets'
splits, what the dataset declares, and one-line errors for bad options."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import pytest

from playseg_core.data.dataset import PlayDataset
from playseg_core.data.features import ACTION, STATE
from playseg_core.domains import load_domain
from playseg_core.domains.tabletop.generate import PRESETS, get_preset
from playseg_core.domains.tabletop.instructions import INSTRUCTIONS
from playseg_core.domains.tabletop.spec import ACTION_HIGH, ACTION_LOW, CAMERA, STATE_NAMES
from playseg_ros.cli import main as cli_main


def digests(root: Path) -> dict[str, str]:
    return {
        str(path.relative_to(root)): hashlib.sha256(path.read_bytes()).hexdigest()
        for path in sorted(root.rglob("*"))
        if path.is_file()
    }


@pytest.mark.slow
def test_same_seed_same_bytes_for_any_worker_count(tmp_path: Path) -> None:
    domain = load_domain("tabletop")
    one = domain.generate_dataset(tmp_path / "one", "tiny", seed=2, workers=1, progress=False)
    two = domain.generate_dataset(tmp_path / "two", "tiny", seed=2, workers=2, progress=False)
    domain.generate_dataset(tmp_path / "other", "tiny", seed=3, workers=1, progress=False)
    assert digests(tmp_path / "one") == digests(tmp_path / "two")
    assert digests(tmp_path / "one") != digests(tmp_path / "other")
    assert (one.steps, one.episodes) == (two.steps, two.episodes) and one.bytes_on_disk > 0
    targets = PRESETS["tiny"].targets
    assert one.segments_per_split["test"] >= targets.test_segments
    assert one.segments_per_split["train"] + one.segments_per_split["val"] >= targets.annotated_segments
    assert one.segments_per_split["val"] > 0 and one.segments_per_split["play"] >= targets.play_segments

    data = PlayDataset.open(tmp_path / "one")
    assert data.domain == "tabletop" and data.instructions == INSTRUCTIONS and data.features.fps == 10.0
    assert data.features[STATE].names == STATE_NAMES and data.features[CAMERA].shape == (96, 96, 3)
    action = data.features[ACTION]
    assert not action.is_discrete and action.low == ACTION_LOW and action.high == ACTION_HIGH
    teleop = json.loads((tmp_path / "one" / "meta/info.json").read_text())["meta"]["teleop"]
    assert teleop["success_rate"] == pytest.approx(one.teleop.success_rate, abs=1e-4)
    assert teleop["instruction_steps"]["count"] == sum(one.segments_per_split.values())
    assert [record.source for record in data.records] == [
        {"generator": "tabletop", "preset": "tiny", "seed": 2, "episode_seed": record.extra["seed"]}
        for record in data.records
    ]


def test_presets_follow_the_papers_calvin_split() -> None:
    paper = PRESETS["paper"].targets
    annotated, play = paper.annotated_segments, paper.play_segments
    assert annotated / (annotated + play) == pytest.approx(0.25) and paper.test_segments > 0
    share = get_preset("paper", annotated_share=1.0).targets
    assert share.annotated_segments == annotated + play and share.play_segments == 0
    with pytest.raises(ValueError, match="unknown tabletop preset 'huge'"):
        get_preset("huge")


def test_the_cli_names_a_bad_preset_in_one_line(tmp_path: Path, capsys) -> None:
    argv = ["generate", "--domain", "tabletop", "--preset", "huge", "--out", str(tmp_path / "d"), "--quiet"]
    assert cli_main(argv) == 1
    err = capsys.readouterr().err.strip()
    assert "huge" in err and "tiny" in err and len(err.splitlines()) == 1
    assert not (tmp_path / "d").exists()
