"""BabyAI GoToLocal play (minigrid): generator and presets, the grid-tile step encoder, the FiLM policy
and its GoToLocal evaluation.

Importing the package registers its `Domain` and the grid-tile encoder; minigrid is imported only by the
modules that run the environment (play.py, evaluation.py, generate.py), the experiment framework only
when its experiment is asked for.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from playseg_core.data.features import STATE, Features
from playseg_core.domains import Domain, preset_generator, register_domain
from playseg_core.domains.babyai.encoder import frames_are_tiled, grid_tile_spec
from playseg_core.domains.babyai.spec import CAMERA, DOMAIN
from playseg_core.ps.encoders import EncoderSpec

if TYPE_CHECKING:
    from playseg_core.augment.policy import PolicyLearner
    from playseg_core.experiment.spec import ExperimentSpec

SEGMENT_BOUNDS = {"min_len": 1, "max_len": 25, "k_max": 5}
"""The measured setting for BabyAI play (tasks of 1-21 steps, mostly ~5): L_min, L_max and the negatives'
shift range k_max, used instead of the values derived from the annotated segments."""

TRUNK_DROPOUT = 0.0
"""No dropout in PS's trunk: BabyAI's figures (docs/segmentation.md) were measured without, on play with
thousands of annotated segments."""


def step_encoders(features: Features) -> dict[str, EncoderSpec | None]:
    """BabyAI's choice of step encoders (see ps/encoders.py `choose_encoders`): the grid-tile encoder for
    its tile-rendered camera, and not the symbolic grid state (the camera frame shows the same grid)."""
    chosen: dict[str, EncoderSpec | None] = {STATE: None}
    if CAMERA in features and frames_are_tiled(features[CAMERA].shape):
        chosen[CAMERA] = grid_tile_spec(features[CAMERA])
    return chosen


def _film_policy(config: dict[str, Any]) -> PolicyLearner:
    from playseg_core.domains.babyai.learner import FilmPolicyLearner

    return FilmPolicyLearner.from_config(config)


POLICIES = {"film": _film_policy}
"""The policies of this domain (see playseg_core.domains)."""

PRESET_NAMES = ("tiny", "sample", "small", "medium", "paper")
"""The dataset sizes `generate_dataset` knows (generate.py PRESETS)."""


generate_dataset = preset_generator("playseg_core.domains.babyai.generate")
"""BabyAI play of a named preset into a dataset directory (`playseg generate`; generate.py)."""


__all__ = [
    "DOMAIN",
    "POLICIES",
    "PRESET_NAMES",
    "SEGMENT_BOUNDS",
    "TRUNK_DROPOUT",
    "experiment",
    "generate_dataset",
    "step_encoders",
]


def experiment() -> ExperimentSpec:
    """The augmentation experiment on BabyAI (`playseg experiment babyai`, playseg_core/experiment)."""
    from playseg_core.experiment.spec import ExperimentScale, ExperimentSpec

    return ExperimentSpec(
        policy="babyai.film",
        scales={
            "tiny": ExperimentScale(
                "tiny",
                0.25,
                {"steps": 20, "batch_size": 32, "channels": 16},
                8,
                segmenter_steps=30,
                description="for tests: seconds per run, figures mean nothing",
            ),
            "small": ExperimentScale(
                "small",
                0.25,
                {"steps": 300, "batch_size": 128, "channels": 32, "learning_rate": 2e-3},
                256,
                segmenter_steps=1200,
                description="a quick look (~10 minutes on 2 cores): 640 annotated start segments of a "
                "3,000-segment pool, short budgets, segmenters trained as medium-5pct's; the figures "
                "are noisy",
                segmenter_reads_actions=False,
                segmenter_augment=True,
            ),
            "medium": ExperimentScale(
                "medium",
                0.10,
                {"steps": 1500, "batch_size": 128, "channels": 32, "learning_rate": 2e-3},
                512,
                description="the paper's split at a sixth of its size: 1,280 annotated start segments of "
                "a 15,700-segment pool; ~3 minutes per policy run on a shared 2-core CPU",
            ),
            "medium-5pct": ExperimentScale(
                "medium",
                0.05,
                {"steps": 1500, "batch_size": 128, "channels": 32, "learning_rate": 2e-3},
                512,
                description="medium's pool with half its start split: 640 annotated start segments, where "
                "the policy has headroom; PS and the labelling model read no actions and learn from "
                "rotated/mirrored clips (a top-down room: labels and ends do not depend on orientation)",
                segmenter_reads_actions=False,
                segmenter_augment=True,
            ),
            "medium-film-only": ExperimentScale(
                "medium",
                0.10,
                {
                    "steps": 3000,
                    "batch_size": 128,
                    "channels": 32,
                    "learning_rate": 2e-3,
                    "relevance_maps": 0,
                },
                512,
                description="medium's data with the policy's FiLM path only (no relevance maps): the "
                "paper's data-hungry regime, where training on the large sets is bistable; ~7 minutes "
                "per policy run",
            ),
            "paper": ExperimentScale(
                "paper",
                0.10,
                {"steps": 6000, "batch_size": 256, "channels": 64, "learning_rate": 2e-3},
                512,
                description="the paper's: 10,000 annotated of a 100,000-segment pool (not run here)",
            ),
        },  # fmt: skip
        paper={
            "gt_start": (0.544, 0.009),
            "gt_100": (0.907, 0.026),
            "oracle_relabel": (0.843, 0.032),
            "ps": (0.702, 0.023),
            "unloc": (0.583, 0.020),
            "tridet": (0.261, 0.134),
            "random_relabel": (0.053, 0.006),
        },  # fmt: skip
        paper_only={"GT - 25%": (0.645, 0.020), "GT - 50%": (0.805, 0.025)},
        paper_source="(BabyAI augmentation table, 8 seeds; start split = GT - 10%)",
    )


register_domain(
    Domain(
        name=DOMAIN,
        step_encoders=step_encoders,
        segment_bounds=SEGMENT_BOUNDS,
        trunk_dropout=TRUNK_DROPOUT,
        policies=POLICIES,
        preset_names=PRESET_NAMES,
        generate_dataset=generate_dataset,
        experiment=experiment,
    )
)
