"""The UnLoc-style baseline learns the synthetic task with clear boundaries of test_baselines.py: the
segments it crops out of random windows are true segments with their labels; checkpoints round-trip."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from test_baselines import scores, synthetic_data, synthetic_episode

from playseg_core.baselines.common import SegmentOptions, TrainOptions
from playseg_core.baselines.registry import load_segmenter
from playseg_core.baselines.unloc import UnlocConfig, train_unloc
from playseg_core.checkpoint import read_checkpoint

torch.set_num_threads(1)

TEST = [synthetic_episode(300 + s, steps=150) for s in range(8)]


@pytest.mark.slow
def test_unloc_crops_true_segments_out_of_random_windows(tmp_path: Path) -> None:
    data = synthetic_data()
    data.bounds = {"k_max": 3}  # 1..3 background steps each side of a training segment
    trained = train_unloc(
        data, TrainOptions(max_steps=200, batch_size=16, eval_every=50), UnlocConfig(dim=32)
    )
    results = scores(trained.segmenter, TEST)
    assert results["pred_segments"] >= 20 and results["segment_precision"] >= 0.9, results
    assert results["covered_label_accuracy"] >= 0.95, results
    path = trained.save(tmp_path / "unloc.pt", {"note": "synthetic"})
    checkpoint = read_checkpoint(path, ("unloc",))
    assert checkpoint.meta["note"] == "synthetic" and checkpoint.config["model"]["pad_max"] == 3
    # Trained through the loop: evaluations every 50 steps (too few for patience 4 to stop it), the
    # best one's weights and val loss kept.
    meta = checkpoint.meta
    assert meta["steps"] == 200 and meta["step_cap"] == 200 and meta["stopped"] == "step cap"
    assert [entry["step"] for entry in meta["history"]] == [50.0, 100.0, 150.0, 200.0]
    kept = next(entry for entry in meta["history"] if entry["step"] == meta["best_step"])
    assert meta["val_loss"] == kept["val_loss"] <= min(entry["val_loss"] for entry in meta["history"]) * 1.001
    assert [spec["kind"] for spec in checkpoint.config["encoders"]] == ["state_mlp", "discrete_action"]
    loaded = load_segmenter("unloc", path, SegmentOptions(seed=0, device="cpu"))
    assert next(loaded.model.parameters()).device == torch.device("cpu")
    assert [loaded.segment(e) for e in TEST[:3]] == [trained.segmenter.segment(e) for e in TEST[:3]]
    # Windows are drawn per episode: another seed cuts other windows.
    other = load_segmenter("unloc", path, SegmentOptions(seed=1))
    assert [other.segment(e) for e in TEST[:3]] != [loaded.segment(e) for e in TEST[:3]]
