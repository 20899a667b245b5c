"""The labelling model's side of the baselines that cut without it (random windows, changepoints):
training it, storing the cutting settings with it, and labelling the pieces.

The checkpoint is an ordinary labelling-model checkpoint (kind ``labeller``, ps/model.py) whose meta
holds ``baseline``: the method and its settings. A labeller from ``playseg train --labeller`` (or a PS
checkpoint, whose label head labels too) can be used as well, with settings from its configuration.
"""

from __future__ import annotations

import time
from dataclasses import asdict
from pathlib import Path
from typing import Any

from playseg_core.baselines.common import TrainingData, TrainOptions, ps_training_setup
from playseg_core.data.episode import Episode, Segment
from playseg_core.ps.labelling import label_segments
from playseg_core.ps.model import LabelModel, PSModel, load_model, save_model


def train_labelling_model(
    data: TrainingData, options: TrainOptions
) -> tuple[LabelModel, dict[str, Any], float]:
    """The stand-alone labelling model (ps/training.py train_labeller, through the one loop with its
    budget and early stopping) on ``data``; -> (model, meta, seconds)."""
    from playseg_core.ps.training import train_labeller

    train_eps, cfg, model_cfg = ps_training_setup(data, options)
    began = time.perf_counter()
    result = train_labeller(train_eps, data.val, data.instructions, cfg, model_cfg)
    meta = {
        "train": asdict(cfg),
        "history": result.history,
        "seconds": result.seconds,
        "fit": result.summary(),
        # of the kept weights: on val, or on the training batches without a val split
        "val_label_accuracy": result.label_accuracy,
    }
    return result.model, meta, time.perf_counter() - began


def save_labeller(path: str | Path, model: LabelModel, meta: dict[str, Any]) -> Path:
    return save_model(path, model, meta)


def load_labeller(path: str | Path) -> tuple[LabelModel | PSModel, dict[str, Any]]:
    """A labelling model (or a PS model, whose label head labels) and its meta."""
    return load_model(path, kinds=("labeller", "ps"))


def label_pieces(
    model: LabelModel | PSModel, episode: Episode, spans: list[tuple[int, int]]
) -> list[Segment]:
    """Label each [start, end); a piece longer than the model can read (L_max) is cut into equal parts
    that it can."""
    fitting = []
    for start, end in spans:
        parts = -(-(end - start) // model.max_len)
        cuts = [start + round(k * (end - start) / parts) for k in range(parts + 1)]
        fitting += list(zip(cuts, cuts[1:], strict=False))
    return label_segments(model, episode, fitting)
