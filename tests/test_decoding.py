"""PS decoding: scores, exact offline DP, online decoder and the reference-style DP agree."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from playseg_core.ps.decoding import (
    OnlineDecoder,
    decode_segments,
    end_columns,
    segment_log_scores,
)
from playseg_core.ps.reference_style import reference_style_decode


def scalar_log_sigmoid(z: float) -> float:
    """Independent scalar log(sigmoid(z)), stable on both sides."""
    if z >= 0:
        return -math.log1p(math.exp(-z))
    return z - math.log1p(math.exp(z))


def direct_log_score(logits: np.ndarray, start: int, end: int) -> float:
    """log s(start, end) straight from the definition: not ending at start+1..end-1, then ending at end."""
    total = 0.0
    for t in range(start + 1, end):
        total += scalar_log_sigmoid(-float(logits[start, t - start - 1]))
    return total + scalar_log_sigmoid(float(logits[start, end - start - 1]))


def all_segmentations(num_steps: int, min_len: int, max_len: int, start: int = 0):
    """Every split of [start, num_steps) into segments of min_len..max_len actions."""
    if start == num_steps:
        yield []
        return
    for length in range(min_len, max_len + 1):
        if start + length > num_steps:
            break
        for rest in all_segmentations(num_steps, min_len, max_len, start + length):
            yield [(start, start + length), *rest]


def brute_force(logits: np.ndarray, min_len: int, max_len: int):
    """(best score, best segmentation) by enumeration, or None when no segmentation exists."""
    best = None
    for segmentation in all_segmentations(logits.shape[0], min_len, max_len):
        score = sum(direct_log_score(logits, s, e) for s, e in segmentation)
        if best is None or score > best[0]:
            best = (score, segmentation)
    return best


def run_online(logits: np.ndarray, min_len: int, max_len: int) -> tuple[list, OnlineDecoder]:
    decoder = OnlineDecoder(max_len=max_len, min_len=min_len)
    segments = []
    for column in end_columns(logits):
        segments.extend(decoder.push(column))
    segments.extend(decoder.finish())
    return segments, decoder


@st.composite
def decoding_problems(draw):
    """Small random problems: continuous logits (ties have probability 0), random length limits."""
    num_steps = draw(st.integers(1, 9))
    max_len = draw(st.integers(1, num_steps))
    min_len = draw(st.integers(1, max_len))
    columns = draw(st.integers(max_len, max_len + 2))
    seed = draw(st.integers(0, 2**32 - 1))
    scale = draw(st.floats(0.1, 30.0))
    logits = np.random.default_rng(seed).normal(size=(num_steps, columns)) * scale
    return logits, min_len, max_len


# --- segment scores ---------------------------------------------------------------------------------


def test_segment_log_scores_match_the_definition_and_mask_unused_entries():
    logits = np.random.default_rng(1).normal(size=(6, 4)) * 3
    scores = segment_log_scores(logits)
    for i in range(6):
        for k in range(4):
            if i + k + 1 <= 6:
                assert scores[i, k] == pytest.approx(direct_log_score(logits, i, i + k + 1), abs=1e-12)
            else:
                assert scores[i, k] == -np.inf


def test_segment_log_scores_are_stable_for_huge_logits():
    # Segment from 0: does not end at 1 (z=-1e4), ends at 2 (z=+1e4); so log s(0,1) = -1e4, log s(0,2) ~ 0.
    logits = np.array([[-1e4, 1e4, -1e4], [1e4, -1e4, 1e4], [1e4, 1e4, 1e4]])
    scores = segment_log_scores(logits)
    assert np.isfinite(scores).sum() == 6  # segments ending inside T=3: 3 + 2 + 1
    assert scores[0, 0] == pytest.approx(-1e4)  # ends at 1 with z=-1e4
    assert scores[0, 1] == pytest.approx(0.0, abs=1e-12)  # passes 1 (z=-1e4), ends at 2 (z=+1e4)
    assert scores[0, 2] == pytest.approx(-2e4)  # passes 1, passes 2 (z=+1e4: -1e4), ends at 3 (-1e4)
    assert scores[1, 0] == pytest.approx(0.0, abs=1e-12)
    assert scores[1, 1] == pytest.approx(-2e4)
    assert scores[2, 0] == pytest.approx(0.0, abs=1e-12)


def test_segment_log_scores_reject_nan_in_used_entries_only():
    logits = np.zeros((3, 3))
    logits[2, 1] = np.nan  # segment [2, 4) ends after T=3: ignored
    assert np.isfinite(segment_log_scores(logits)[0]).all()
    logits[1, 1] = np.nan  # segment [1, 3): used
    with pytest.raises(ValueError, match="end_logits"):
        segment_log_scores(logits)


# --- offline decoding --------------------------------------------------------------------------------


@settings(max_examples=150, deadline=None)
@given(decoding_problems())
def test_decode_segments_equals_brute_force(problem):
    logits, min_len, max_len = problem
    expected = brute_force(logits, min_len, max_len)
    if expected is None:
        with pytest.raises(ValueError, match="no segmentation"):
            decode_segments(logits, min_len=min_len, max_len=max_len)
        return
    decoded = decode_segments(logits, min_len=min_len, max_len=max_len)
    assert decoded.log_score == pytest.approx(expected[0], rel=1e-9, abs=1e-9)
    assert decoded.segments == expected[1]
    assert sum(decoded.segment_log_scores) == pytest.approx(decoded.log_score, rel=1e-9, abs=1e-9)


def test_decode_segments_covers_the_episode_within_the_length_limits():
    logits = np.random.default_rng(2).normal(size=(500, 12)) * 4
    decoded = decode_segments(logits, min_len=3, max_len=10)
    assert decoded.segments[0][0] == 0 and decoded.segments[-1][1] == 500
    for (_, end), (start, _) in zip(decoded.segments, decoded.segments[1:], strict=False):
        assert end == start
    assert all(3 <= e - s <= 10 for s, e in decoded.segments)


def test_decode_segments_follows_clear_end_signals():
    # Logit +20 exactly at length 3 and -20 elsewhere: segments of three steps.
    logits = np.full((12, 5), -20.0)
    logits[:, 2] = 20.0
    assert decode_segments(logits).segments == [(0, 3), (3, 6), (6, 9), (9, 12)]
    # Infinite logits act as hard constraints: segments of exactly two steps.
    hard = np.full((8, 4), -np.inf)
    hard[:, 1] = np.inf
    decoded = decode_segments(hard)
    assert decoded.segments == [(0, 2), (2, 4), (4, 6), (6, 8)] and decoded.log_score == 0.0


def test_decode_segments_ties_prefer_the_smallest_start():
    # All logits 0: every segment of length n scores n*log(1/2), so every segmentation ties.
    decoded = decode_segments(np.zeros((5, 3)))
    assert decoded.segments == [(0, 2), (2, 5)]  # backtracking from 5 takes the longest last segment
    assert decoded.segments == run_online(np.zeros((5, 3)), 1, 3)[0]


@pytest.mark.parametrize(
    ("shape", "kwargs", "message"),
    [
        ((4,), {}, "end_logits"),
        ((0, 3), {}, "end_logits"),
        ((4, 3), {"min_len": 0}, "min_len"),
        ((4, 3), {"max_len": 5}, "max_len"),
        ((4, 3), {"min_len": 3, "max_len": 2}, "max_len"),
        ((2, 3), {"min_len": 3}, "no segmentation"),
        ((5, 4), {"min_len": 3, "max_len": 4}, "no segmentation"),
    ],
)
def test_decode_segments_rejects_bad_input(shape, kwargs, message):
    with pytest.raises(ValueError, match=message):
        decode_segments(np.zeros(shape), **kwargs)


# --- online decoding ---------------------------------------------------------------------------------


@settings(max_examples=150, deadline=None)
@given(decoding_problems())
def test_online_decoder_equals_offline(problem):
    logits, min_len, max_len = problem
    try:
        offline = decode_segments(logits, min_len=min_len, max_len=max_len)
    except ValueError:
        with pytest.raises(ValueError, match="no segmentation"):
            run_online(logits, min_len, max_len)
        return
    segments, decoder = run_online(logits, min_len, max_len)
    assert segments == offline.segments
    assert decoder.log_score == offline.log_score
    assert [(c.start, c.end) for c in decoder.commits] == offline.segments
    assert [c.log_score for c in decoder.commits] == offline.segment_log_scores
    assert all(c.latency >= 0 for c in decoder.commits)


def earliest_commit_points(logits: np.ndarray, min_len: int, max_len: int) -> list[int]:
    """After each step t, the latest position every live best-path chain passes through.

    Independent plain-Python DP; live = the last max_len positions with a finite best score.
    """
    num_steps = logits.shape[0]
    value = [0.0] + [-math.inf] * num_steps
    back = [0] * (num_steps + 1)
    points = []
    for t in range(1, num_steps + 1):
        for start in range(max(0, t - max_len), t - min_len + 1):
            if value[start] > -math.inf:
                candidate = value[start] + direct_log_score(logits, start, t)
                if candidate > value[t]:
                    value[t], back[t] = candidate, start
        chains = []
        for position in range(max(0, t - max_len + 1), t + 1):
            if value[position] > -math.inf:
                chain = {position}
                while position > 0:
                    position = back[position]
                    chain.add(position)
                chains.append(chain)
        points.append(max(set.intersection(*chains)))
    return points


@settings(max_examples=100, deadline=None)
@given(decoding_problems())
def test_online_decoder_commits_as_soon_as_the_best_paths_converge(problem):
    logits, min_len, max_len = problem
    decoder = OnlineDecoder(max_len=max_len, min_len=min_len)
    committed_to = []
    for column in end_columns(logits):
        decoder.push(column)
        committed_to.append(decoder.commits[-1].end if decoder.commits else 0)
    assert committed_to == earliest_commit_points(logits, min_len, max_len)


@settings(max_examples=100, deadline=None)
@given(
    st.integers(1, 12),
    st.integers(1, 5),
    st.integers(1, 5),
    st.integers(0, 2**32 - 1),
    st.sampled_from([(-1.0, 0.0, 1.0), (-np.inf, np.inf), (-np.inf, 0.0, 2.0)]),
)
def test_online_decoder_equals_offline_under_ties_and_infinite_logits(
    num_steps, max_len, min_len, seed, values
):
    # Few distinct (or infinite) logit values make exact ties common: the tie rule must agree too.
    min_len = min(min_len, max_len)
    logits = np.random.default_rng(seed).choice(values, size=(num_steps, max_len))
    try:
        offline = decode_segments(logits, min_len=min_len, max_len=max_len)
    except ValueError:
        with pytest.raises(ValueError, match="no segmentation|-inf"):
            run_online(logits, min_len, max_len)
        return
    segments, decoder = run_online(logits, min_len, max_len)
    assert segments == offline.segments
    assert decoder.log_score == offline.log_score


def test_online_decoder_equals_offline_on_a_long_noisy_episode():
    rng = np.random.default_rng(3)
    logits = rng.normal(size=(3000, 25)) * 3
    logits[np.arange(3000), rng.integers(0, 25, size=3000)] += 8  # some likely ends
    segments, decoder = run_online(logits, 2, 25)
    assert segments == decode_segments(logits, min_len=2, max_len=25).segments
    # Bounded memory: backpointers only since the last committed boundary.
    assert len(decoder._back) == 0


def test_online_decoder_commits_before_the_episode_ends_when_ends_are_clear():
    logits = np.full((30, 5), -20.0)
    logits[:, 2] = 20.0
    decoder = OnlineDecoder(max_len=5)
    committed_early = []
    for column in end_columns(logits):
        committed_early.extend(decoder.push(column))
    # Every boundary except the last few is decided while streaming. Off-grid paths (ending at 3n+1,
    # 3n+2) stay off-grid for a segment or two before they rejoin, so latency exceeds max_len a little.
    assert committed_early == [(3 * n, 3 * n + 3) for n in range(8)]
    assert all(c.latency < 2 * 5 for c in decoder.commits)
    assert committed_early + decoder.finish() == [(3 * n, 3 * n + 3) for n in range(10)]


def test_online_decoder_rejects_misuse():
    decoder = OnlineDecoder(max_len=4)
    with pytest.raises(ValueError, match="end_column"):
        decoder.push(np.zeros(3))
    with pytest.raises(ValueError, match="finish"):
        decoder.finish()
    decoder.push(np.array([0.0, np.nan, np.nan, np.nan]))  # entries before step 0 are ignored
    with pytest.raises(ValueError, match="end_column"):
        decoder.push(np.array([np.nan, 0.0, 0.0, 0.0]))
    committed = decoder.push(np.zeros(4))
    committed += decoder.finish()
    assert committed == decode_segments(np.zeros((2, 4))).segments
    with pytest.raises(RuntimeError, match="reset"):
        decoder.push(np.zeros(4))
    decoder.reset()
    decoder.push(np.zeros(4))
    # A fresh episode: one step in, V[1] = log sigmoid(0), nothing decided yet (positions 0 and 1 live).
    assert decoder.t == 1 and decoder.commits == []
    assert decoder.log_score == pytest.approx(math.log(0.5))
    with pytest.raises(ValueError, match="min_len"):
        OnlineDecoder(max_len=4, min_len=0)
    with pytest.raises(ValueError, match="max_len"):
        OnlineDecoder(max_len=2, min_len=3)


# --- reference-style DP ------------------------------------------------------------------------------


@settings(max_examples=60, deadline=None)
@given(decoding_problems())
def test_reference_style_decode_equals_decode_segments(problem):
    logits, min_len, max_len = problem
    scores = segment_log_scores(logits)

    def score_segment(i: int, j: int) -> float:
        return float(scores[i, j - i - 1])

    try:
        offline = decode_segments(logits, min_len=min_len, max_len=max_len)
    except ValueError:
        with pytest.raises(ValueError, match="no segmentation"):
            reference_style_decode(score_segment, logits.shape[0], min_len, max_len)
        return
    reference = reference_style_decode(score_segment, logits.shape[0], min_len, max_len)
    assert reference.segments == offline.segments
    assert reference.log_score == pytest.approx(offline.log_score, rel=1e-12, abs=1e-12)
