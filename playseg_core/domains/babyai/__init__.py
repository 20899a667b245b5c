"""BabyAI GoToLocal play (minigrid): generator and presets, the grid-tile step encoder, the FiLM policy
and its GoToLocal evaluation.

Importing the package registers the grid-tile encoder; minigrid is imported only by the modules that run
the environment (play.py, evaluation.py, generate.py).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from playseg_core.data.features import STATE, Features
from playseg_core.domains.babyai.encoder import frames_are_tiled, grid_tile_spec
from playseg_core.domains.babyai.spec import CAMERA, DOMAIN
from playseg_core.ps.encoders import EncoderSpec

SEGMENT_BOUNDS = {"min_len": 1, "max_len": 25, "k_max": 5}
"""The measured setting for BabyAI play (tasks of 1-21 steps, mostly ~5): L_min, L_max and the negatives'
shift range k_max, used instead of the values derived from the annotated segments."""


def step_encoders(features: Features) -> dict[str, EncoderSpec | None]:
    """BabyAI's choice of step encoders (see ps/encoders.py `choose_encoders`): the grid-tile encoder for
    its tile-rendered camera, and not the symbolic grid state (the camera frame shows the same grid)."""
    chosen: dict[str, EncoderSpec | None] = {STATE: None}
    if CAMERA in features and frames_are_tiled(features[CAMERA].shape):
        chosen[CAMERA] = grid_tile_spec(features[CAMERA])
    return chosen


def _film_policy(config: dict[str, Any]) -> Any:
    from playseg_core.domains.babyai.learner import FilmPolicyLearner

    return FilmPolicyLearner.from_config(config)


POLICIES = {"film": _film_policy}
"""The policies of this domain (see playseg_core.domains)."""

PRESET_NAMES = ("tiny", "sample", "small", "paper")
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
    """BabyAI play of the named preset into the dataset directory ``out`` (`playseg generate`)."""
    from playseg_core.domains.babyai import generate

    chosen = generate.get_preset(preset, annotated_share=annotated_share)
    return generate.generate_dataset(out, chosen, seed, workers, progress, overwrite)


__all__ = ["DOMAIN", "POLICIES", "PRESET_NAMES", "SEGMENT_BOUNDS", "generate_dataset", "step_encoders"]
