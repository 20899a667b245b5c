"""Training samples of Play Segmentation: positives, negatives, and batches of windows.

Every annotated segment [s, e) is a positive; its negatives move the end earlier, widen both sides, take
the window before it, and shift it left / right, by k drawn from 1..k_max, always inside the episode and
never longer than the model's L_max. Beyond the paper (`dense_prefix_negatives`): the trunk is causal
from the start, so one pass over a positive window also yields the end logit of every proper prefix
[s, s+m), m < e-s, which did *not* end, supervised as 0. That is exactly the `log(1 - p_seg)` term of
the segment score the decoder maximises.

The end head is trained as the decoder reads it (decoding.py): as a hazard, the probability that the
segment ends at j given that it has not ended before j. So from an annotated segment's start nothing
at or past its end is supervised as "not ended": the paper's "end later" negative [s, e+k) is left out
(the decoder already scores [s, e+k) low through the factor 1 - p_end(e)), and so is a negative of the
next segment that starts where a short one starts and reaches its end (a window before, shifted or
widened by k >= its length). Why: docs/segmentation.md "Training".

Steps are encoded once per batch (or once per training, for encoders that learn nothing: fixed_features.py);
windows are gathered from those features by index.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch

from playseg_core.data.episode import Episode, Segment
from playseg_core.ps.encoders import StepEncoders
from playseg_core.ps.fixed_features import FixedFeatureCache
from playseg_core.ps.symmetries import ClipSymmetries

NEGATIVE_KINDS = ("end_earlier", "widened", "before", "shift_left", "shift_right")


@dataclass(frozen=True)
class Sample:
    """A training window [start, end) of one episode; is_end says whether a segment ends at `end`."""

    start: int
    end: int
    is_end: bool
    kind: str  # "positive" or one of NEGATIVE_KINDS


def _draw(rng: np.random.Generator, high: int) -> int | None:
    """k uniform in 1..high, or None when the range is empty."""
    return int(rng.integers(1, high + 1)) if high >= 1 else None


def segment_samples(
    start: int, end: int, num_steps: int, max_len: int, k_max: int, rng: np.random.Generator
) -> list[Sample]:
    """The positive [start, end) and up to five negatives; a kind that cannot fit is left out.

    A segment longer than max_len cannot be scored by the model and yields no samples at all.
    """
    length = end - start
    if not 0 < length <= max_len or end > num_steps or start < 0:
        return []
    samples = [Sample(start, end, True, "positive")]

    def add(kind: str, s: int, e: int) -> None:
        samples.append(Sample(s, e, False, kind))

    room_left, room_right, room_len = start, num_steps - end, max_len - length
    if (k := _draw(rng, min(k_max, length - 1))) is not None:
        add("end_earlier", start, end - k)
    if (k3 := _draw(rng, min(k_max, room_left, room_len - 1))) is not None:
        if (k4 := _draw(rng, min(k_max, room_right, room_len - k3))) is not None:
            add("widened", start - k3, end + k4)
    if (k := _draw(rng, min(k_max, room_left, max_len))) is not None:
        add("before", start - k, start)
    if (k := _draw(rng, min(k_max, room_left))) is not None:
        add("shift_left", start - k, end - k)
    if (k := _draw(rng, min(k_max, room_right))) is not None:
        add("shift_right", start + k, end + k)
    return samples


# ----------------------------------------------------------------------------------------------------
# Batches


@dataclass
class Batch:
    """Training windows of a few episodes. A window starts at one step and is supervised at positions.

    Samples that share a start share a window (the trunk is causal from the start, so one pass yields
    the end logit at every position): the positive and its end-earlier negative both live in the window
    of the segment's true start.
    """

    inputs: dict[str, torch.Tensor]  # step-encoder input rows by feature, N rows (see StepEncoders)
    encoded: dict[str, torch.Tensor]  # or, for encoders that learn nothing, their output rows
    window_index: torch.Tensor  # (S, L_max+1+lookahead) rows into features (N: a zero row past the end)
    starts_episode: torch.Tensor  # (S,) bool: the window starts at step 0
    end_target: torch.Tensor  # (S, L_max+1) 1 where a segment ends at that position
    end_weight: torch.Tensor  # (S, L_max+1) 1 where the end head is supervised
    label_window: torch.Tensor  # (M,) window of each positive
    label_position: torch.Tensor  # (M,) its length (the position of its end in the window)
    labels: torch.Tensor  # (M,) its class index

    @property
    def needed_len(self) -> torch.Tensor:
        """(S,) positions each window needs: 1 + the last supervised position."""
        positions = torch.arange(self.end_weight.shape[1], device=self.end_weight.device)
        return (positions * (self.end_weight > 0)).amax(1) + 1


def label_index(instructions: Sequence[str]) -> dict[str, int]:
    return {text: index for index, text in enumerate(instructions)}


def make_batch(
    items: Sequence[tuple[Episode, Segment]],
    classes: dict[str, int],
    encoders: StepEncoders,
    max_len: int,
    k_max: int,
    rng: np.random.Generator,
    negatives: bool = True,
    dense_prefix_negatives: bool = False,
    symmetries: ClipSymmetries | None = None,
    fixed: FixedFeatureCache | None = None,
    lookahead: int = 0,
) -> Batch:
    """The windows of the annotated segments `items` (only positives if not `negatives`).

    Only the steps each segment's samples can touch (k_max around it) are included: a batch holds
    segments from many episodes, which trains far faster than whole episodes (many scenes per step).
    With `dense_prefix_negatives`, the true-start window is also supervised as "not ended" at every
    position before the end (the end-earlier negatives for all k at once), and at none past it. No
    negative is supervised that starts at an annotated segment's start of the episode and ends at or
    past that segment's end (module docstring). With `symmetries` (augmentation), each segment's clip is
    turned by one of them drawn at random, its instruction with it (a turned instruction the classes lack
    leaves the clip as it was). The batch carries every step encoder's input rows, or, for the features
    ``fixed`` caches, their encoder output rows. ``lookahead``: each window also holds that many steps
    past its last supervised position (the PS end head reads them: `ModelConfig.end_lookahead`).
    """
    regions = [
        (max(0, seg.start - k_max), min(ep.num_steps, seg.end + k_max + lookahead)) for ep, seg in items
    ]
    zero_row = sum(hi - lo + 1 for lo, hi in regions)
    num_pos = max_len + 1
    cached = fixed.features if fixed is not None else []
    raw = [spec.feature for spec in encoders.specs if spec.feature not in cached]
    inputs: dict[str, list[torch.Tensor]] = {feature: [] for feature in raw}
    encoded: dict[str, list[torch.Tensor]] = {feature: [] for feature in cached}
    rows, starts_episode, targets, weights = [], [], [], []
    label_window, label_position, labels = [], [], []
    offset = 0
    for (ep, seg), (lo, hi) in zip(items, regions, strict=True):
        annotated_ends = {other.start: other.end for other in ep.segments}
        recorded = encoders.recorded_clip(ep, lo, hi, raw)
        label, number = classes[seg.instruction], 0
        if symmetries is not None:
            number = int(rng.integers(symmetries.count))
            instruction = symmetries.turn_instruction(seg.instruction, number) if number else seg.instruction
            if instruction in classes:
                label = classes[instruction]
                recorded = symmetries.turn_clip(recorded, number) if number else recorded
            else:
                number = 0
        clips = encoders.clip_inputs(recorded, lo, f"episode {ep.episode_id!r}")
        for feature, clip in clips.items():
            inputs[feature].append(torch.from_numpy(np.array(clip)))
        if fixed is not None:
            for feature, part in fixed.clip_rows(ep, lo, hi, number, symmetries).items():
                encoded[feature].append(part)
        samples = segment_samples(seg.start, seg.end, ep.num_steps, max_len, k_max, rng)
        windows: dict[int, int] = {}  # start -> row
        for sample in samples:
            if not negatives and not sample.is_end:
                continue
            annotated_end = annotated_ends.get(sample.start)
            if not sample.is_end and annotated_end is not None and sample.end >= annotated_end:
                continue  # from an annotated segment's start, at or past its end: not a negative
            if sample.start not in windows:
                windows[sample.start] = len(rows)
                steps = sample.start + np.arange(num_pos + lookahead)
                rows.append(np.where(steps <= hi, offset + steps - lo, zero_row))
                starts_episode.append(sample.start == 0)
                targets.append(np.zeros(num_pos, np.float32))
                weights.append(np.zeros(num_pos, np.float32))
            row, position = windows[sample.start], sample.end - sample.start
            targets[row][position] = float(sample.is_end)
            weights[row][position] = 1.0
            if sample.is_end:
                label_window.append(row)
                label_position.append(position)
                labels.append(label)
        if negatives and dense_prefix_negatives and seg.start in windows:
            row, length = windows[seg.start], seg.end - seg.start
            weights[row][1 : length + 1] = 1.0  # targets stay 0 except at the true end
        offset += hi - lo + 1

    def stack(arrays: list[np.ndarray], dtype: type, width: int = num_pos) -> torch.Tensor:
        return torch.from_numpy(np.array(arrays, dtype=dtype).reshape(-1, width))

    return Batch(
        inputs={feature: torch.cat(parts) for feature, parts in inputs.items()},
        encoded={feature: torch.cat(parts) for feature, parts in encoded.items()},
        window_index=stack(rows, np.int64, num_pos + lookahead),
        starts_episode=torch.tensor(starts_episode, dtype=torch.bool),
        end_target=stack(targets, np.float32),
        end_weight=stack(weights, np.float32),
        label_window=torch.tensor(label_window, dtype=torch.long),
        label_position=torch.tensor(label_position, dtype=torch.long),
        labels=torch.tensor(labels, dtype=torch.long),
    )
