"""The tabletop policy ``tabletop.bc``: the generic behaviour-cloning policy (augment/bc_policy.py: camera,
state, instruction embedding, continuous velocity) evaluated in the tabletop simulator (evaluation.py)
instead of not at all. Its camera goes through this domain's object maps (encoder.py) found as blocks,
or, by the ``camera_encoder`` setting, pooled to a grid or to keypoints, or through the generic CNN;
`POLICY_DEFAULTS` are its settings unless told otherwise."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from playseg_core.augment.bc_policy import BCPolicy, BCPolicyLearner
from playseg_core.augment.policy import PolicyTrainReport
from playseg_core.data.episode import SegmentClip
from playseg_core.data.features import Features
from playseg_core.domains.tabletop.encoder import ObjectMapConfig, object_map_spec
from playseg_core.domains.tabletop.spec import (
    CAMERA,
    DEFAULT_IMAGE_SIZE,
    DOMAIN,
    EVAL_STEP_BUDGET,
    STATE_NAMES,
)
from playseg_core.errors import PlaysegError
from playseg_core.ps.encoders import EncoderSpec

POLICY_NAME = f"{DOMAIN}.bc"

CAMERA_ENCODERS: dict[str, str | None] = {
    "image_cnn": None,
    "object_maps": "grid",
    "keypoints": "keypoints",
    "blocks": "blocks",
}
"""The policy's ``camera_encoder`` setting -> the object-map encoder's pooling (None: the generic CNN).
``blocks`` gives each block where its colour is (the default), ``keypoints`` the image coordinates of
``camera_keypoints`` learnt detectors (a spatial soft-argmax each), ``object_maps`` the 8x8-grid features
PS read before the blocks (encoder.py)."""

POLICY_DEFAULTS: dict[str, Any] = {
    "camera_encoder": "blocks",
    "instruction_attention": 2,
    "instruction_film": True,
    "known_instructions": False,
    "word_order": True,
    "hash_buckets": 4096,
    "state_exclude": ",".join(name for name in STATE_NAMES if "velocity" in name),
    "moved_entity_loss": 1.0,
    "related_entity_loss": 1.0,
    "augment": True,
}
"""What ``tabletop.bc`` sets unless told otherwise (docs/tabletop.md "The policy and its evaluation"): the blocks as entities
the instruction attends over (which block, which other block), read through the instruction's words only
with their order (which block is pushed next to which: a bag of words has the two the same; more hash
buckets for the ~300 tokens), not the measured velocity, which lets behaviour cloning repeat the
last command, the block a segment pushes as what its instruction's first query should find (the
moved-entity loss: the block moved most is the named one in 95-98 % of the block tasks' annotated
segments) and the block it ends next to as the second's, and the table's 8 symmetries (`augment`)."""


@dataclass
class TabletopPolicyLearner:
    """`augment.policy.PolicyLearner` of ``tabletop.bc``: a ``bc`` learner for the tabletop's features
    (camera of ``image_size`` pixels) and the simulator evaluation's step budget."""

    bc: BCPolicyLearner
    image_size: int = DEFAULT_IMAGE_SIZE
    eval_max_steps: int = EVAL_STEP_BUDGET
    name: str = POLICY_NAME
    task_set: str = "all"  # the instructions the evaluation gives (instructions.py TASK_SETS)

    @classmethod
    def from_config(cls, config: dict[str, Any]) -> TabletopPolicyLearner:
        """From plain settings: ``image_size`` (the dataset's camera side, default 96), ``eval_max_steps``
        (default spec.EVAL_STEP_BUDGET), ``task_set`` (the evaluation's instructions: ``all`` or ``calvin``,
        as the data's play), ``camera_encoder`` (CAMERA_ENCODERS) and ``camera_keypoints``, and
        any setting of the ``bc`` policy (BCTrainConfig, ``channels`` =
        ``hidden``); ValueError naming an unknown or bad one."""
        from playseg_core.domains.tabletop.instructions import TASK_SETS
        from playseg_core.domains.tabletop.play import PlayConfig  # the physics: only when built
        from playseg_core.domains.tabletop.symmetry import random_symmetry

        if config.get("camera_encoder") == "keypoints":  # keypoints are no entities to attend over
            config = {"instruction_attention": 0, **config}
        try:  # the defaults teach only the queries there are
            queries = int(config.get("instruction_attention", POLICY_DEFAULTS["instruction_attention"]))
        except (TypeError, ValueError):
            queries = 2  # a bad value: `BCPolicyLearner.from_config` names it
        if queries < 2:
            config = {
                "related_entity_loss": 0.0,
                **({"moved_entity_loss": 0.0} if queries < 1 else {}),
                **config,
            }
        if config.get("camera_encoder", POLICY_DEFAULTS["camera_encoder"]) != "blocks":
            # a grid's cells never move: the losses would have no target to teach
            config = {"moved_entity_loss": 0.0, "related_entity_loss": 0.0, **config}
        config = {**POLICY_DEFAULTS, **config}
        image_size = int(config.pop("image_size", DEFAULT_IMAGE_SIZE))
        camera = str(config.pop("camera_encoder"))
        keypoints = int(config.pop("camera_keypoints", ObjectMapConfig.keypoints))
        eval_max_steps = int(config.pop("eval_max_steps", EVAL_STEP_BUDGET))
        tasks = str(config.pop("task_set", "all"))
        if tasks not in TASK_SETS:
            raise PlaysegError(
                f"policy {POLICY_NAME}: task_set must be one of {list(TASK_SETS)}, got {tasks!r}"
            )
        if eval_max_steps <= 0:
            raise PlaysegError(f"policy {POLICY_NAME}: eval_max_steps must be > 0, got {eval_max_steps}")
        features = PlayConfig(image_size=image_size).features  # ValueError naming a bad image size
        if camera not in CAMERA_ENCODERS or keypoints < 1:
            raise PlaysegError(
                f"policy {POLICY_NAME}: camera_encoder must be one of {list(CAMERA_ENCODERS)} and "
                f"camera_keypoints >= 1, got {camera!r} and {keypoints}"
            )
        pooling = CAMERA_ENCODERS[camera]
        if pooling == "keypoints" and int(config.get("instruction_attention", 0)) > 0:
            raise PlaysegError(
                f"policy {POLICY_NAME}: camera_encoder 'keypoints' gives no entities for "
                "instruction_attention; set instruction_attention=0 or another camera_encoder"
            )

        def encoder_choice(data: Features) -> dict[str, EncoderSpec | None]:
            if pooling is None or CAMERA not in data:
                return {}  # the generic CNN
            return {
                CAMERA: object_map_spec(
                    data[CAMERA],
                    ObjectMapConfig(pooling=pooling, keypoints=keypoints, twins_by_size=pooling == "blocks"),
                )
            }

        bc = BCPolicyLearner.from_config(config, features, encoder_choice, random_symmetry)
        return cls(bc, image_size, eval_max_steps, task_set=tasks)

    @property
    def features(self) -> Features:
        return self.bc.features

    def train(
        self, clips: Sequence[SegmentClip], progress: bool = False
    ) -> tuple[BCPolicy, PolicyTrainReport]:
        return self.bc.train(clips, progress)

    def evaluate(self, policy: BCPolicy, num_episodes: int, seed: int) -> Any:
        from playseg_core.domains.tabletop.evaluation import evaluate_policy
        from playseg_core.domains.tabletop.instructions import TASK_SETS

        return evaluate_policy(
            policy, num_episodes, seed, self.eval_max_steps, self.image_size,
            num_threads=self.bc.settings.num_threads, tasks=TASK_SETS[self.task_set],
        )  # fmt: skip

    def save(self, path: Path, policy: BCPolicy, meta: dict[str, Any]) -> None:
        self.bc.save(path, policy, {**meta, "learner": self.name})

    def load(self, path: Path) -> tuple[BCPolicy, dict[str, Any]]:
        return self.bc.load(path)


__all__ = ["CAMERA_ENCODERS", "POLICY_DEFAULTS", "POLICY_NAME", "TabletopPolicyLearner"]
