"""The symmetries of a world that PS and its labeller may train on (``augment``): how a recorded clip and its
instruction look under each; a domain declares its own, `camera_symmetries` turns camera frames only.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    import torch

    from playseg_core.ps.encoders import EncoderSpec


@dataclass(frozen=True)
class ClipSymmetries:
    """The symmetries `augment` trains on: ``count`` of them, number 0 the identity.

    ``turn_clip(recorded, number)``: a clip as recorded (`StepEncoders.recorded_clip`: observations and
    the actions that led to them, by feature; any may be absent) under symmetry ``number``, as new arrays.
    ``turn_instruction(text, number)``: what the instruction says of the turned world. A domain's own
    are its ``clip_symmetries`` (playseg_core/domains); `camera_symmetries` turns the frames only.
    ``turn_encoded(spec, rows, number)`` (optional): the output rows of an encoder that learns nothing
    (`spec`) for the turned clip, from its rows of the clip as recorded, where the domain knows how that
    encoder's output turns (object positions turn as the world does), else None: training then encodes
    each symmetry's frames once instead of every symmetry's (ps/fixed_features.py).
    """

    count: int
    turn_clip: Callable[[dict[str, np.ndarray], int], dict[str, np.ndarray]]
    turn_instruction: Callable[[str, int], str]
    turn_encoded: Callable[[EncoderSpec, torch.Tensor, int], torch.Tensor | None] | None = None


def camera_symmetries(cameras: Sequence[str]) -> ClipSymmetries:
    """The 8 rotations of the ``cameras``' frames by multiples of 90 degrees, each also mirrored (number
    k + 4m: k quarter turns, then a mirror if m), instructions unchanged: for top-down views whose
    instructions and ends do not depend on orientation. Actions are left as they are, so only for models
    that read none (a mirror swaps left and right turns)."""

    def turn_clip(recorded: dict[str, np.ndarray], number: int) -> dict[str, np.ndarray]:
        turned = dict(recorded)
        for feature in cameras:
            if feature in recorded:
                frames = np.rot90(np.asarray(recorded[feature]), k=number % 4, axes=(1, 2))
                turned[feature] = np.ascontiguousarray(frames[:, :, ::-1] if number >= 4 else frames)
        return turned

    return ClipSymmetries(8, turn_clip, lambda text, number: text)
