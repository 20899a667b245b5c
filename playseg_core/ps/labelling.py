"""Labelling extracted segments, and which of them are kept for training (`KeepRule`).

A segment's confidence is the probability of its predicted instruction. A keep rule is a score and a
threshold from calibration.py, chosen on held-out annotated data for a target label accuracy; applied to
extracted segments, it trades coverage for label quality before policy training. The rules:

- ``label``: label confidence >= the threshold chosen on the *true* cuts of the val episodes (the
  paper's filter; ``calibration`` in a checkpoint's record);
- ``own_cuts``: label x cut probability (`segment_probability`) >= the threshold chosen on the model's
  *own* cuts of the val episodes (``own_cuts_calibration``; PS only): what to use when the model's cuts
  of play are often pieces of tasks, which the label confidence cannot see;
- ``all``: every segment.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Any

import torch

from playseg_core.data.episode import Episode, Segment
from playseg_core.errors import PlaysegError
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


def segment_probability(segment: Segment) -> float:
    """The model's probability that ``segment``, given its start, is exactly right: its label's
    probability times its cut's, s(i, j) (no end before j and an end at j; ``Segment.log_prob``). The
    label probability alone is what the true-cut threshold reads; on the model's own cuts the cut can be
    wrong too (half a task, two tasks), and this score ranks those pieces low."""
    return segment.confidence * math.exp(segment.log_prob)


def threshold_json(threshold: float) -> float | None:
    """A threshold as strict JSON: null for +inf, the threshold calibration returns when none reaches its
    target (keeps nothing). ``json.dumps`` would write ``Infinity``, which JSON parsers outside Python
    refuse."""
    return threshold if math.isfinite(threshold) else None


KEEP_RULES: dict[str, tuple[str, str]] = {
    "label": ("calibration", "label confidence"),
    "own_cuts": ("own_cuts_calibration", "label x cut probability"),
    "all": ("", "every segment"),
}
"""Keep rule -> (the checkpoint record holding its threshold, what its score is)."""


@dataclass(frozen=True)
class KeepRule:
    """Which extracted segments are used: those whose score (`KEEP_RULES`) reaches ``threshold``."""

    kind: str
    threshold: float = 0.0

    def __post_init__(self) -> None:
        if self.kind not in KEEP_RULES:
            raise PlaysegError(f"keep rule must be one of {', '.join(KEEP_RULES)}, got {self.kind!r}")

    def score(self, segment: Segment) -> float:
        return segment_probability(segment) if self.kind == "own_cuts" else segment.confidence

    def keeps(self, segment: Segment) -> bool:
        return self.kind == "all" or self.score(segment) >= self.threshold

    def describe(self) -> str:
        what = KEEP_RULES[self.kind][1]
        return what if self.kind == "all" else f"{what} >= {self.threshold:.3f}"

    def to_json(self) -> dict[str, Any]:
        return {
            "rule": self.kind,
            "threshold": threshold_json(self.threshold),
            "score": KEEP_RULES[self.kind][1],
        }

    @classmethod
    def of_checkpoint(cls, kind: str, meta: Mapping[str, Any], source: str) -> KeepRule:
        """The rule ``kind`` with the threshold the checkpoint's ``meta`` records for it. A checkpoint
        without a label calibration keeps everything by label (threshold 0: nothing says which
        confidences to trust); ValueError naming ``source`` when it records no own-cut calibration."""
        rule = cls(kind)  # checks the kind
        record = KEEP_RULES[kind][0]
        if kind == "own_cuts" and "threshold" not in meta.get(record, {}):
            raise PlaysegError(
                f"{source}: records no own-cut calibration (a PS checkpoint calibrated on a val split does; "
                "`playseg calibrate` adds it); keep by 'label' instead"
            )
        return cls(kind, float(meta.get(record, {}).get("threshold", 0.0))) if record else rule


def is_calibrated(meta: Mapping[str, Any]) -> bool:
    """Whether a PS checkpoint's ``meta`` records a label calibration (a threshold chosen on held-out
    annotated segments); a model trained without any has confidences that mean nothing yet."""
    return "threshold" in (meta.get("calibration") or {})


def uncalibrated_warning(source: str) -> str:
    """What `segment`, `convert --segment` and the segmenter node say, once, of a PS checkpoint that
    `is_calibrated` is not."""
    return (
        f"{source}: not calibrated (trained without held-out annotated episodes): its confidences are "
        "not calibrated and the label rule keeps every segment; `playseg calibrate --model ... --data ...` "
        "with annotated val episodes calibrates it"
    )
