"""`--method` through the command line: `playseg train --method M`, `playseg segment --method M` and
`playseg evaluate` for every method, on a small synthetic dataset (tiny budgets: the round trip, not
the quality, which test_baselines*.py check)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch
from test_baselines import FEATURES, INSTRUCTIONS, synthetic_episode

from playseg_core.baselines.registry import METHODS
from playseg_core.checkpoint import read_checkpoint
from playseg_core.data.dataset import DatasetWriter, PlayDataset
from playseg_core.ps.labelling import KEEP_RULES
from playseg_core.ps.model import LABEL_HEADS
from playseg_ros.cli import KEEP_RULE_CHOICES, SEGMENTATION_METHODS
from playseg_ros.cli import LABEL_HEADS as CLI_LABEL_HEADS
from playseg_ros.cli import main as cli_main

torch.set_num_threads(1)


@pytest.fixture(scope="module")
def dataset(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("baselines") / "data"
    with DatasetWriter(path, INSTRUCTIONS, features=FEATURES) as writer:
        for seed in range(10):
            split = "train" if seed < 6 else "val" if seed < 8 else "test"
            writer.add(synthetic_episode(seed), split)
    return path


def test_the_command_line_offers_the_registry_methods_label_heads_and_keep_rules() -> None:
    assert SEGMENTATION_METHODS == tuple(METHODS)
    assert CLI_LABEL_HEADS == LABEL_HEADS
    assert KEEP_RULE_CHOICES == tuple(KEEP_RULES)


@pytest.mark.slow
@pytest.mark.parametrize("method", list(METHODS))
def test_train_segment_evaluate_round_trip(method: str, dataset: Path, tmp_path: Path, capsys) -> None:
    model = tmp_path / f"{method}.pt"
    argv = ["train", "--method", method, "--data", str(dataset), "--out", str(model), "--epochs", "1"]
    assert cli_main(argv) == 0
    kind = {"ps": "ps", "unloc": "unloc", "tridet": "tridet"}.get(method, "labeller")
    if kind in ("unloc", "tridet"):  # a long run shows where it is, as PS's does
        shown = capsys.readouterr().err
        assert f"{method}:" in shown and "step/s" in shown, shown
    checkpoint = read_checkpoint(model, (kind,))
    assert checkpoint.kind == kind and "observation.state" in checkpoint.features.by_name
    if kind == "labeller":
        assert checkpoint.meta["baseline"]["method"] == method
    out = tmp_path / "segmented"
    argv = ["segment", "--method", method, "--model", str(model), "--input", str(dataset), "--out", str(out)]
    assert cli_main([*argv, "--splits", "test"]) == 0
    segmented = PlayDataset.open(out)
    assert segmented.info["meta"]["method"] == method and len(segmented) == 2
    assert segmented.info["meta"]["tiles"] == METHODS[method].tiles
    if METHODS[method].tiles:  # every step of the test episodes is in a segment
        for index in range(len(segmented)):
            segments = segmented.segments(index, truth=True)
            assert sum(s.length for s in segments) == segmented.records[index].num_steps
    capsys.readouterr()
    assert cli_main(["evaluate", "--pred", str(out), "--truth", str(dataset), "--plot-episodes", "0"]) == 0
    printed = capsys.readouterr().out
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["episodes"] == 2 and "segment_precision" in metrics
    assert ("covered_label_accuracy" in metrics) == (not METHODS[method].tiles)
    assert ("cuts single segments out of windows" in printed) == (not METHODS[method].tiles)


@pytest.mark.slow
def test_a_checkpoint_of_another_method_is_one_clear_line(dataset: Path, tmp_path: Path, capsys) -> None:
    model = tmp_path / "tridet.pt"
    argv = ["train", "--method", "tridet", "--data", str(dataset), "--out", str(model), "--epochs", "1"]
    assert cli_main(argv) == 0
    capsys.readouterr()
    argv = [
        "segment",
        "--method",
        "unloc",
        "--model",
        str(model),
        "--input",
        str(dataset),
        "--out",
        str(tmp_path / "s"),
    ]
    assert cli_main(argv) == 1
    error = capsys.readouterr().err.strip()
    assert error.count("\n") == 0 and "tridet.pt: a 'tridet' checkpoint, expected unloc" in error
    assert not (tmp_path / "s").exists()
    argv = ["train", "--method", "random", "--data", str(dataset), "--out", str(tmp_path / "r.pt")]
    assert cli_main([*argv, "--labeller", str(tmp_path / "l.pt")]) == 1
    assert "--labeller: only with --method ps" in capsys.readouterr().err


@pytest.mark.slow
def test_window_methods_can_read_a_trained_models_step_encoders(dataset: Path, tmp_path: Path) -> None:
    """--encoders-from: the PS model's step encoders, frozen (their weights are the PS model's after
    training), recorded in the baseline's checkpoint; other methods refuse the option."""
    ps = tmp_path / "ps.pt"
    assert cli_main(["train", "--data", str(dataset), "--out", str(ps), "--epochs", "1"]) == 0
    model = tmp_path / "unloc.pt"
    argv = ["train", "--method", "unloc", "--data", str(dataset), "--out", str(model), "--epochs", "2"]
    assert cli_main([*argv, "--encoders-from", str(ps)]) == 0
    pretrained, trained = read_checkpoint(ps), read_checkpoint(model, ("unloc",))
    assert trained.meta["encoders_from"] == str(ps)
    encoder_weights = {k: v for k, v in pretrained.state_dict.items() if k.startswith("encoders.")}
    assert encoder_weights and all(torch.equal(trained.state_dict[k], v) for k, v in encoder_weights.items())
    argv = ["train", "--method", "random", "--data", str(dataset), "--out", str(tmp_path / "r.pt")]
    assert cli_main([*argv, "--encoders-from", str(ps)]) == 1
