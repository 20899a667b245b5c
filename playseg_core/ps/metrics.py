"""Segmentation metrics, defined once for every report (DESIGN.md "Metrics").

A *boundary* is a segment's end step. Boundary precision/recall/F1 match predicted to true boundaries
one-to-one within ``tolerance`` steps; with ``tolerance=0`` and the final boundary T included this is the
reference implementation's exact-match definition (the final boundary is always right, so it inflates
both numbers: report it with and without). Label accuracy is per timestep, over the steps the truth
covers. Segment precision is the share of predicted segments equal to a true segment (same start and
end) with the same instruction; segment recall the share of true segments found that way.

Ratios with a zero denominator are 0.0. Episode totals are micro-averaged: counts are summed over
episodes before dividing.
"""

from __future__ import annotations

import re
import sys
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

from playseg_core.data.episode import Segment, check_segments
from playseg_core.errors import PlaysegError

__all__ = [
    "TOLERANCES",
    "BoundaryCounts",
    "LabelCounts",
    "MatchCounts",
    "SegmentCounts",
    "boundary_key",
    "boundary_scores",
    "evaluate",
    "format_metrics_table",
    "label_accuracy",
    "match_boundaries",
    "segment_matches",
]

TOLERANCES: tuple[int, ...] = (0, 1, 2, 5)
"""Boundary tolerances every report gives (steps): exact, the reference's +-1 and +-2, and +-5 for robot
data whose instructions last tens of steps."""


def _ratio(numerator: int, denominator: int) -> float:
    return numerator / denominator if denominator else 0.0


@dataclass(frozen=True)
class MatchCounts:
    """Matched items out of the predicted and the true ones."""

    matched: int
    num_pred: int
    num_truth: int

    @property
    def precision(self) -> float:
        return _ratio(self.matched, self.num_pred)

    @property
    def recall(self) -> float:
        return _ratio(self.matched, self.num_truth)

    @property
    def f1(self) -> float:
        precision, recall = self.precision, self.recall
        return 2 * precision * recall / (precision + recall) if precision + recall else 0.0

    def __add__(self, other: MatchCounts) -> MatchCounts:
        if type(other) is not type(self):
            return NotImplemented
        return type(self)(
            self.matched + other.matched, self.num_pred + other.num_pred, self.num_truth + other.num_truth
        )


class BoundaryCounts(MatchCounts):
    """Boundaries (segment ends) matched one-to-one within a tolerance."""


class SegmentCounts(MatchCounts):
    """Predicted segments equal to a true segment (start, end and instruction)."""


@dataclass(frozen=True)
class LabelCounts:
    """Timesteps whose predicted label equals the true one, out of the timesteps the truth covers."""

    correct: int
    total: int

    @property
    def accuracy(self) -> float:
        return _ratio(self.correct, self.total)

    def __add__(self, other: LabelCounts) -> LabelCounts:
        return LabelCounts(self.correct + other.correct, self.total + other.total)


def _check(segments: Sequence[Segment], argument: str, num_steps: int | None = None) -> None:
    """Segments must be Segment objects, sorted, disjoint and (when num_steps is known) inside it."""
    for seg in segments:
        if not isinstance(seg, Segment):
            raise TypeError(
                f"{argument}: expected playseg_core.data.episode.Segment items, got {type(seg).__name__}"
            )
    check_segments(segments, sys.maxsize if num_steps is None else num_steps, argument)


def match_boundaries(pred: Sequence[int], truth: Sequence[int], tolerance: int = 0) -> int:
    """Size of a maximum one-to-one matching of sorted boundaries with ``|p - t| <= tolerance``.

    Greedy over both sorted lists, matching each predicted boundary to the earliest unmatched true one
    in reach; optimal because all reach windows have the same width.
    """
    if tolerance < 0:
        raise PlaysegError(f"tolerance must be >= 0, got {tolerance}")
    matched = p = t = 0
    while p < len(pred) and t < len(truth):
        if truth[t] < pred[p] - tolerance:
            t += 1
        elif truth[t] > pred[p] + tolerance:
            p += 1
        else:
            matched += 1
            p += 1
            t += 1
    return matched


def boundary_scores(
    pred: Sequence[Segment],
    truth: Sequence[Segment],
    tolerance: int = 0,
    include_final: bool = True,
    num_steps: int | None = None,
) -> BoundaryCounts:
    """Boundary matches between predicted and true segment ends.

    ``include_final=False`` drops the trivial final boundary (an end equal to ``num_steps``) from both
    sides; it needs ``num_steps``.
    """
    _check(pred, "pred", num_steps)
    _check(truth, "truth", num_steps)
    pred_ends = [seg.end for seg in pred]
    true_ends = [seg.end for seg in truth]
    if not include_final:
        if num_steps is None:
            raise PlaysegError("num_steps is required when include_final=False (the final boundary is T)")
        pred_ends = [end for end in pred_ends if end != num_steps]
        true_ends = [end for end in true_ends if end != num_steps]
    return BoundaryCounts(match_boundaries(pred_ends, true_ends, tolerance), len(pred_ends), len(true_ends))


def label_accuracy(pred: Sequence[Segment], truth: Sequence[Segment], num_steps: int) -> LabelCounts:
    """Per-timestep label agreement over the steps covered by ``truth``.

    A covered step counts as correct when a predicted segment covers it with the same instruction; a
    step no prediction covers counts as wrong.
    """
    if num_steps < 0:
        raise PlaysegError(f"num_steps must be >= 0, got {num_steps}")
    _check(pred, "pred", num_steps)
    _check(truth, "truth", num_steps)
    predicted: list[str | None] = [None] * num_steps
    for seg in pred:
        predicted[seg.start : seg.end] = [seg.instruction] * seg.length
    correct = sum(predicted[step] == seg.instruction for seg in truth for step in range(seg.start, seg.end))
    return LabelCounts(correct, sum(seg.length for seg in truth))


def segment_matches(pred: Sequence[Segment], truth: Sequence[Segment]) -> SegmentCounts:
    """Predicted segments with the same start, end and instruction as a true segment."""
    _check(pred, "pred")
    _check(truth, "truth")
    true_keys = {(seg.start, seg.end, seg.instruction) for seg in truth}
    matched = sum((seg.start, seg.end, seg.instruction) in true_keys for seg in pred)
    return SegmentCounts(matched, len(pred), len(truth))


def boundary_key(metric: str, tolerance: int, include_final: bool) -> str:
    """Result-dict key of a boundary metric, e.g. ``boundary_f1_tol1_nofinal``."""
    return f"boundary_{metric}_tol{tolerance}" + ("" if include_final else "_nofinal")


def evaluate(
    pred_by_episode: Mapping[str, Sequence[Segment]],
    truth_by_episode: Mapping[str, Sequence[Segment]],
    num_steps_by_episode: Mapping[str, int],
    tolerances: Sequence[int] = TOLERANCES,
) -> dict[str, float | int]:
    """Micro-averaged metrics over the episodes of ``truth_by_episode``.

    An episode with no entry in ``pred_by_episode`` counts as an empty prediction. Keys: ``episodes``,
    ``pred_segments``, ``true_segments``, ``boundary_{precision,recall,f1}_tol{n}[_nofinal]`` (see
    ``boundary_key``), ``label_accuracy``, ``label_steps``, ``segment_precision``, ``segment_recall``.
    """
    unknown = sorted(set(pred_by_episode) - set(truth_by_episode))
    if unknown:
        raise PlaysegError(f"pred_by_episode has episodes without ground truth: {unknown[:5]}")
    missing = sorted(set(truth_by_episode) - set(num_steps_by_episode))
    if missing:
        raise PlaysegError(f"num_steps_by_episode lacks episodes: {missing[:5]}")

    variants = [(tol, final) for tol in tolerances for final in (True, False)]
    boundaries = {variant: BoundaryCounts(0, 0, 0) for variant in variants}
    labels = LabelCounts(0, 0)
    segments = SegmentCounts(0, 0, 0)
    for episode_id, truth in truth_by_episode.items():
        pred = pred_by_episode.get(episode_id, [])
        num_steps = num_steps_by_episode[episode_id]
        try:
            for tol, final in variants:
                boundaries[(tol, final)] += boundary_scores(pred, truth, tol, final, num_steps)
            labels += label_accuracy(pred, truth, num_steps)
            segments += segment_matches(pred, truth)
        except ValueError as error:
            raise PlaysegError(f"episode {episode_id!r}: {error}") from error

    results: dict[str, float | int] = {
        "episodes": len(truth_by_episode),
        "pred_segments": segments.num_pred,
        "true_segments": segments.num_truth,
    }
    for (tol, final), counts in boundaries.items():
        results[boundary_key("precision", tol, final)] = counts.precision
        results[boundary_key("recall", tol, final)] = counts.recall
        results[boundary_key("f1", tol, final)] = counts.f1
    results["label_accuracy"] = labels.accuracy
    results["label_steps"] = labels.total
    results["segment_precision"] = segments.precision
    results["segment_recall"] = segments.recall
    return results


def format_metrics_table(results: Mapping[str, float | int]) -> str:
    """A plain-text table of an ``evaluate`` result."""
    tolerances = sorted(
        {int(m.group(1)) for key in results if (m := re.match(r"boundary_f1_tol(\d+)$", key))}
    )
    lines = [
        f"episodes {results['episodes']}, predicted segments {results['pred_segments']}, "
        f"true segments {results['true_segments']}",
        f"{'boundaries':<30}{'precision':>10}{'recall':>10}{'F1':>10}",
    ]
    for tol in tolerances:
        for final in (True, False):
            name = ("exact" if tol == 0 else f"+-{tol} steps") + ("" if final else ", no final boundary")
            row = [results[boundary_key(metric, tol, final)] for metric in ("precision", "recall", "f1")]
            lines.append(f"{name:<30}" + "".join(f"{value:>10.3f}" for value in row))
    lines.append(
        f"{'label accuracy':<30}{results['label_accuracy']:>10.3f}  ({results['label_steps']} steps)"
    )
    lines.append(
        f"{'segment precision/recall':<30}{results['segment_precision']:>10.3f}{results['segment_recall']:>10.3f}"
    )
    return "\n".join(lines)
