"""`playseg train / calibrate / segment / evaluate` end to end on a tiny generated BabyAI dataset."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

from playseg_core.data.dataset import PlayDataset
from playseg_core.data.features import ACTION, Feature
from playseg_core.domains.babyai.spec import CAMERA
from playseg_ros.cli import main as cli_main
from playseg_ros.offline import _action_features


@pytest.fixture(scope="module")
def tiny_data(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("data") / "tiny"
    assert cli_main(["generate", "--preset", "tiny", "--seed", "3", "--out", str(out), "--quiet"]) == 0
    return out


def test_train_calibrate_segment_evaluate(tiny_data: Path, tmp_path: Path, capsys) -> None:
    model = tmp_path / "ps.pt"
    assert cli_main(["train", "--data", str(tiny_data), "--out", str(model), "--epochs", "1"]) == 0
    printed = capsys.readouterr().out
    # BabyAI's camera by the domain's grid-tile encoder; its declared discrete actions, by --actions auto
    assert f"model reads {CAMERA} (babyai.grid_tiles), action (discrete_action)" in printed
    assert "end bias" in printed and "label threshold" in printed
    raw = torch.load(model, weights_only=True)
    assert raw["features"]["features"][ACTION]["num_values"] == 7
    assert [spec["kind"] for spec in raw["config"]["encoders"]] == ["babyai.grid_tiles", "discrete_action"]
    # the bias the checkpoint records is the one its model segments with
    assert raw["state_dict"]["end_bias"].item() == raw["meta"]["end_bias"]["bias"]
    assert len(raw["meta"]["end_bias"]["sweep"]) >= 5

    recalibrated = tmp_path / "ps-recalibrated.pt"
    assert (
        cli_main(["calibrate", "--model", str(model), "--data", str(tiny_data), "--out", str(recalibrated)])
        == 0
    )
    again = torch.load(recalibrated, weights_only=True)
    assert again["meta"]["end_bias"] == raw["meta"]["end_bias"]  # same model, same val split
    assert again["meta"]["calibrated_on"] == str(tiny_data.resolve())

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
    features = PlayDataset.open(tiny_data).features
    assert _action_features("auto", features) == (features, True)  # the declared discrete action
    assert _action_features("none", features) == (features, False)
    three, reads = _action_features("3", features)
    assert reads and three.action.num_values == 3
    continuous = features.with_action(Feature(ACTION, "action", "float32", (1,)))
    assert _action_features("auto", continuous) == (continuous, False)  # declared continuous: not read
    with pytest.raises(ValueError, match="--actions must be a count"):
        _action_features("many", features)


def test_segment_refuses_data_with_other_features(tiny_data: Path, tmp_path: Path, capsys) -> None:
    model = tmp_path / "ps.pt"
    assert cli_main(["train", "--data", str(tiny_data), "--out", str(model), "--epochs", "1"]) == 0
    dataset = PlayDataset.open(tiny_data)
    from playseg_core.data.dataset import DatasetWriter

    other = tmp_path / "wrist"
    wrist = "observation.images.wrist"
    with DatasetWriter(other, dataset.instructions) as writer:
        for index in dataset.episode_indices("test")[:2]:
            episode = dataset.episode(index)
            images = {wrist: episode.images[CAMERA]}
            writer.add(type(episode)(episode.episode_id, episode.actions, images, episode.state), "test")
    capsys.readouterr()
    # A bag that declares nothing (as the recorder writes it): its image is the camera the model reads,
    # as in the live segmenter.
    from playseg_ros.play_bags import read_play_bag_info, write_play_bag

    test_episodes = [dataset.episode(i) for i in dataset.episode_indices("test")[:2]]
    write_play_bag(tmp_path / "recorded", test_episodes, annotated=False)
    assert read_play_bag_info(tmp_path / "recorded").features is None
    out = tmp_path / "from-bag"
    assert (
        cli_main(["segment", "--model", str(model), "--input", str(tmp_path / "recorded"), "--out", str(out)])
        == 0
    )
    assert len(PlayDataset.open(out)) == 2 and (out / "segments_bag" / "metadata.yaml").is_file()
    code = cli_main(
        [
            "segment",
            "--model",
            str(model),
            "--input",
            str(other),
            "--splits",
            "test",
            "--out",
            str(tmp_path / "o"),
        ]
    )
    assert code == 1
    assert f"reads feature '{CAMERA}', which the data lacks" in capsys.readouterr().err
