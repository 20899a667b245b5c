"""The selection point: a segmentation method's name -> how to train it and how to segment with it.

    method = get_method("tridet")
    trained = method.train(data, TrainOptions(max_steps=500))   # TrainedSegmenter; .save(path, meta)
    segmenter = method.load(path, SegmentOptions(seed=0))   # Segmenter; .segment(episode) -> [Segment]

`playseg train --method` and `playseg segment --method` dispatch through `METHODS`; so do the benchmark
and the experiment runner. ``ps`` is Play Segmentation itself (ps/), the others are the paper's baselines.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from playseg_core.baselines.changepoint import load_changepoint_segmenter, train_changepoint
from playseg_core.baselines.common import (
    Segmenter,
    SegmentOptions,
    TrainedSegmenter,
    TrainingData,
    TrainOptions,
    ps_training_setup,
)
from playseg_core.baselines.random_windows import load_random_segmenter, train_random
from playseg_core.baselines.tridet import load_tridet_segmenter, train_tridet
from playseg_core.baselines.unloc import load_unloc_segmenter, train_unloc
from playseg_core.data.episode import Episode, Segment
from playseg_core.errors import PlaysegError
from playseg_core.ps.model import PSModel, load_model, save_model
from playseg_core.registry import Registry


class PlaySegmenter(Segmenter):
    """Play Segmentation (ps/segmentation.py) behind the common interface."""

    method = "ps"
    tiles = True

    def __init__(self, model: PSModel, meta: dict[str, Any], options: SegmentOptions) -> None:
        from playseg_core.training.device import resolve_device

        self.model = model.to(resolve_device(options.device)).eval()
        self.instructions = model.instructions
        self.features = model.cfg.features
        self.feature_names = model.cfg.feature_names
        self.min_len = options.min_len or model.cfg.min_len
        self.checkpoint_meta = meta

    def segment(self, episode: Episode) -> list[Segment]:
        from playseg_core.ps.segmentation import segment_episode

        return segment_episode(self.model, episode, min_len=self.min_len)


def train_play_segmentation(data: TrainingData, options: TrainOptions) -> TrainedSegmenter:
    """The PS model as `playseg train` trains it (TrainConfig defaults: the data-scaled budget with early
    stopping; the options' budget and device where given), calibrated on the val split."""
    from playseg_core.ps.calibration import calibrate_ps_model
    from playseg_core.ps.training import train_ps

    train_eps, cfg, model_cfg = ps_training_setup(data, options)
    began = time.perf_counter()
    result = train_ps(train_eps, data.val, data.instructions, cfg, model_cfg)
    calibrated = calibrate_ps_model(result.model, data.val, options.label_accuracy) if data.val else {}
    meta = {"train": asdict(cfg), "history": result.history, "seconds": result.seconds, "calibration": {}}
    meta |= calibrated
    seconds = time.perf_counter() - began

    def save(path: Path, extra: dict[str, Any]) -> Path:
        return save_model(path, result.model, {**meta, **extra})

    segmenter = PlaySegmenter(result.model, meta, SegmentOptions())
    text = f"PS model: {result.summary()}, val label accuracy {result.label_accuracy:.3f}"
    return TrainedSegmenter(segmenter, save, seconds, text)


def load_play_segmenter(path: str | Path, options: SegmentOptions) -> PlaySegmenter:
    model, meta = load_model(path, kinds=("ps",))
    return PlaySegmenter(model, meta, options)


@dataclass(frozen=True)
class Method:
    name: str
    summary: str
    tiles: bool  # whether its segments cover the trajectory (else: report precision and label accuracy)
    train: Callable[[TrainingData, TrainOptions], TrainedSegmenter]
    load: Callable[[str | Path, SegmentOptions], Segmenter]
    # whether its training honours TrainingData.augment (rotated/mirrored clips): PS and the methods
    # that train the labelling model do
    augments: bool = False


METHODS: Registry[Method] = Registry("segmentation method")
"""The segmentation methods by name (`train` and `segment`'s ``--method``), in the order tables list them."""
for _method in (
    Method(
        "ps", "Play Segmentation (ps/)", True, train_play_segmentation, load_play_segmenter, augments=True
    ),
    Method(
        "unloc",
        "UnLoc-style per-step classification, background cropped",
        False,
        train_unloc,
        load_unloc_segmenter,
    ),
    Method(
        "tridet",
        "TriDet-style localisation, top-1 detection per window",
        False,
        train_tridet,
        load_tridet_segmenter,
    ),
    Method(
        "random",
        "random windows labelled by the labelling model",
        True,
        train_random,
        load_random_segmenter,
        augments=True,
    ),
    Method(
        "changepoint",
        "PELT changepoints labelled by the labelling model",
        True,
        train_changepoint,
        load_changepoint_segmenter,
        augments=True,
    ),
):
    METHODS.register(_method.name, _method)


def get_method(name: str) -> Method:
    """The method called ``name``; ValueError listing the known ones otherwise."""
    try:
        return METHODS[name]
    except PlaysegError as error:
        raise PlaysegError(f"--method {name!r}: {error}") from None


def train_segmenter(name: str, data: TrainingData, options: TrainOptions) -> TrainedSegmenter:
    return get_method(name).train(data, options)


def load_segmenter(name: str, path: str | Path, options: SegmentOptions | None = None) -> Segmenter:
    """The segmenter of method ``name`` saved at ``path`` (its errors name the checkpoint)."""
    segmenter = get_method(name).load(path, options or SegmentOptions())
    segmenter.source = f"checkpoint {path}"
    return segmenter
