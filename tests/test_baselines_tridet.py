"""The TriDet-style baseline learns the synthetic task with clear boundaries of test_baselines.py: the
top-1 detection of each window is a true segment with its label; checkpoints round-trip."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from test_baselines import scores, synthetic_data, synthetic_episode

from playseg_core.baselines.common import SegmentOptions, TrainOptions
from playseg_core.baselines.registry import load_segmenter
from playseg_core.baselines.tridet import TridetConfig, train_tridet
from playseg_core.checkpoint import read_checkpoint

torch.set_num_threads(1)

TEST = [synthetic_episode(300 + s, steps=150) for s in range(8)]


@pytest.mark.slow
def test_tridet_top1_detections_are_true_segments(tmp_path: Path) -> None:
    cfg = TridetConfig.for_lengths(7)
    cfg.dim = 32
    trained = train_tridet(
        synthetic_data(), TrainOptions(max_steps=100, batch_size=8, lr=3e-3, eval_every=50), cfg
    )
    results = scores(trained.segmenter, TEST)
    # One detection per 32-step window: about 4 per 150-step episode.
    assert results["pred_segments"] >= 24 and results["segment_precision"] >= 0.9, results
    path = trained.save(tmp_path / "tridet.pt", {})
    checkpoint = read_checkpoint(path, ("tridet",))
    assert checkpoint.config["model"]["window"] == 32
    meta = checkpoint.meta  # the loop's run: evaluations every 50 steps, the best one's weights kept
    assert meta["steps"] == 100 and [entry["step"] for entry in meta["history"]] == [50.0, 100.0]
    assert (
        meta["val_loss"] == {entry["step"]: entry for entry in meta["history"]}[meta["best_step"]]["val_loss"]
    )
    loaded = load_segmenter("tridet", path, SegmentOptions(min_len=100))
    assert loaded.segment(TEST[0]) == []  # nothing is that long
    loaded = load_segmenter("tridet", path, SegmentOptions())
    assert [loaded.segment(e) for e in TEST[:3]] == [trained.segmenter.segment(e) for e in TEST[:3]]
