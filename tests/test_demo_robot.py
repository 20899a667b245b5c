"""The robot half of `make demo` on the sample tabletop bags (real processes, real DDS): an unannotated
bag (the short one; the demo replays the long one the same way) replayed with its /clock through topic_adapter into the segmenter gives one PlayStep per step of
`playseg convert`'s episode, a tiling of segments, the same segments `playseg convert --segment` stores,
and a LeRobot v3 export of both bags. An untrained model: this checks the plumbing, not the model."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch
from test_tabletop_encoder import tabletop_shaped_episode

from playseg_core.domains.tabletop.play import PlayConfig
from playseg_core.domains.tabletop.spec import CAMERA, DOMAIN
from playseg_core.ps.model import PSModel, save_model
from playseg_core.ps.training import model_config_for
from playseg_ros.demo_robot import PLAY_BAG, run_robot_half
from playseg_ros.play_bags import read_play_bag

pytestmark = pytest.mark.dds  # the robot half streams through nodes

BAGS = Path(__file__).resolve().parents[1] / "bags"
SHORT_PLAY_BAG = "tabletop-1"  # 4 tasks; the demo's PLAY_BAG has 30


def test_the_demo_replays_at_least_30_true_segments() -> None:
    truth = json.loads((BAGS / "tabletop" / PLAY_BAG / "ground_truth.json").read_text())
    assert len(truth["annotations"]) >= 30


def _untrained_tabletop_model(path: Path) -> Path:
    episode = tabletop_shaped_episode(20)
    instructions = ["push the red cube left", "push the blue cube right", "move the arm to the centre"]
    config = model_config_for(
        PlayConfig().features, DOMAIN, len(instructions), max_len=40, episodes=[episode]
    )
    torch.manual_seed(0)
    return save_model(path, PSModel(config, instructions).eval())


def test_robot_half_live_equals_convert_and_exports_lerobot(tmp_path: Path) -> None:
    model = _untrained_tabletop_model(tmp_path / "tabletop.pt")
    result = run_robot_half(BAGS, tmp_path, model, SHORT_PLAY_BAG)
    summary = result.summary
    assert summary["steps"] == 146 and summary["true_segments"] == 4
    assert summary["model_test"] is None  # an untrained model has no test-split figures
    robot = tmp_path / "robot"
    steps = read_play_bag(robot / "robot_bag")
    assert [e.episode_id for e in steps] == [f"{SHORT_PLAY_BAG}:0"] and steps[0].num_steps == 146
    # Uncalibrated: every segment is stored, and they are the live ones; live, they tile the episode.
    assert summary["label_threshold"] == 0.0
    assert summary["live_equals_convert"], summary  # the demo's warning on stderr says where they differ
    assert summary["stored_segments"] == summary["segments"] > 0
    lerobot = summary["lerobot"]
    assert (lerobot["codebase_version"], lerobot["episodes"], lerobot["frames"]) == ("v3.0", 2, 285 + 146)
    assert lerobot["videos"] == [f"videos/{CAMERA}/chunk-000/file-000.mp4"]
    info = json.loads((robot / "lerobot" / "meta" / "info.json").read_text())
    assert info["fps"] == 10 and CAMERA in info["features"]
    assert json.loads((robot / "summary.json").read_text()) == summary
    assert "boundaries" in result.table
    for log in (robot / "logs").glob("*.log"):
        assert "Traceback" not in log.read_text(), log
