"""The data model: play episodes and segments. Every other module speaks these types.

A play episode is ``(o_0, a_0, o_1, a_1, ..., o_T)``: T+1 observations (any number of camera frames and
an optional low-dimensional state each) and T actions. A segment is a half-open step range ``[start, end)`` of one
episode plus an instruction: actions ``a_start .. a_end-1`` and observations ``o_start .. o_end``. The
boundary observation ``o_end`` belongs to both neighbouring segments and is stored once, in the episode.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from playseg_core.errors import PlaysegError


@dataclass(frozen=True, order=True)
class Segment:
    """Steps ``[start, end)`` of an episode carrying out ``instruction``.

    ``confidence`` is the label probability (1.0 for human annotations); ``log_prob`` the segment's
    log-score under the segmentation model (0.0 for annotations).
    """

    start: int
    end: int
    instruction: str = ""
    confidence: float = 1.0
    log_prob: float = 0.0

    def __post_init__(self) -> None:
        if not 0 <= self.start < self.end:
            raise PlaysegError(f"segment [{self.start}, {self.end}) must satisfy 0 <= start < end")

    @property
    def length(self) -> int:
        """Number of actions in the segment."""
        return self.end - self.start


@dataclass
class Episode:
    """One play episode: T actions and T+1 observations.

    actions: (T, *action_shape) float32 (a discrete action is its index, shape (T, 1)).
    images:  camera feature name (``observation.images.<camera>``) -> (T+1, H, W, 3) uint8; any number of
             cameras, none included.
    state:   (T+1, *state_shape) low-dimensional observations, or None.
    segments: the labelled segments known for this episode (all, some or none of them), sorted, disjoint.
    timestamps: (T+1,) float64 recording time of each observation in seconds from its source's start (a
             bag's first message), non-decreasing; None when the source has no clock.
    source:  where the episode comes from, JSON-serialisable: ``{"bag": path, "topics": [...],
             "start_ns": the bag's first message time}``, or ``{"generator": domain, "preset": name,
             "seed": run seed, "episode_seed": seed}`` (docs/dataset-format.md); None when unknown.

    data/features.py names and describes these arrays (`Features`).
    """

    episode_id: str
    actions: np.ndarray
    images: dict[str, np.ndarray] = field(default_factory=dict)
    state: np.ndarray | None = None
    segments: list[Segment] = field(default_factory=list)
    timestamps: np.ndarray | None = None
    source: dict[str, Any] | None = None

    def __post_init__(self) -> None:
        check_episode(self)

    @property
    def num_steps(self) -> int:
        """T, the number of actions (the episode has T+1 observations)."""
        return int(self.actions.shape[0])

    def with_segments(self, segments: Sequence[Segment]) -> Episode:
        """The same data (no copy) with other segments."""
        return replace(self, segments=list(segments))


@dataclass
class SegmentClip:
    """A labelled segment carrying its own data: a LabelledSegment message, a trainer buffer record.

    ``segment`` is in the source episode's step numbering (with its label, confidence and log-score);
    ``actions`` holds its ``length`` actions a_start..a_end-1, ``images`` and ``state`` (as in `Episode`)
    its ``length + 1`` observations o_start..o_end. ``source`` says who labelled it: the segmentation
    model id, or "annotation".
    """

    episode_id: str
    segment: Segment
    actions: np.ndarray
    images: dict[str, np.ndarray] = field(default_factory=dict)
    state: np.ndarray | None = None
    source: str = ""

    def __post_init__(self) -> None:
        seg = self.segment
        name = f"episode {self.episode_id!r} segment [{seg.start}, {seg.end})"
        if self.actions.ndim < 2 or self.actions.shape[0] != seg.length:
            raise PlaysegError(
                f"{name}: actions must be ({seg.length}, action_dim), got {self.actions.shape}"
            )
        _check_observations(name, self.images, self.state, seg.length + 1)

    @classmethod
    def from_episode(cls, episode: Episode, segment: Segment, source: str) -> SegmentClip:
        """The clip of ``segment`` of ``episode`` (views into the episode's arrays)."""
        start, end = segment.start, segment.end
        return cls(
            episode_id=episode.episode_id,
            segment=segment,
            actions=episode.actions[start:end],
            images={name: frames[start : end + 1] for name, frames in episode.images.items()},
            state=None if episode.state is None else episode.state[start : end + 1],
            source=source,
        )

    def as_episode(self, episode_id: str) -> Episode:
        """The clip as a one-segment episode (steps renumbered from 0)."""
        seg = self.segment
        return Episode(
            episode_id=episode_id,
            actions=np.asarray(self.actions, np.float32),
            images={name: np.asarray(frames) for name, frames in self.images.items()},
            state=None if self.state is None else np.asarray(self.state),
            segments=[Segment(0, seg.length, seg.instruction, seg.confidence, seg.log_prob)],
        )


def _check_observations(
    name: str, images: dict[str, np.ndarray], state: np.ndarray | None, rows: int
) -> None:
    for camera, frames in images.items():
        if frames.ndim != 4 or frames.shape[0] != rows or frames.shape[-1] != 3 or frames.dtype != np.uint8:
            raise PlaysegError(
                f"{name}: images[{camera!r}] must be ({rows}, H, W, 3) uint8, got {frames.shape} {frames.dtype}"
            )
    if state is not None and state.shape[:1] != (rows,):
        raise PlaysegError(f"{name}: state must have {rows} rows, got shape {state.shape}")


def check_episode(episode: Episode) -> None:
    """Raise ValueError naming the episode and field when the arrays or segments are inconsistent."""
    name = f"episode {episode.episode_id!r}"
    if episode.actions.ndim < 2:
        raise PlaysegError(f"{name}: actions must be (T, action_dim), got shape {episode.actions.shape}")
    _check_observations(name, episode.images, episode.state, episode.num_steps + 1)
    times = episode.timestamps
    if times is not None and (
        times.shape != (episode.num_steps + 1,)
        or not np.all(np.isfinite(times))
        or np.any(np.diff(times) < 0)
    ):
        raise PlaysegError(
            f"{name}: timestamps must be ({episode.num_steps + 1},) finite non-decreasing seconds, "
            f"got shape {times.shape}"
        )
    check_segments(episode.segments, episode.num_steps, name)


def check_segments(segments: Sequence[Segment], num_steps: int, name: str) -> None:
    """Segments must be sorted, disjoint and inside ``[0, num_steps]``."""
    previous_end = 0
    for seg in segments:
        if seg.end > num_steps:
            raise PlaysegError(
                f"{name}: segment [{seg.start}, {seg.end}) ends after the episode ({num_steps} steps)"
            )
        if seg.start < previous_end:
            raise PlaysegError(
                f"{name}: segment [{seg.start}, {seg.end}) overlaps or precedes the previous one"
            )
        previous_end = seg.end
