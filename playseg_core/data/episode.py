"""The data model: play episodes and segments. Every other module speaks these types.

A play episode is ``(o_0, a_0, o_1, a_1, ..., o_T)``: T+1 observations (an RGB frame and an optional
low-dimensional state each) and T actions. A segment is a half-open step range ``[start, end)`` of one
episode plus an instruction: actions ``a_start .. a_end-1`` and observations ``o_start .. o_end``. The
boundary observation ``o_end`` belongs to both neighbouring segments and is stored once, in the episode.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np


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
            raise ValueError(f"segment [{self.start}, {self.end}) must satisfy 0 <= start < end")

    @property
    def length(self) -> int:
        """Number of actions in the segment."""
        return self.end - self.start


@dataclass
class Episode:
    """One play episode.

    frames:  (T+1, H, W, 3) uint8 RGB observations.
    states:  (T+1, *state_shape) low-dimensional observations (BabyAI: (T+1, 8, 8, 3) uint8), or None.
    actions: (T, action_dim) float32 (BabyAI: action_dim 1, the discrete action index).
    segments: the labelled segments known for this episode (all, some or none of them), sorted, disjoint.
    """

    episode_id: str
    frames: np.ndarray
    actions: np.ndarray
    states: np.ndarray | None = None
    segments: list[Segment] = field(default_factory=list)

    def __post_init__(self) -> None:
        check_episode(self)

    @property
    def num_steps(self) -> int:
        """T, the number of actions (the episode has T+1 observations)."""
        return int(self.actions.shape[0])


@dataclass
class SegmentClip:
    """A labelled segment carrying its own data: a LabelledSegment message, a trainer buffer record.

    ``segment`` is in the source episode's step numbering (with its label, confidence and log-score);
    ``actions`` holds its ``length`` actions a_start..a_end-1, ``frames`` and ``states`` (each optional)
    its ``length + 1`` observations o_start..o_end. ``source`` says who labelled it: the segmentation
    model id, or "annotation".
    """

    episode_id: str
    segment: Segment
    actions: np.ndarray
    frames: np.ndarray | None = None
    states: np.ndarray | None = None
    source: str = ""

    def __post_init__(self) -> None:
        seg = self.segment
        name = f"episode {self.episode_id!r} segment [{seg.start}, {seg.end})"
        if self.actions.ndim != 2 or self.actions.shape[0] != seg.length:
            raise ValueError(f"{name}: actions must be ({seg.length}, action_dim), got {self.actions.shape}")
        frames = self.frames
        if frames is not None and (
            frames.ndim != 4
            or frames.shape[0] != seg.length + 1
            or frames.shape[-1] != 3
            or frames.dtype != np.uint8
        ):
            raise ValueError(
                f"{name}: frames must be ({seg.length + 1}, H, W, 3) uint8, got {frames.shape} {frames.dtype}"
            )
        if self.states is not None and self.states.shape[:1] != (seg.length + 1,):
            raise ValueError(f"{name}: states must have {seg.length + 1} rows, got shape {self.states.shape}")

    @classmethod
    def from_episode(cls, episode: Episode, segment: Segment, source: str) -> SegmentClip:
        """The clip of ``segment`` of ``episode`` (views into the episode's arrays)."""
        start, end = segment.start, segment.end
        return cls(
            episode_id=episode.episode_id,
            segment=segment,
            actions=episode.actions[start:end],
            frames=episode.frames[start : end + 1],
            states=None if episode.states is None else episode.states[start : end + 1],
            source=source,
        )


def check_episode(episode: Episode) -> None:
    """Raise ValueError naming the episode and field when the arrays or segments are inconsistent."""
    name = f"episode {episode.episode_id!r}"
    frames, actions = episode.frames, episode.actions
    if frames.ndim != 4 or frames.shape[-1] != 3 or frames.dtype != np.uint8:
        raise ValueError(f"{name}: frames must be (T+1, H, W, 3) uint8, got {frames.shape} {frames.dtype}")
    if actions.ndim != 2:
        raise ValueError(f"{name}: actions must be (T, action_dim), got shape {actions.shape}")
    if frames.shape[0] != actions.shape[0] + 1:
        raise ValueError(
            f"{name}: {frames.shape[0]} frames for {actions.shape[0]} actions (need actions + 1 frames)"
        )
    if episode.states is not None and episode.states.shape[0] != frames.shape[0]:
        raise ValueError(f"{name}: {episode.states.shape[0]} states for {frames.shape[0]} frames")
    check_segments(episode.segments, actions.shape[0], name)


def check_segments(segments: Sequence[Segment], num_steps: int, name: str) -> None:
    """Segments must be sorted, disjoint and inside ``[0, num_steps]``."""
    previous_end = 0
    for seg in segments:
        if seg.end > num_steps:
            raise ValueError(
                f"{name}: segment [{seg.start}, {seg.end}) ends after the episode ({num_steps} steps)"
            )
        if seg.start < previous_end:
            raise ValueError(
                f"{name}: segment [{seg.start}, {seg.end}) overlaps or precedes the previous one"
            )
        previous_end = seg.end


def boundaries(segments: Sequence[Segment]) -> list[int]:
    """End steps of the segments, in order (the positions where a segment ends)."""
    return [seg.end for seg in segments]
