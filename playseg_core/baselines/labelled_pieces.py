"""The labelling model's side of the baselines that cut without it (random windows, changepoints):
training it, storing the cutting settings with it, and labelling the pieces.

The checkpoint is an ordinary labelling-model checkpoint (kind ``labeller``, ps/model.py) whose meta
holds ``baseline``: the method and its settings. A labeller from ``playseg train --labeller`` (or a PS
checkpoint, whose label head labels too) can be used as well, with settings from its configuration.
"""

from __future__ import annotations

import time
from dataclasses import asdict, replace
from pathlib import Path
from typing import Any

import torch

from playseg_core.baselines.common import TrainingData, TrainOptions
from playseg_core.data.episode import Episode, Segment
from playseg_core.ps.labelling import label_segments
from playseg_core.ps.model import LabelModel, PSModel, load_model, save_model


def train_labelling_model(
    data: TrainingData, options: TrainOptions
) -> tuple[LabelModel, dict[str, Any], float]:
    """The stand-alone labelling model (ps/training.py train_labeller) on ``data``; -> (model, meta, seconds)."""
    from playseg_core.ps.training import TrainConfig, model_config_for, segment_bounds, train_labeller

    train_eps = data.annotated()
    bounds = segment_bounds(train_eps, data.domain, **data.bounds)
    threads = options.num_threads or torch.get_num_threads()
    cfg = TrainConfig(seed=options.seed, k_max=bounds.k_max, num_threads=threads, progress=False)
    cfg = replace(cfg, log_epochs=bool(options.log_every))
    if options.epochs is not None:
        cfg = replace(cfg, epochs=options.epochs, min_steps=0)
    if options.steps is not None:
        cfg = replace(cfg, epochs=1, min_steps=options.steps)
    if options.batch_size is not None:
        cfg = replace(cfg, segments_per_batch=options.batch_size)
    if options.lr is not None:
        cfg = replace(cfg, lr=options.lr)
    model_cfg = model_config_for(
        data.features,
        data.domain,
        len(data.instructions),
        max_len=bounds.max_len,
        read_actions=data.read_actions,
        episodes=train_eps,
        overrides=data.encoder_overrides,
        min_len=bounds.min_len,
    )
    began = time.perf_counter()
    result = train_labeller(train_eps, data.val, data.instructions, cfg, model_cfg)
    final = result.history[-1].get("val", result.history[-1]["train"])
    meta = {"train": asdict(cfg), "history": result.history, "val_label_accuracy": final["label_accuracy"]}
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
