"""The reference implementation's way of segmenting: the oracle of the equivalence tests and the baseline
of the decoding benchmarks.

`reference_style_decode`: the paper's DP over (number of segments, end) with Python loops.
`reference_style_segment`: the whole model (encoder included) re-run on every prefix o_i..o_j, one pass
each, then `reference_style_decode`. Both return what playseg_core's fast path returns (same model, same
episode); benchmarks measure how much slower they are.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch

from playseg_core.data.episode import Episode, Segment
from playseg_core.errors import PlaysegError
from playseg_core.ps.decoding import Decoded, check_feasible, check_lengths, log_sigmoid
from playseg_core.ps.encoders import as_tensors
from playseg_core.ps.model import PSModel
from playseg_core.ps.segmentation import labelled_segment


def reference_style_decode(
    score_segment: Callable[[int, int], float], num_steps: int, min_len: int, max_len: int
) -> Decoded:
    """The paper's DP over (number of segments, end), with Python loops, for benchmarking only.

    ``score_segment(i, j)`` returns log s(i, j) and is called once per candidate segment (as the
    reference scores every prefix once). ``S[n][j]`` is the best score of ``[0, j)`` split into n
    segments: ``S[n][j] = max_l S[n-1][l] + log s(l, j)``; the answer is ``max_n S[n][T]``. Ties prefer
    the smallest start, then the fewest segments. The best score equals ``decode_segments``'s; the
    segmentation too unless several segmentations tie (after rounding), where the two tie rules differ.
    """
    if not isinstance(num_steps, int | np.integer) or num_steps < 1:
        raise PlaysegError(f"num_steps must be an integer >= 1, got {num_steps!r}")
    check_lengths(min_len, max_len, max_len)
    check_feasible(num_steps, min_len, max_len)
    score: dict[tuple[int, int], float] = {}
    for i in range(num_steps):
        for j in range(i + min_len, min(i + max_len, num_steps) + 1):
            score[(i, j)] = float(score_segment(i, j))

    neg_inf = float("-inf")
    max_count = num_steps // min_len
    best = [[neg_inf] * (num_steps + 1) for _ in range(max_count + 1)]
    back = [[-1] * (num_steps + 1) for _ in range(max_count + 1)]
    best[0][0] = 0.0
    for n in range(1, max_count + 1):
        for j in range(n * min_len, num_steps + 1):
            for start in range(max(0, j - max_len), j - min_len + 1):
                candidate = best[n - 1][start] + score[(start, j)]
                if candidate > best[n][j]:
                    best[n][j] = candidate
                    back[n][j] = start

    count = max(range(1, max_count + 1), key=lambda n: (best[n][num_steps], -n))
    total = best[count][num_steps]
    if total == neg_inf:
        raise PlaysegError("score_segment: every feasible segmentation has log-score -inf")
    segments: list[tuple[int, int]] = []
    end = num_steps
    for n in range(count, 0, -1):
        start = back[n][end]
        segments.append((start, end))
        end = start
    segments.reverse()
    return Decoded(segments, total, [score[s] for s in segments])


@torch.no_grad()
def reference_style_segment(model: PSModel, episode: Episode, min_len: int = 1) -> list[Segment]:
    """Same result as `segment_episode`, computed the reference's way (benchmarking only).

    Every prefix o_i .. o_j (j - i <= L_max) goes through the full model separately, steps encoded anew
    each time; then the DP over (number of segments, end) of `reference_style_decode`.
    """
    model.eval()
    if model.lookahead:
        raise PlaysegError("the reference reads no step past an end: use a model with end_lookahead 0")
    num_steps = episode.num_steps
    if num_steps == 0:
        return []
    inputs = model.encoders.episode_inputs(episode)

    def encode(start: int, end: int) -> torch.Tensor:  # the prefix o_start .. o_end, encoded anew
        return model.encode_steps(as_tensors(inputs, slice(start, end + 1)))

    max_len = min(model.max_len, num_steps)
    end_logit: dict[tuple[int, int], float] = {}
    starts = [torch.tensor([start == 0]) for start in range(num_steps)]
    for start in range(num_steps):
        for end in range(start + 1, min(start + max_len, num_steps) + 1):
            hidden = model.trunk(encode(start, end)[None], starts[start])
            end_logit[(start, end)] = float(model.raw_end_logits(hidden)[0, -1] + model.end_bias)

    def score_segment(start: int, end: int) -> float:
        # log s(i, j): not ending at every t in (i, j), then ending at j; summed in order like cumsum.
        total = 0.0
        for t in range(start + 1, end):
            total += float(log_sigmoid(-end_logit[(start, t)]))
        return total + float(log_sigmoid(end_logit[(start, end)]))

    decoded = reference_style_decode(score_segment, num_steps, min_len, max_len)
    segments = []
    for (start, end), log_prob in zip(decoded.segments, decoded.segment_log_scores, strict=True):
        hidden = model.trunk(encode(start, end)[None], starts[start])
        segments.append(labelled_segment(model, start, end, model.label_head(hidden[0, -1]), log_prob))
    return segments
