"""Labelling extracted segments, and a confidence threshold calibrated on held-out annotated data.

A segment's confidence is the probability of its predicted instruction. The threshold is chosen on the
annotated validation split so that the segments it keeps reach a target label accuracy (e.g. 0.95);
applied to extracted segments, it trades coverage for label quality before policy training.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np
import torch

from playseg_core.data_model import Episode, Segment
from playseg_core.models import LabelModel, PSModel
from playseg_core.segmentation import episode_frames


@torch.no_grad()
def label_segments(
    model: PSModel | LabelModel, episode: Episode, spans: Iterable[tuple[int, int]]
) -> list[Segment]:
    """Label each [start, end) of `episode` with the model's most probable instruction."""
    model.eval()
    spans = list(spans)
    if not spans:
        return []
    features = model.encode_frames(episode_frames(episode))
    labelled = []
    for start, end in spans:
        probs = torch.softmax(model.label_logits(features, start, end).double(), dim=-1)
        best = int(probs.argmax())
        labelled.append(Segment(start, end, model.instructions[best], float(probs[best])))
    return labelled


def calibrate_threshold(
    confidences: Sequence[float] | np.ndarray, correct: Sequence[bool] | np.ndarray, target_accuracy: float
) -> float:
    """The lowest threshold whose kept items (confidence >= threshold) reach `target_accuracy`.

    Lowest = the most items kept. Items with equal confidence are kept or dropped together. Returns
    +inf (keep nothing) when no threshold reaches the target, and the lowest confidence (keep
    everything) when all items together already do.
    """
    conf = np.asarray(confidences, dtype=np.float64)
    hits = np.asarray(correct, dtype=bool)
    if conf.shape != hits.shape or conf.ndim != 1:
        raise ValueError(f"confidences {conf.shape} and correct {hits.shape} must be equal-length 1-D")
    if not 0.0 < target_accuracy <= 1.0:
        raise ValueError(f"target_accuracy must be in (0, 1], got {target_accuracy}")
    if conf.size == 0:
        return math.inf
    order = np.argsort(-conf, kind="stable")
    conf, hits = conf[order], hits[order]
    kept_accuracy = np.cumsum(hits) / np.arange(1, conf.size + 1)
    # Only cut where the confidence changes (ties stay together).
    cut = np.append(conf[1:] != conf[:-1], True)
    good = np.nonzero(cut & (kept_accuracy >= target_accuracy))[0]
    if good.size == 0:
        return math.inf
    return float(conf[good[-1]])


@dataclass(frozen=True)
class Calibration:
    threshold: float
    target_accuracy: float
    accuracy_kept: float  # label accuracy of the held-out segments the threshold keeps
    coverage: float  # share of held-out segments kept
    accuracy_all: float  # label accuracy without a threshold
    num_segments: int


def calibrate_on_annotated(
    model: PSModel | LabelModel, episodes: Iterable[Episode], target_accuracy: float
) -> Calibration:
    """Label the annotated segments of held-out `episodes` and calibrate the threshold on them."""
    confidences, correct = [], []
    for episode in episodes:
        spans = [(seg.start, seg.end) for seg in episode.segments if seg.length <= model.max_len]
        truth = {(seg.start, seg.end): seg.instruction for seg in episode.segments}
        for predicted in label_segments(model, episode, spans):
            confidences.append(predicted.confidence)
            correct.append(predicted.instruction == truth[(predicted.start, predicted.end)])
    if not confidences:
        raise ValueError("calibration needs annotated segments; the held-out episodes have none")
    threshold = calibrate_threshold(confidences, correct, target_accuracy)
    conf, hits = np.asarray(confidences), np.asarray(correct)
    kept = conf >= threshold
    return Calibration(
        threshold=threshold,
        target_accuracy=target_accuracy,
        accuracy_kept=float(hits[kept].mean()) if kept.any() else float("nan"),
        coverage=float(kept.mean()),
        accuracy_all=float(hits.mean()),
        num_segments=int(conf.size),
    )


def keep_confident(segments: Iterable[Segment], threshold: float) -> list[Segment]:
    """The segments whose label confidence reaches the calibrated threshold."""
    return [seg for seg in segments if seg.confidence >= threshold]
