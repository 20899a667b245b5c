"""`playseg train / calibrate / segment / evaluate` end to end on a tiny generated BabyAI dataset."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

from playseg_core.data.dataset import PlayDataset
from playseg_ros.cli import main as cli_main
from playseg_ros.offline import _num_actions


@pytest.fixture(scope="module")
def tiny_data(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("data") / "tiny"
    assert cli_main(["generate", "--preset", "tiny", "--seed", "3", "--out", str(out), "--quiet"]) == 0
    return out


def test_train_calibrate_segment_evaluate(tiny_data: Path, tmp_path: Path, capsys) -> None:
    model = tmp_path / "ps.pt"
    assert cli_main(["train", "--data", str(tiny_data), "--out", str(model), "--epochs", "1"]) == 0
    printed = capsys.readouterr().out
    assert "model reads 7 discrete actions" in printed  # BabyAI actions, found by --actions auto
    assert "end bias" in printed and "label threshold" in printed
    raw = torch.load(model, weights_only=True)
    assert raw["config"]["num_actions"] == 7
    # the bias the checkpoint records is the one its model segments with
    assert raw["state_dict"]["end_bias"].item() == raw["extra"]["end_bias"]["bias"]
    assert len(raw["extra"]["end_bias"]["sweep"]) >= 5

    recalibrated = tmp_path / "ps-recalibrated.pt"
    assert (
        cli_main(["calibrate", "--model", str(model), "--data", str(tiny_data), "--out", str(recalibrated)])
        == 0
    )
    again = torch.load(recalibrated, weights_only=True)
    assert again["extra"]["end_bias"] == raw["extra"]["end_bias"]  # same model, same val split
    assert again["extra"]["calibrated_on"] == str(tiny_data.resolve())

    pred = tmp_path / "pred"
    assert (
        cli_main(
            [
                "segment",
                "--model",
                str(model),
                "--input",
                str(tiny_data),
                "--splits",
                "test",
                "--out",
                str(pred),
            ]
        )
        == 0
    )
    segmented = PlayDataset.open(pred)
    assert len(segmented) == len(PlayDataset.open(tiny_data).episode_indices("test"))
    assert cli_main(["evaluate", "--pred", str(pred), "--truth", str(tiny_data), "--plot-episodes", "0"]) == 0
    metrics = json.loads((pred / "metrics.json").read_text())
    assert 0.0 <= metrics["boundary_precision_tol0"] <= 1.0 and metrics["episodes"] == len(segmented)


def test_calibrate_refuses_a_dataset_without_annotated_val(tmp_path: Path, capsys) -> None:
    assert cli_main(["calibrate", "--model", str(tmp_path / "none.pt"), "--data", str(tmp_path)]) == 1
    assert "none.pt: no such file" in capsys.readouterr().err


def test_actions_option(tiny_data: Path) -> None:
    episodes = list(PlayDataset.open(tiny_data).episodes("train"))
    assert _num_actions("auto", episodes) == 7 and _num_actions("none", episodes) == 0
    assert _num_actions("3", episodes) == 3
    continuous = [type(episodes[0])("c", episodes[0].frames, episodes[0].actions + 0.5)]
    assert _num_actions("auto", continuous) == 0  # not BabyAI's discrete actions: frames only
    with pytest.raises(ValueError, match="--actions must be a count"):
        _num_actions("many", episodes)
