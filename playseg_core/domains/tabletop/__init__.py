"""Tabletop play: a top-down table where a round end effector pushes 8 blocks (pymunk physics, OpenCV
rendering), a scripted teleoperator carrying out instructions one after another, a task oracle that
decides completion, and generator presets. See docs/tabletop.md.

The data is robot-shaped (a camera, a state vector, a continuous 2-D velocity action), so the generic
step encoders and the generic ``bc`` policy (augment/policy.py) read it as they are: this package adds
no encoders, no policies of its own and no segment-length bounds (the ones derived from the annotated
segments apply). Importing it imports neither pymunk nor OpenCV; the modules that run the world do.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from playseg_core.domains.tabletop.spec import CAMERA, DOMAIN

POLICIES: dict[str, Any] = {}
"""The policies of this domain (see playseg_core.domains): none; the generic ``bc`` policy reads its data."""

PRESET_NAMES = ("tiny", "small", "paper")
"""The dataset sizes `generate_dataset` knows (generate.py PRESETS)."""


def generate_dataset(
    out: str | Path,
    preset: str,
    seed: int = 0,
    workers: int = 1,
    progress: bool = True,
    overwrite: bool = False,
    annotated_share: float | None = None,
) -> Any:
    """Tabletop play of the named preset into the dataset directory ``out`` (`playseg generate`)."""
    from playseg_core.domains.tabletop import generate

    chosen = generate.get_preset(preset, annotated_share=annotated_share)
    return generate.generate_dataset(out, chosen, seed, workers, progress, overwrite)


def play_config(**settings: Any) -> Any:
    """A `play.PlayConfig` with ``settings`` (for callers that reach this domain by name)."""
    from playseg_core.domains.tabletop.play import PlayConfig

    return PlayConfig(**settings)


def record_robot_log(config: Any, seed: int, state_hz: float = 50.0) -> Any:
    """The play episode of ``seed`` as a robot logs it (robot_log.py): streams with times, for writing
    standard-message bags (playseg_ros/tabletop)."""
    from playseg_core.domains.tabletop.robot_log import record_robot_log as record

    return record(config, seed, state_hz=state_hz)


__all__ = [
    "CAMERA",
    "DOMAIN",
    "POLICIES",
    "PRESET_NAMES",
    "generate_dataset",
    "play_config",
    "record_robot_log",
]
