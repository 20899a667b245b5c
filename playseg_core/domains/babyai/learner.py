"""BabyAI's policy for augmentation: the FiLM policy (policy.py), trained by imitation (imitation.py) on the
grid states of segment clips, evaluated in GoToLocal (evaluation.py). Policy name ``babyai.film``."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import Any

import numpy as np

from playseg_core.augment.policy import PolicyTrainReport
from playseg_core.data.episode import SegmentClip
from playseg_core.data.features import Features
from playseg_core.domains.babyai.imitation import Demonstration, PolicyTrainConfig, train_policy
from playseg_core.domains.babyai.policy import (
    POLICY_NAME,
    PolicyConfig,
    PolicyNet,
    load_policy,
    policy_features,
    save_policy,
)
from playseg_core.errors import PlaysegError


def demonstration(clip: SegmentClip) -> Demonstration:
    """(instruction, grid states o_start..o_end, actions a_start..a_end-1) of a clip."""
    seg = clip.segment
    if clip.state is None:
        raise PlaysegError(
            f"segment {clip.episode_id}[{seg.start}, {seg.end}): the policy needs states, it has none"
        )
    return seg.instruction, np.asarray(clip.state), np.asarray(clip.actions)


@dataclass
class FilmPolicyLearner:
    """`augment.policy.PolicyLearner` for BabyAI: imitation settings plus the evaluation's step limit."""

    train_config: PolicyTrainConfig = field(default_factory=PolicyTrainConfig)
    eval_max_steps: int = 25  # success must come within this many steps
    name: str = POLICY_NAME

    @classmethod
    def from_config(cls, config: dict[str, Any]) -> FilmPolicyLearner:
        """From plain settings: ``steps``, ``batch_size``, ``seed``, ``channels``, ``relevance_maps``,
        ``eval_max_steps``, and any other field of PolicyTrainConfig; ValueError naming an unknown one."""
        config = dict(config)
        network = {key: int(config.pop(key)) for key in ("channels", "relevance_maps") if key in config}
        eval_max_steps = int(config.pop("eval_max_steps", 25))
        known = {f.name for f in fields(PolicyTrainConfig)} - {"policy"}
        unknown = sorted(set(config) - known)
        if unknown:
            raise PlaysegError(f"policy {POLICY_NAME}: unknown settings {unknown} (known: {sorted(known)})")
        train = PolicyTrainConfig(**config)
        if network.get("channels", 1) < 1 or network.get("relevance_maps", 0) < 0:
            raise PlaysegError(
                f"policy {POLICY_NAME}: need channels >= 1 and relevance_maps >= 0, got {network}"
            )
        train = replace(train, policy=replace(train.policy, **network))
        if eval_max_steps <= 0:
            raise PlaysegError(f"policy {POLICY_NAME}: eval_max_steps must be > 0, got {eval_max_steps}")
        return cls(train, eval_max_steps)

    @property
    def features(self) -> Features:
        return policy_features(self.train_config.policy)

    def train(
        self, clips: Sequence[SegmentClip], progress: bool = False
    ) -> tuple[PolicyNet, PolicyTrainReport]:
        model, stats = train_policy([demonstration(clip) for clip in clips], self.train_config, progress)
        report = PolicyTrainReport(
            stats.steps, stats.seconds, stats.num_segments, stats.final_loss, stats.losses
        )
        return model, report

    def evaluate(self, policy: PolicyNet, num_episodes: int, seed: int) -> Any:
        from playseg_core.domains.babyai.evaluation import evaluate_policy  # minigrid: only when evaluating

        return evaluate_policy(policy, num_episodes=num_episodes, max_steps=self.eval_max_steps, seed=seed)

    def save(self, path: Path, policy: PolicyNet, meta: dict[str, Any]) -> None:
        save_policy(path, policy, meta)

    def load(self, path: Path) -> tuple[PolicyNet, dict[str, Any]]:
        return load_policy(path)


__all__ = ["FilmPolicyLearner", "PolicyConfig", "demonstration"]
