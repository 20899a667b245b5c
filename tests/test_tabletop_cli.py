"""End to end through the command line on tabletop play: generate -> train -> segment -> evaluate
(tiny budgets: this checks that the pieces fit, not how well the model segments)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

from playseg_core.data.dataset import PlayDataset
from playseg_core.domains.tabletop.instructions import INSTRUCTIONS
from playseg_core.ps.model import load_model
from playseg_ros.cli import main as cli_main

torch.set_num_threads(1)


@pytest.mark.slow
def test_generate_train_segment_evaluate(tmp_path: Path, capsys) -> None:
    data, model, pred = tmp_path / "data", tmp_path / "ps.pt", tmp_path / "pred"
    assert (
        cli_main(["generate", "--domain", "tabletop", "--preset", "tiny", "--out", str(data), "--quiet"]) == 0
    )
    assert "preset tiny" in capsys.readouterr().out

    assert cli_main(["train", "--data", str(data), "--out", str(model), "--epochs", "1"]) == 0
    out = capsys.readouterr().out
    # The domain's object-map encoder reads the camera, the generic ones the state and the continuous
    # action; each instruction has its own label weights (the domain's LABEL_HEAD).
    assert "tabletop.object_maps" in out and "state_mlp" in out and "continuous_action" in out
    assert "linear label head" in out
    # The table's symmetries are declared by the domain, so training uses them unless told not to.
    assert "clips under the domain's 8 symmetries" in out
    assert load_model(model)[1]["train"]["augment"] is True

    argv = ["segment", "--model", str(model), "--input", str(data), "--out", str(pred), "--splits", "test"]
    assert cli_main(argv) == 0
    segmented = PlayDataset.open(pred)
    truth = PlayDataset.open(data)
    assert len(segmented.records) == len(truth.episode_indices("test"))
    for index in range(len(segmented.records)):
        segments = segmented.segments(index, truth=True)
        assert segments and segments[-1].end == segmented.records[index].num_steps
        assert all(seg.instruction in INSTRUCTIONS for seg in segments)

    assert cli_main(["evaluate", "--pred", str(pred), "--truth", str(data), "--plot-episodes", "0"]) == 0
    metrics = json.loads((pred / "metrics.json").read_text())
    test_episodes = truth.episode_indices("test")
    assert metrics["episodes"] == len(test_episodes)
    assert metrics["true_segments"] == sum(len(truth.segments(i, truth=True)) for i in test_episodes)
    assert 0.0 <= metrics["boundary_f1_tol2"] <= 1.0 and 0.0 <= metrics["label_accuracy"] <= 1.0


def test_no_augment_trains_on_the_clips_as_recorded(tmp_path: Path, capsys) -> None:
    data, model = tmp_path / "data", tmp_path / "ps.pt"
    assert (
        cli_main(["generate", "--domain", "tabletop", "--preset", "tiny", "--out", str(data), "--quiet"]) == 0
    )
    argv = ["train", "--data", str(data), "--out", str(model), "--max-steps", "2", "--no-augment"]
    assert cli_main(argv) == 0
    assert "symmetries" not in capsys.readouterr().out
    assert load_model(model)[1]["train"]["augment"] is False
