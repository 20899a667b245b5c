"""Play Segmentation decoding: the most likely segmentation of an episode from segment-end logits.

Score matrix convention: ``end_logits`` has shape (T, L_max) and
``end_logits[i, k]`` is the logit that the segment starting at step i ends at step ``i + k + 1``, i.e. the
segment ``[i, i+k+1)`` of k+1 actions. Entries with ``i + k + 1 > T`` are ignored (they may hold anything,
NaN included).

The log-score of a segment ``[i, j)`` is
``log s(i, j) = sum_{i<t<j} log(1 - p(i, t)) + log p(i, j)``, and a segmentation's score is the sum of its
segments' scores. ``decode_segments`` finds the exact maximum with the recursion
``V[0] = 0, V[j] = max_i V[i] + log s(i, j)`` in O(T * L_max). ``OnlineDecoder`` runs the same recursion
one step at a time and commits segments as soon as every surviving best path agrees on them.

Tie rule (shared by every decoder here, so their outputs are identical): among equally good last
segments ending at j, the one with the smallest start wins.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from playseg_core.errors import PlaysegError

__all__ = [
    "Commit",
    "Decoded",
    "OnlineDecoder",
    "decode_segments",
    "end_columns",
    "log_sigmoid",
    "segment_log_scores",
]


@dataclass(frozen=True)
class Decoded:
    """A segmentation covering ``[0, T)`` exactly.

    segments: (start, end) pairs in order. log_score: the total log-score.
    segment_log_scores: log s(start, end) of each segment, in the same order.
    """

    segments: list[tuple[int, int]]
    log_score: float
    segment_log_scores: list[float] = field(default_factory=list)


@dataclass(frozen=True)
class Commit:
    """A segment committed by the online decoder at step ``decided_at`` (the push that decided it)."""

    start: int
    end: int
    log_score: float
    decided_at: int

    @property
    def latency(self) -> int:
        """Steps between the segment's end boundary and the step at which it was committed."""
        return self.decided_at - self.end


def log_sigmoid(z: np.ndarray) -> np.ndarray:
    """log(sigmoid(z)) without overflow for any finite z: ``min(z, 0) - log1p(exp(-|z|))``."""
    z = np.asarray(z, dtype=np.float64)
    return np.minimum(z, 0.0) - np.log1p(np.exp(-np.abs(z)))


def _check_end_logits(end_logits: np.ndarray) -> np.ndarray:
    logits = np.asarray(end_logits, dtype=np.float64)
    if logits.ndim != 2:
        raise PlaysegError(f"end_logits must be a 2-D (T, L_max) array, got shape {logits.shape}")
    num_steps, max_len = logits.shape
    if num_steps < 1 or max_len < 1:
        raise PlaysegError(f"end_logits must have at least one step and one length, got shape {logits.shape}")
    valid = _valid_mask(num_steps, max_len)
    if np.isnan(logits[valid]).any():
        raise PlaysegError("end_logits contains NaN in a used entry (one with start + k + 1 <= T)")
    return logits


def _valid_mask(num_steps: int, max_len: int) -> np.ndarray:
    """(T, L) mask of the entries [i, k] whose segment [i, i+k+1) ends inside the episode."""
    starts = np.arange(num_steps)[:, None]
    lengths = np.arange(1, max_len + 1)[None, :]
    return starts + lengths <= num_steps


def check_lengths(min_len: int, max_len: int, available: int) -> None:
    if not isinstance(min_len, int | np.integer) or min_len < 1:
        raise PlaysegError(f"min_len must be an integer >= 1, got {min_len!r}")
    if not isinstance(max_len, int | np.integer) or max_len < min_len:
        raise PlaysegError(f"max_len must be an integer >= min_len ({min_len}), got {max_len!r}")
    if max_len > available:
        raise PlaysegError(f"max_len ({max_len}) exceeds the number of score columns L_max ({available})")


def check_feasible(num_steps: int, min_len: int, max_len: int) -> None:
    """Some number of segments K with K*min_len <= T <= K*max_len must exist."""
    smallest_count = -(-num_steps // max_len)
    if smallest_count * min_len > num_steps:
        raise PlaysegError(
            f"no segmentation of T={num_steps} steps into segments of length "
            f"min_len={min_len}..max_len={max_len} exists"
        )


def segment_log_scores(end_logits: np.ndarray) -> np.ndarray:
    """(T, L_max) float64 array of ``log s(i, i+k+1)``; entries ending after T are -inf.

    Row i accumulates ``logsigmoid(-z)`` (the log-probability of *not* ending) along k with an exclusive
    cumulative sum, then adds ``logsigmoid(z)`` of the end itself.
    """
    logits = _check_end_logits(end_logits)
    valid = _valid_mask(*logits.shape)
    # Unused entries are zeroed so NaN/inf there cannot leak into the sums of used entries.
    logits = np.where(valid, logits, 0.0)
    not_ending = log_sigmoid(-logits)
    prefix = np.zeros_like(not_ending)
    np.cumsum(not_ending[:, :-1], axis=1, out=prefix[:, 1:])
    scores = prefix + log_sigmoid(logits)
    scores[~valid] = -np.inf
    return scores


def _by_end(scores: np.ndarray) -> np.ndarray:
    """Re-index (T, L) scores by end: ``out[j-1, m] = log s(j-L+m, j)``, -inf where the start is < 0.

    Candidates for an end are thus ordered by increasing start, so argmax's first-maximum rule is the
    smallest-start tie rule.
    """
    num_steps, max_len = scores.shape
    padded = np.concatenate([np.full((max_len, max_len), -np.inf), scores], axis=0)
    ends = np.arange(1, num_steps + 1)[:, None]
    m = np.arange(max_len)[None, :]
    return padded[ends - max_len + m + max_len, max_len - 1 - m]


def decode_segments(end_logits: np.ndarray, min_len: int = 1, max_len: int | None = None) -> Decoded:
    """The exact most likely segmentation of ``[0, T)`` into segments of ``min_len..max_len`` actions.

    ``max_len`` defaults to L_max (the number of columns). Raises ValueError naming the argument when the
    logits are malformed or no segmentation is feasible.
    """
    logits = _check_end_logits(end_logits)
    num_steps, available = logits.shape
    max_len = available if max_len is None else max_len
    check_lengths(min_len, max_len, available)
    check_feasible(num_steps, min_len, max_len)

    by_end = _by_end(segment_log_scores(logits[:, :max_len]))
    width = max_len - min_len + 1  # candidates m = 0..width-1, starts j-max_len .. j-min_len
    by_end = np.ascontiguousarray(by_end[:, :width])
    # values[p + max_len] = V[p]; the leading -inf stand for starts before 0.
    values = np.full(num_steps + max_len + 1, -np.inf)
    values[max_len] = 0.0
    back = np.zeros(num_steps + 1, dtype=np.int64)
    for j in range(1, num_steps + 1):
        candidates = values[j : j + width] + by_end[j - 1]
        best = int(candidates.argmax())
        values[j + max_len] = candidates[best]
        back[j] = j - max_len + best

    total = float(values[num_steps + max_len])
    if total == -np.inf:
        raise PlaysegError("end_logits: every feasible segmentation has log-score -inf")
    segments = _backtrack(back, num_steps, stop=0)
    seg_scores = [float(by_end[end - 1, start - end + max_len]) for start, end in segments]
    return Decoded(segments=segments, log_score=total, segment_log_scores=seg_scores)


def _backtrack(back: np.ndarray | dict[int, int], end: int, stop: int) -> list[tuple[int, int]]:
    """Follow backpointers from ``end`` down to ``stop``; segments in increasing order."""
    segments = []
    while end > stop:
        start = int(back[end])
        segments.append((start, end))
        end = start
    segments.reverse()
    return segments


def end_columns(end_logits: np.ndarray) -> np.ndarray:
    """(T, L) array whose row t-1 is the online decoder's input at step t.

    ``out[t-1, k] = end_logits[t-k-1, k]`` (the logit that segment ``[t-k-1, t)`` ends at t); NaN where
    ``t-k-1 < 0`` (ignored by the decoder).
    """
    logits = np.asarray(end_logits, dtype=np.float64)
    if logits.ndim != 2:
        raise PlaysegError(f"end_logits must be a 2-D (T, L_max) array, got shape {logits.shape}")
    num_steps, max_len = logits.shape
    steps = np.arange(1, num_steps + 1)[:, None]
    k = np.arange(max_len)[None, :]
    starts = steps - k - 1
    return np.where(starts >= 0, logits[np.maximum(starts, 0), k], np.nan)


class OnlineDecoder:
    """Exact PS decoding on a stream: commits segments as soon as all surviving best paths agree.

    Call ``push(end_column)`` for t = 1, 2, ... (``end_column[k]`` is the logit that ``[t-k-1, t)`` ends
    at t; entries with ``t-k-1 < 0`` and beyond ``max_len`` are ignored), then ``finish()`` at the end of
    the episode. The concatenated output equals ``decode_segments`` on the same scores with the same
    ``min_len``/``max_len``, bit for bit: both run the same float operations in the same order.

    Convergence test: the positions from which a later segment may still start are the last
    max_len positions with a finite V (the frontier). Their backpointer chains form a tree rooted at the
    last committed boundary; the tree is kept pruned to the ancestors of frontier positions (a node is
    dropped when it leaves the frontier childless), and the root moves down while it is not on the
    frontier and has a single child. Every move commits a segment. Amortised O(1) tree work per step.
    Since a later segment may start at any frontier position, a boundary is committed no earlier than
    max_len-1 steps after it when every position is reachable (min_len=1); the latency is exactly what
    the scores need beyond that, not a fixed window.

    Memory is O(max_len) plus the tree since the last committed boundary.
    """

    def __init__(self, max_len: int, min_len: int = 1) -> None:
        check_lengths(min_len, max_len, max_len)
        self.max_len = int(max_len)
        self.min_len = int(min_len)
        self.reset()

    def reset(self) -> None:
        """Start a new episode."""
        self.t = 0
        self.finished = False
        self.commits: list[Commit] = []
        self._root = 0  # the last committed boundary
        # _not_ending[k]: sum of log(1 - p) for the open segment starting at t-k-1, over ends in (start, t).
        self._not_ending = np.zeros(self.max_len)
        # _recent[m] = V[t - max_len + 1 + m], the last max_len values (-inf before step 0).
        self._recent = np.full(self.max_len, -np.inf)
        self._recent[-1] = 0.0
        # The pruned backpointer tree: parent (segment start), segment score and children per position.
        self._back: dict[int, int] = {}
        self._score_of: dict[int, float] = {}
        self._children: dict[int, set[int]] = {0: set()}

    def push(self, end_column: np.ndarray) -> list[tuple[int, int]]:
        """Feed the end logits of step t (the next step); returns the segments committed by it."""
        if self.finished:
            raise RuntimeError("OnlineDecoder.push after finish(); call reset() to start a new episode")
        column = np.asarray(end_column, dtype=np.float64)
        if column.ndim != 1 or column.shape[0] < self.max_len:
            raise PlaysegError(
                f"end_column must be a 1-D array of at least max_len={self.max_len} logits, "
                f"got shape {column.shape}"
            )
        t = self.t + 1
        usable = min(t, self.max_len)  # k < usable <=> start t-k-1 >= 0
        column = column[: self.max_len].copy()
        if np.isnan(column[:usable]).any():
            raise PlaysegError(f"end_column at step {t} contains NaN in a used entry")
        column[usable:] = 0.0

        scores = self._not_ending + log_sigmoid(column)
        scores[usable:] = -np.inf
        # Candidates ordered by increasing start (k descending), as in decode_segments.
        width = self.max_len - self.min_len + 1
        by_start = scores[::-1][:width]
        candidates = self._recent[:width] + by_start
        best = int(candidates.argmax())
        value = candidates[best]

        shifted = self._not_ending + log_sigmoid(-column)
        self._not_ending[1:] = shifted[:-1]
        self._not_ending[0] = 0.0
        self._recent[:-1] = self._recent[1:]
        self._recent[-1] = value
        self.t = t

        if value > -np.inf:  # unreachable positions never join the tree
            start = t - self.max_len + best
            self._back[t] = start
            self._score_of[t] = float(by_start[best])
            self._children[t] = set()
            self._children[start].add(t)
        self._prune(t - self.max_len)  # it just left the frontier
        return self._advance_root()

    def _on_frontier(self, position: int) -> bool:
        return position > self.t - self.max_len

    def _prune(self, position: int) -> None:
        """Drop ``position`` and then its ancestors while they are childless and off the frontier."""
        while (
            position != self._root
            and position in self._children
            and not self._children[position]
            and not self._on_frontier(position)
        ):
            parent = self._back.pop(position)
            del self._score_of[position], self._children[position]
            self._children[parent].discard(position)
            position = parent

    def _advance_root(self) -> list[tuple[int, int]]:
        """Move the root down its single-child path: all surviving best paths pass through it."""
        root = self._root
        while not self._on_frontier(root) and len(self._children[root]) == 1:
            root = next(iter(self._children[root]))
        return self._commit_to(root, decided_at=self.t) if root != self._root else []

    def _commit_to(self, boundary: int, decided_at: int) -> list[tuple[int, int]]:
        segments = _backtrack(self._back, boundary, stop=self._root)
        for start, end in segments:
            self.commits.append(Commit(start, end, self._score_of[end], decided_at))
            del self._children[start]
            del self._back[end], self._score_of[end]
        self._root = boundary
        return segments

    def finish(self) -> list[tuple[int, int]]:
        """Close the episode at the last step pushed; returns the remaining segments."""
        if self.finished:
            raise RuntimeError("OnlineDecoder.finish called twice; call reset() to start a new episode")
        if self.t == 0:
            raise PlaysegError(
                "OnlineDecoder.finish: no step was pushed (an episode needs at least one step)"
            )
        check_feasible(self.t, self.min_len, self.max_len)
        if self._recent[-1] == -np.inf:
            raise PlaysegError("end_column stream: every feasible segmentation has log-score -inf")
        self.finished = True
        segments = self._commit_to(self.t, decided_at=self.t)
        self._back.clear()
        self._score_of.clear()
        self._children = {self.t: set()}
        return segments

    @property
    def log_score(self) -> float:
        """V[t]: the best total log-score of a segmentation of the steps pushed so far."""
        return float(self._recent[-1])
