"""Policy augmentation: train the instruction-conditioned policy on the annotated segments plus the
extracted (segmented and labelled) ones, keep versioned checkpoints, evaluate reproducibly.

The trainer node is a thin ROS adapter over `AugmentationTrainer`.
"""

from __future__ import annotations

import json
import os
import threading
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from playseg_core.augment.buffer import AugmentationBuffer
from playseg_core.data.episode import Episode, Segment, SegmentClip
from playseg_core.domains.babyai.imitation import (
    Demonstration,
    EvalResult,
    PolicyTrainConfig,
    evaluate_policy,
    train_policy,
)
from playseg_core.domains.babyai.policy import PolicyNet, load_policy, save_policy


def demonstrations_from_episodes(episodes: Iterable[Episode]) -> list[Demonstration]:
    """(instruction, states o_start..o_end, actions a_start..a_end-1) for every labelled segment."""
    demos = []
    for episode in episodes:
        if episode.states is None:
            raise ValueError(f"episode {episode.episode_id!r}: the policy needs states, the episode has none")
        for seg in episode.segments:
            demos.append(
                (
                    seg.instruction,
                    np.asarray(episode.states[seg.start : seg.end + 1]),
                    np.asarray(episode.actions[seg.start : seg.end]),
                )
            )
    return demos


def demonstration_from_clip(clip: SegmentClip) -> Demonstration:
    seg = clip.segment
    if clip.states is None:
        raise ValueError(f"segment {clip.episode_id}[{seg.start}, {seg.end}) has no states")
    return seg.instruction, clip.states, clip.actions


@dataclass
class TrainerConfig:
    buffer_dir: str
    checkpoint_dir: str
    retrain_every: int = 0  # retrain after this many new segments (0: only on request)
    min_confidence: float = 0.0  # segments below this label confidence are stored but not trained on
    eval_episodes: int = 512
    eval_max_steps: int = 25
    eval_seed: int = 1_000_000  # evaluation seeds are disjoint from the play-generation seeds
    train: PolicyTrainConfig = field(default_factory=PolicyTrainConfig)


@dataclass
class PolicyVersion:
    version: int
    checkpoint: str
    success_rate: float
    eval_episodes: int
    train_loss: float
    num_base_segments: int
    num_buffer_segments: int


class AugmentationTrainer:
    """Buffer + base data -> versioned policies. Thread-safe: `add` may run while `retrain` runs."""

    def __init__(self, config: TrainerConfig, base_demos: list[Demonstration] | None = None) -> None:
        self.config = config
        self.base_demos = list(base_demos or [])
        self.buffer = AugmentationBuffer(config.buffer_dir)
        self.checkpoint_dir = Path(config.checkpoint_dir)
        self.checkpoint_dir.mkdir(parents=True, exist_ok=True)
        self._lock = threading.Lock()
        self._since_retrain = 0
        self.latest: PolicyVersion | None = self._read_latest()

    @property
    def policy_version(self) -> int:
        return self.latest.version if self.latest else 0

    def add(self, clip: SegmentClip) -> bool:
        """Store a segment durably. Returns True when a periodic retraining is due."""
        with self._lock:
            self.buffer.append(clip)
            self._since_retrain += 1
            return self.config.retrain_every > 0 and self._since_retrain >= self.config.retrain_every

    def training_demos(self) -> list[Demonstration]:
        with self._lock:
            extracted = [
                demonstration_from_clip(clip)
                for clip in self.buffer
                if clip.segment.confidence >= self.config.min_confidence
            ]
            self._since_retrain = 0
        return self.base_demos + extracted

    def retrain(self, progress: bool = False) -> PolicyVersion:
        """Train a new policy version on base + buffer, evaluate it, write its checkpoint."""
        demos = self.training_demos()
        if not demos:
            raise ValueError("no segments to train on: the buffer and the annotated data are empty")
        model, stats = train_policy(demos, self.config.train, progress=progress)
        result = self.evaluate(model)
        version = self.policy_version + 1
        path = self.checkpoint_dir / f"policy-v{version:04d}.pt"
        meta = {"version": version, "success_rate": result.success_rate, "segments": len(demos)}
        save_policy(path, model, model.config, meta)
        latest = PolicyVersion(
            version=version,
            checkpoint=str(path),
            success_rate=result.success_rate,
            eval_episodes=result.num_episodes,
            train_loss=stats.final_loss,
            num_base_segments=len(self.base_demos),
            num_buffer_segments=len(demos) - len(self.base_demos),
        )
        _write_json_atomically(self.checkpoint_dir / "latest.json", latest.__dict__)
        self.latest = latest
        return latest

    def evaluate(self, model: PolicyNet | None = None, episodes: int | None = None) -> EvalResult:
        if model is None:
            if self.latest is None:
                raise ValueError("no policy trained yet")
            model = load_policy(self.latest.checkpoint)[0]
        return evaluate_policy(
            model,
            num_episodes=episodes or self.config.eval_episodes,
            max_steps=self.config.eval_max_steps,
            seed=self.config.eval_seed,
        )

    def close(self) -> None:
        self.buffer.close()

    def _read_latest(self) -> PolicyVersion | None:
        path = self.checkpoint_dir / "latest.json"
        if not path.exists():
            return None
        try:
            return PolicyVersion(**json.loads(path.read_text()))
        except (ValueError, TypeError) as exc:
            raise ValueError(f"{path}: not a policy version record: {exc}") from exc


def _write_json_atomically(path: Path, data: dict) -> None:
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(data, indent=2))
    os.replace(tmp, path)


def export_buffer_dataset(buffer: AugmentationBuffer, path: str | Path) -> int:
    """Write every buffered segment as a one-segment episode of a playseg dataset (split 'train').

    Episode ids are ``<source episode>:<start>-<end>``; segment confidence and log-score are kept.
    Returns the number of segments written. The dataset appears at ``path`` only when complete.
    """
    from playseg_core.data.dataset import DatasetWriter
    from playseg_core.domains.babyai.play import INSTRUCTIONS

    clips = list(buffer)
    used = {clip.segment.instruction for clip in clips}
    instructions = INSTRUCTIONS if used <= set(INSTRUCTIONS) else sorted(used)
    with DatasetWriter(path, instructions, meta={"source": f"augmentation buffer {buffer.path}"}) as writer:
        for clip in clips:
            seg = clip.segment
            if clip.frames is None:
                raise ValueError(
                    f"{buffer.path}: segment {clip.episode_id}[{seg.start}, {seg.end}) has no frames"
                )
            episode = Episode(
                episode_id=f"{clip.episode_id}:{seg.start}-{seg.end}",
                frames=np.asarray(clip.frames),
                actions=np.asarray(clip.actions, np.float32),
                states=None if clip.states is None else np.asarray(clip.states),
                segments=[Segment(0, seg.length, seg.instruction, seg.confidence, seg.log_prob)],
            )
            writer.add(episode, "train", extra={"source": clip.source})
    return len(clips)
