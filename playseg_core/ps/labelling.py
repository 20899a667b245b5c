"""Labelling extracted segments, and keeping those whose label is confident enough.

A segment's confidence is the probability of its predicted instruction. The threshold comes from
calibration.py (chosen on held-out annotated data for a target label accuracy); applied to extracted
segments, it trades coverage for label quality before policy training.
"""

from __future__ import annotations

from collections.abc import Iterable

import torch

from playseg_core.data.episode import Episode, Segment
from playseg_core.ps.model import LabelModel, PSModel


@torch.no_grad()
def label_segments(
    model: PSModel | LabelModel, episode: Episode, spans: Iterable[tuple[int, int]]
) -> list[Segment]:
    """Label each [start, end) of `episode` with the model's most probable instruction."""
    model.eval()
    spans = list(spans)
    if not spans:
        return []
    features = model.encode_episode(episode)
    labelled = []
    for start, end in spans:
        probs = torch.softmax(model.label_logits(features, start, end).double(), dim=-1)
        best = int(probs.argmax())
        labelled.append(Segment(start, end, model.instructions[best], float(probs[best])))
    return labelled


def keep_confident(segments: Iterable[Segment], threshold: float) -> list[Segment]:
    """The segments whose label confidence reaches the calibrated threshold."""
    return [seg for seg in segments if seg.confidence >= threshold]
