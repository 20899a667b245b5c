"""Samples of a topic aligned onto the step clock: which sample (or pair of samples) each step takes.

A step at time t takes, within the feature's tolerance (inclusive: a sample exactly ``tolerance`` away
matches, one a nanosecond further does not):

- ``nearest``:  the sample closest to t (on a tie the earlier one);
- ``previous``: the latest sample at or before t (what was known at t; commands that hold until replaced);
- ``linear``:   the samples at or before and after t, both within the tolerance, interpolated linearly
  (numeric features only; a sample exactly at t is taken as it is).

A step without a match is not filled in: `Alignment.matched` is False there and the step is dropped.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from playseg_core.errors import PlaysegError
from playseg_ros.convert.mapping import AlignMethod


@dataclass(frozen=True)
class Alignment:
    """For each of N steps: the samples ``lo`` and ``hi`` it reads and the weight of ``hi`` (0 unless
    interpolated); ``matched`` is False where no sample lies within the tolerance."""

    lo: np.ndarray  # (N,) int64 sample indices (meaningless where not matched)
    hi: np.ndarray
    weight: np.ndarray  # (N,) float64 in [0, 1)
    matched: np.ndarray  # (N,) bool

    def take(self, values: np.ndarray) -> np.ndarray:
        """The aligned rows of ``values`` (one row per sample) for the matched steps only."""
        lo, hi, weight = self.lo[self.matched], self.hi[self.matched], self.weight[self.matched]
        if not np.any(weight):
            return values[lo]
        w = weight.reshape(-1, *([1] * (values.ndim - 1)))
        return ((1.0 - w) * values[lo] + w * values[hi]).astype(values.dtype)


def align(step_ns: np.ndarray, sample_ns: np.ndarray, method: AlignMethod, tolerance_ns: int) -> Alignment:
    """Align samples stamped ``sample_ns`` (sorted, int64 ns) onto steps at ``step_ns`` (int64 ns)."""
    steps = np.asarray(step_ns, dtype=np.int64)
    samples = np.asarray(sample_ns, dtype=np.int64)
    n = len(steps)
    none = np.zeros(n, dtype=bool)
    if len(samples) == 0:
        zeros = np.zeros(n, dtype=np.int64)
        return Alignment(zeros, zeros, np.zeros(n), none)
    if np.any(np.diff(samples) < 0):
        raise PlaysegError("align: sample times must be sorted")
    last = len(samples) - 1
    # at_or_before: the latest sample with time <= step (-1 if none)
    at_or_before = np.searchsorted(samples, steps, side="right") - 1
    before = np.clip(at_or_before, 0, last)
    after = np.clip(at_or_before + 1, 0, last)
    has_before = at_or_before >= 0
    has_after = at_or_before + 1 <= last
    distance_before = np.where(has_before, steps - samples[before], np.iinfo(np.int64).max)
    distance_after = np.where(has_after, samples[after] - steps, np.iinfo(np.int64).max)
    zero_weight = np.zeros(n)
    if method == "previous":
        return Alignment(before, before, zero_weight, has_before & (distance_before <= tolerance_ns))
    if method == "nearest":
        take_after = distance_after < distance_before  # a tie goes to the earlier sample
        chosen = np.where(take_after, after, before)
        distance = np.minimum(distance_before, distance_after)
        return Alignment(chosen, chosen, zero_weight, distance <= tolerance_ns)
    if method == "linear":
        exact = has_before & (distance_before == 0)
        bracketed = (
            has_before & has_after & (distance_before <= tolerance_ns) & (distance_after <= tolerance_ns)
        )
        span = np.where(bracketed & ~exact, samples[after] - samples[before], 1).astype(np.float64)
        weight = np.where(bracketed & ~exact, distance_before / span, 0.0)
        hi = np.where(exact, before, after)
        return Alignment(before, hi, weight, exact | bracketed)
    raise PlaysegError(f"align: unknown method {method!r}")
