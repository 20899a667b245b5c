"""Unsupervised changepoints: PELT (the ``ruptures`` library, as robot-data tools use it) on a
trajectory's signal, each piece labelled by the labelling model. It tiles the trajectory and answers
"how much do the annotations buy over cutting without them?".

The signal of step t is what the data declares, read generically: the state o_t flattened and the
action a_t (one-hot when discrete) (``signal="state_action"``), and/or the labelling model's step
features of the transition o_t -> o_{t+1} (``"features"``, ``"all"``), each dimension standardised
within the episode. The cost is the l2 cost (a change of mean), computed from cumulative sums. The one
number PELT needs, its penalty per changepoint, is proportional to the signal's width; the factor is
chosen on the annotated training episodes (best boundary F1, a grid search), unless given.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import ruptures
import torch
from ruptures.base import BaseCost

from playseg_core.baselines.common import (
    Segmenter,
    SegmentOptions,
    TrainedSegmenter,
    TrainingData,
    TrainOptions,
)
from playseg_core.baselines.labelled_pieces import (
    label_pieces,
    load_labeller,
    save_labeller,
    train_labelling_model,
)
from playseg_core.data.episode import Episode, Segment
from playseg_core.data.features import Features
from playseg_core.errors import PlaysegError
from playseg_core.ps.metrics import boundary_scores
from playseg_core.ps.model import LabelModel, PSModel

METHOD = "changepoint"
SIGNALS = ("state_action", "features", "all")
PENALTY_GRID = tuple(float(x) for x in np.geomspace(0.001, 20.0, 18))
"""Penalty factors tried (x the signal's width)."""


class CumulativeL2Cost(BaseCost):
    """ruptures' l2 cost (sum of squared deviations from the piece mean) in O(width) per piece."""

    model = "l2_cumulative"
    min_size = 1

    def fit(self, signal: np.ndarray) -> CumulativeL2Cost:
        self.signal = signal = np.asarray(signal, np.float64).reshape(len(signal), -1)  # ruptures reads it
        self.sums = np.concatenate([np.zeros((1, signal.shape[1])), np.cumsum(signal, 0)])
        self.squares = np.concatenate([[0.0], np.cumsum(np.square(signal).sum(1))])
        return self

    def error(self, start: int, end: int) -> float:
        total = self.sums[end] - self.sums[start]
        return float(self.squares[end] - self.squares[start] - total @ total / (end - start))


def _standardised(columns: np.ndarray) -> np.ndarray:
    std = columns.std(0)
    return (columns - columns.mean(0)) / np.where(std > 1e-6, std, 1.0)


def step_signal(
    episode: Episode, features: Features, signal: str, model: LabelModel | PSModel | None = None
) -> np.ndarray:
    """(T, width) standardised signal of ``episode``'s steps (see the module docstring)."""
    if signal not in SIGNALS:
        raise PlaysegError(f"changepoint signal must be one of {', '.join(SIGNALS)}, got {signal!r}")
    steps = episode.num_steps
    parts = []
    if signal in ("state_action", "all"):
        if episode.state is not None:
            parts.append(np.asarray(episode.state[:steps], np.float64).reshape(steps, -1))
        actions = np.asarray(episode.actions, np.float64).reshape(steps, -1)
        action = features.action
        if action.is_discrete:
            parts.append(
                np.eye(action.num_values)[np.clip(actions[:, 0].astype(np.int64), 0, action.num_values - 1)]
            )
        else:
            parts.append(actions)
    if signal in ("features", "all"):
        if model is None:
            raise PlaysegError(f"changepoint signal {signal!r} needs the labelling model's step features")
        with torch.no_grad():
            parts.append(model.encode_episode(episode)[1:].double().numpy())
    return _standardised(np.concatenate(parts, axis=1))


def changepoints(signal: np.ndarray, penalty: float, min_size: int = 1) -> list[tuple[int, int]]:
    """PELT pieces [start, end) of a (T, width) signal with ``penalty`` per changepoint."""
    if len(signal) == 0:
        return []
    if len(signal) <= min_size:
        return [(0, len(signal))]
    algo = ruptures.Pelt(custom_cost=CumulativeL2Cost(), min_size=min_size, jump=1).fit(signal)
    ends = algo.predict(pen=penalty)
    return list(zip([0, *ends[:-1]], ends, strict=True))


def choose_penalty(
    episodes: Sequence[Episode],
    features: Features,
    signal: str,
    model: LabelModel | PSModel | None,
    min_size: int,
) -> tuple[float, float]:
    """The penalty factor of `PENALTY_GRID` with the best boundary F1 (exact, no final boundary) on the
    annotated ``episodes``; -> (factor, F1)."""
    signals = [step_signal(e, features, signal, model) for e in episodes]
    best = (PENALTY_GRID[0], -1.0)
    for factor in PENALTY_GRID:
        counts = None
        for episode, values in zip(episodes, signals, strict=True):
            pieces = [Segment(s, e) for s, e in changepoints(values, factor * values.shape[1], min_size)]
            found = boundary_scores(pieces, episode.segments, 0, False, episode.num_steps)
            counts = found if counts is None else counts + found
        if counts is not None and counts.f1 > best[1]:
            best = (factor, counts.f1)
    return best


class ChangepointSegmenter(Segmenter):
    method = METHOD
    tiles = True

    def __init__(
        self,
        model: LabelModel | PSModel,
        penalty_factor: float,
        signal: str,
        min_size: int,
        options: SegmentOptions,
    ) -> None:
        self.model = model.eval()
        self.instructions = model.instructions
        self.features = model.cfg.features
        self.feature_names = model.cfg.feature_names
        self.penalty_factor, self.signal = penalty_factor, signal
        self.min_size = options.min_len or min_size

    def segment(self, episode: Episode) -> list[Segment]:
        values = step_signal(episode, self.features, self.signal, self.model)
        pieces = changepoints(values, self.penalty_factor * values.shape[1], self.min_size)
        return label_pieces(self.model, episode, pieces)


def train_changepoint(
    data: TrainingData,
    options: TrainOptions,
    signal: str = "state_action",
    penalty_factor: float | None = None,
    labeller: tuple[LabelModel | PSModel, dict[str, Any]] | None = None,
) -> TrainedSegmenter:
    """Train the labelling model (or take ``labeller``: a trained model and its meta); choose PELT's
    penalty factor on the annotated training episodes."""
    began = time.perf_counter()
    if labeller is None:
        model, meta, _ = train_labelling_model(data, options)
    else:
        model, meta = labeller[0], {**labeller[1], "labeller_reused": True}
    min_size = model.cfg.min_len
    tuned_f1 = None
    if penalty_factor is None:
        penalty_factor, tuned_f1 = choose_penalty(data.annotated(), data.features, signal, model, min_size)
    settings = {"method": METHOD, "penalty_factor": penalty_factor, "signal": signal, "min_size": min_size}
    meta["baseline"] = {**settings, "train_boundary_f1": tuned_f1}

    def save(path: Path, extra: dict[str, Any]) -> Path:
        return save_labeller(path, model, {**meta, **extra})

    segmenter = ChangepointSegmenter(model, penalty_factor, signal, min_size, SegmentOptions())
    seconds = time.perf_counter() - began
    chosen = "given" if tuned_f1 is None else f"train boundary F1 {tuned_f1:.3f}"
    text = (
        f"labelling model (val accuracy {meta.get('val_label_accuracy', float('nan')):.3f}) + PELT on {signal}, penalty "
        f"{penalty_factor:.3g} x width ({chosen}); {seconds:.0f} s"
    )
    return TrainedSegmenter(segmenter, save, seconds, text)


def load_changepoint_segmenter(path: str | Path, options: SegmentOptions) -> ChangepointSegmenter:
    """From a checkpoint `train_changepoint` wrote; ValueError naming the file for another labeller
    (its penalty was never chosen)."""
    model, meta = load_labeller(path)
    settings = meta.get("baseline", {})
    if settings.get("method") != METHOD:
        raise PlaysegError(
            f"checkpoint {path}: no changepoint settings (train it with `playseg train --method changepoint`)"
        )
    return ChangepointSegmenter(
        model, float(settings["penalty_factor"]), str(settings["signal"]), int(settings["min_size"]), options
    )
