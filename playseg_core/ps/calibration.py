"""Calibration of a trained PS model on held-out annotated play: the end bias and the label threshold.

Both are chosen on the annotated validation split, never on the play being segmented:
- `calibrate_end_bias`: the bias added to the end logit when segmenting (``PSModel.end_bias``): the
  one nearest 0 whose boundary F1 within `END_BIAS_TOLERANCE` steps is within noise of the best
  (`pick_end_bias`). Training weights the rare positive ends, which inflates the end probability the
  decoder reads as a hazard; the bias takes that back by as much as held-out play says.
- `calibrate_on_annotated` / `calibrate_threshold`: the lowest label confidence whose kept segments
  reach a target label accuracy (e.g. 0.95), used to filter extracted segments (labelling.py).
- `check_own_cuts`: what that threshold keeps of the model's *own* segmentation of the held-out
  episodes, and how many of the kept steps carry the true instruction. The threshold is chosen on true
  cuts, as the paper does; play gets the model's cuts, whose pieces (half a task, two tasks) the true
  cuts never show, so this is the figure that says what the filter will keep on play.
- `calibrate_on_own_cuts`: a threshold chosen on the model's own cuts instead, for the score that
  ranks them (`segment_probability`: the label's probability times the cut's): the filter for play when
  the true-cut threshold keeps pieces that are wrong (the experiment's ``ps_own_cuts``).
`calibrate_ps_model` does all four and returns what a checkpoint records about them.
"""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import asdict, dataclass

import numpy as np
import torch

from playseg_core.data.episode import Episode, Segment
from playseg_core.errors import PlaysegError
from playseg_core.ps.decoding import decode_segments
from playseg_core.ps.labelling import label_segments, segment_probability
from playseg_core.ps.metrics import BoundaryCounts, match_boundaries
from playseg_core.ps.model import LabelModel, PSModel
from playseg_core.ps.segmentation import segment_episode

END_BIAS_CANDIDATES: tuple[float, ...] = tuple(float(b) for b in np.arange(-3.0, 3.01, 0.25))
"""End biases `calibrate_end_bias` tries by default."""


END_BIAS_TOLERANCE = 2
"""Steps a predicted end may lie from a true one and still count when `calibrate_end_bias` scores a bias:
the tolerance segmentation is judged at (boundary F1 +-2 steps). Annotated ends are a human's choice to
a step or two; scored exactly, a bias that finds every skill's end a step early looks no better than one
that merges skills."""


@dataclass(frozen=True)
class EndBiasCalibration:
    """The end bias chosen on held-out annotated episodes, and the boundary scores it gave there.

    Scores are boundary precision / recall / F1 within ``tolerance`` steps, final boundary included.
    sweep: (bias, precision, recall, F1) of every candidate, for reports.
    """

    bias: float
    precision: float
    recall: float
    f1: float
    tolerance: int
    f1_without_bias: float  # at bias 0 (the raw end head), for comparison
    num_episodes: int
    num_boundaries: int  # true boundaries of the held-out episodes the scores count
    sweep: list[tuple[float, float, float, float]]


def pick_end_bias(f1_by_bias: Mapping[float, float], num_boundaries: int) -> float:
    """Of the biases whose boundary F1 is no more than one standard error (sqrt(F1 (1 - F1) / n) at the
    best F1, n the true boundaries scored) below the best, the one nearest 0; on a tie, the higher."""
    best = max(f1_by_bias.values())
    noise = math.sqrt(best * (1.0 - best) / max(1, num_boundaries))
    near_best = [bias for bias, f1 in f1_by_bias.items() if f1 >= best - noise]
    return min(near_best, key=lambda bias: (abs(bias), -bias))


@torch.no_grad()
def calibrate_end_bias(
    model: PSModel,
    episodes: Iterable[Episode],
    candidates: Sequence[float] = END_BIAS_CANDIDATES,
    tolerance: int = END_BIAS_TOLERANCE,
) -> EndBiasCalibration:
    """The end bias to segment with: of the `candidates` whose segmentation of the annotated `episodes`
    scores a boundary F1 within `tolerance` steps (final boundary included) no more than one standard
    error below the best, the one nearest 0 (on a tie, the higher).

    Nearest 0: the least correction of the trained end head. A few held-out episodes cannot tell biases
    apart whose F1 differ by less than their noise (a bias of +2 that wins a sweep over 69 boundaries by
    0.05 cuts play into twice as many segments as it holds); the standard error is that of a proportion
    over the true boundaries, sqrt(F1 (1 - F1) / n). With many held-out boundaries the error shrinks and
    the pick is the best F1. The model is not changed: set ``model.end_bias`` to the result's bias to
    segment with it (`calibrate_ps_model` does).
    """
    if not candidates:
        raise PlaysegError("calibrate_end_bias needs at least one candidate bias")
    model.eval()
    raw_logits, true_ends = [], []
    for episode in episodes:
        if episode.num_steps == 0 or not episode.segments:
            continue
        raw_logits.append(
            (model.end_logits(model.encode_episode(episode)) - model.end_bias).double().cpu().numpy()
        )
        true_ends.append([seg.end for seg in episode.segments])
    if not raw_logits:
        raise PlaysegError("calibrate_end_bias needs annotated episodes; none of the given ones has segments")
    allowed = sorted({float(b) for b in candidates})
    scores: dict[float, BoundaryCounts] = {}
    for bias in sorted(set(allowed) | {0.0}):  # 0.0 too, for f1_without_bias
        counts = BoundaryCounts(0, 0, 0)
        for logits, ends in zip(raw_logits, true_ends, strict=True):
            max_len = min(model.max_len, logits.shape[0])
            min_len = min(model.cfg.min_len, max_len)  # segmenting cuts with the model's L_min too
            decoded = decode_segments(logits[:, :max_len] + bias, min_len=min_len, max_len=max_len)
            pred = [end for _, end in decoded.segments]
            counts += BoundaryCounts(match_boundaries(pred, ends, tolerance), len(pred), len(ends))
        scores[bias] = counts
    chosen = pick_end_bias({b: scores[b].f1 for b in allowed}, scores[allowed[0]].num_truth)
    return EndBiasCalibration(
        bias=chosen,
        precision=scores[chosen].precision,
        recall=scores[chosen].recall,
        f1=scores[chosen].f1,
        tolerance=tolerance,
        f1_without_bias=scores[0.0].f1,
        num_episodes=len(raw_logits),
        num_boundaries=scores[chosen].num_truth,
        sweep=[(b, scores[b].precision, scores[b].recall, scores[b].f1) for b in allowed],
    )


LABEL_ACCURACY_TARGET = 0.95
"""The label accuracy on held-out annotated segments that the confidence threshold is chosen for unless
told otherwise (`calibrate_ps_model`; ``--label-accuracy``). The paper chose 90 % for CALVIN."""


def check_target_accuracy(target: float, what: str = "target_accuracy") -> float:
    """``target`` when it is a label accuracy a threshold can be chosen for, in (0, 1]; else ValueError
    naming ``what`` (the option or field it came from)."""
    if not 0.0 < target <= 1.0:
        raise PlaysegError(f"{what} must be in (0, 1], got {target}")
    return target


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
        raise PlaysegError(f"confidences {conf.shape} and correct {hits.shape} must be equal-length 1-D")
    check_target_accuracy(target_accuracy)
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
class LabelCalibration:
    threshold: float
    target_accuracy: float
    accuracy_kept: float  # label accuracy of the held-out segments the threshold keeps
    coverage: float  # share of held-out segments kept
    accuracy_all: float  # label accuracy without a threshold
    num_segments: int

    @classmethod
    def from_scores(
        cls, scores: Sequence[float], correct: Sequence[bool], target_accuracy: float, what: str
    ) -> LabelCalibration:
        """The threshold on ``scores`` for ``target_accuracy`` (`calibrate_threshold`) and what it keeps;
        ValueError saying the held-out episodes have no ``what`` when there are no scores."""
        if not scores:
            raise PlaysegError(f"calibration needs {what}; the held-out episodes have none")
        threshold = calibrate_threshold(scores, correct, target_accuracy)
        score, hits = np.asarray(scores), np.asarray(correct)
        kept = score >= threshold
        return cls(
            threshold=threshold,
            target_accuracy=target_accuracy,
            accuracy_kept=float(hits[kept].mean()) if kept.any() else float("nan"),
            coverage=float(kept.mean()),
            accuracy_all=float(hits.mean()),
            num_segments=int(score.size),
        )


def calibrate_on_annotated(
    model: PSModel | LabelModel, episodes: Iterable[Episode], target_accuracy: float
) -> LabelCalibration:
    """Label the annotated segments of held-out `episodes` and calibrate the threshold on them."""
    confidences, correct = [], []
    for episode in episodes:
        spans = [(seg.start, seg.end) for seg in episode.segments if seg.length <= model.max_len]
        truth = {(seg.start, seg.end): seg.instruction for seg in episode.segments}
        for predicted in label_segments(model, episode, spans):
            confidences.append(predicted.confidence)
            correct.append(predicted.instruction == truth[(predicted.start, predicted.end)])
    return LabelCalibration.from_scores(confidences, correct, target_accuracy, "annotated segments")


@dataclass(frozen=True)
class OwnCutsCheck:
    """A label threshold applied to a model's own segmentation of annotated episodes.

    kept / segments: segments at or above the threshold, of all cut. step_accuracy_kept: share of the
    kept segments' steps whose true instruction (the annotated segment covering the step; none = wrong)
    is the segment's label (nan when none is kept); step_accuracy_all: the same without the threshold.
    """

    threshold: float
    kept: int
    segments: int
    kept_steps: int
    step_accuracy_kept: float
    step_accuracy_all: float


def true_instructions(truth: Sequence[Segment], num_steps: int) -> list[str | None]:
    """The annotated instruction of each of ``num_steps`` steps (None where no segment of ``truth`` covers it)."""
    true_label: list[str | None] = [None] * num_steps
    for segment in truth:
        true_label[segment.start : segment.end] = [segment.instruction] * segment.length
    return true_label


def steps_labelled_right(segments: Sequence[Segment], truth: Sequence[Segment], num_steps: int) -> list[int]:
    """For each of ``segments``, how many of its steps the annotated ``truth`` labels as it does."""
    true_label = true_instructions(truth, num_steps)
    return [sum(label == s.instruction for label in true_label[s.start : s.end]) for s in segments]


def own_cuts(model: PSModel, episodes: Iterable[Episode]) -> list[tuple[Episode, list[Segment]]]:
    """Each annotated episode of ``episodes`` with ``model``'s segmentation of it, cut as play is (the
    truth hidden, the model's end bias and L_min)."""
    return [
        (episode, segment_episode(model, episode.with_segments([]), min_len=model.cfg.min_len))
        for episode in episodes
        if episode.segments
    ]


def majority_instructions(
    segments: Sequence[Segment], truth: Sequence[Segment], num_steps: int
) -> list[str | None]:
    """For each of ``segments``, the true instruction of more of its steps than any other (None: steps in
    no annotated segment outnumber each instruction's); ties go to the earliest."""
    true_label = true_instructions(truth, num_steps)
    return [Counter(true_label[s.start : s.end]).most_common(1)[0][0] for s in segments]


@torch.no_grad()
def calibrate_on_own_cuts(
    model: PSModel,
    episodes: Iterable[Episode],
    target_accuracy: float,
    cuts: Sequence[tuple[Episode, list[Segment]]] | None = None,
) -> LabelCalibration:
    """The lowest `segment_probability` whose kept own cuts of the held-out annotated ``episodes`` are
    labelled right for ``target_accuracy`` of them, a cut being right when its label is the true
    instruction of the most of its steps (`majority_instructions`; ``cuts``: `own_cuts` already
    computed). Coverage and accuracies are over the cuts; +inf when no threshold reaches the target
    (`calibrate_threshold`)."""
    scores, correct = [], []
    for episode, cut in own_cuts(model, episodes) if cuts is None else cuts:
        scores += [segment_probability(s) for s in cut]
        truth = majority_instructions(cut, episode.segments, episode.num_steps)
        correct += [s.instruction == label for s, label in zip(cut, truth, strict=True)]
    return LabelCalibration.from_scores(scores, correct, target_accuracy, "annotated episodes")


@torch.no_grad()
def check_own_cuts(
    model: PSModel,
    episodes: Iterable[Episode],
    threshold: float,
    cuts: Sequence[tuple[Episode, list[Segment]]] | None = None,
) -> OwnCutsCheck:
    """Segment the annotated ``episodes`` with ``model`` (its end bias as set) and score what
    ``threshold`` keeps (`OwnCutsCheck`; ``cuts``: `own_cuts` already computed)."""
    right, steps, kept_right, kept_steps, kept, total = 0, 0, 0, 0, 0, 0
    for episode, cut in own_cuts(model, episodes) if cuts is None else cuts:
        for segment, hits in zip(
            cut, steps_labelled_right(cut, episode.segments, episode.num_steps), strict=True
        ):
            total, right, steps = total + 1, right + hits, steps + segment.length
            if segment.confidence >= threshold:
                kept, kept_right, kept_steps = kept + 1, kept_right + hits, kept_steps + segment.length
    return OwnCutsCheck(
        threshold=threshold,
        kept=kept,
        segments=total,
        kept_steps=kept_steps,
        step_accuracy_kept=kept_right / kept_steps if kept_steps else float("nan"),
        step_accuracy_all=right / steps if steps else float("nan"),
    )


def calibrate_ps_model(
    model: PSModel, val_episodes: Sequence[Episode], target_accuracy: float = LABEL_ACCURACY_TARGET
) -> dict[str, dict]:
    """Set ``model.end_bias`` from `val_episodes`, calibrate the label threshold on them, check it on
    the model's own cuts of them and calibrate a threshold on those cuts too (both for ``target_accuracy``).

    Returns the checkpoint's record: ``{"end_bias": ..., "calibration": ..., "own_cuts": ...,
    "own_cuts_calibration": ...}`` (the paper's label threshold under "calibration", where segmenting
    commands look for it; the own-cut threshold applies to `segment_probability`).
    """
    end_bias = calibrate_end_bias(model, val_episodes)
    model.end_bias.fill_(end_bias.bias)
    labels = calibrate_on_annotated(model, val_episodes, target_accuracy)
    cuts = own_cuts(model, val_episodes)
    return {
        "end_bias": asdict(end_bias),
        "calibration": asdict(labels),
        "own_cuts": asdict(check_own_cuts(model, val_episodes, labels.threshold, cuts)),
        "own_cuts_calibration": asdict(calibrate_on_own_cuts(model, val_episodes, target_accuracy, cuts)),
    }
