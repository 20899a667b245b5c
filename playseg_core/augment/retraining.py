"""Policy augmentation: train an instruction-following policy on the annotated segments plus the extracted
(segmented and labelled) ones, keep versioned checkpoints, evaluate reproducibly.

The policy is any `augment.policy.PolicyLearner`; the trainer node is a thin ROS adapter over
`AugmentationTrainer`.
"""

from __future__ import annotations

import json
import math
import os
import threading
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

from playseg_core.augment.buffer import AugmentationBuffer
from playseg_core.augment.policy import PolicyEvaluation, PolicyLearner, PolicyTrainReport
from playseg_core.data.episode import Episode, SegmentClip
from playseg_core.data.features import ACTION, STATE, Features
from playseg_core.errors import PlaysegError


def _check_clip(clip: SegmentClip, features: Features, what: str) -> None:
    seg = clip.segment
    where = f"segment {clip.episode_id}[{seg.start}, {seg.end})"
    rows = {**clip.images, ACTION: clip.actions, **({} if clip.state is None else {STATE: clip.state})}
    for name, feature in features.by_name.items():
        if name not in rows:
            raise PlaysegError(f"{where}: {what} reads {feature.describe()}, the segment has no {name!r}")
        if rows[name].shape[1:] != feature.shape:
            raise PlaysegError(
                f"{where}: {what} reads {feature.describe()}, the segment's is {list(rows[name].shape[1:])}"
            )


def annotated_clips(episodes: Iterable[Episode]) -> list[SegmentClip]:
    """A clip of every labelled segment of ``episodes`` (source "annotation")."""
    return [SegmentClip.from_episode(ep, seg, "annotation") for ep in episodes for seg in ep.segments]


@dataclass
class TrainerConfig:
    buffer_dir: str
    checkpoint_dir: str
    retrain_every: int = 0  # retrain after this many new segments (0: only on request)
    min_confidence: float = 0.0  # segments below this label confidence are stored but not trained on
    eval_episodes: int = 512
    eval_seed: int = 1_000_000  # evaluation seeds are disjoint from the play-generation seeds


@dataclass
class PolicyVersion:
    version: int
    checkpoint: str
    success_rate: float  # NaN when the policy's domain has no simulator to evaluate in
    eval_episodes: int
    train_loss: float
    num_base_segments: int
    num_buffer_segments: int
    # What this version's evaluation reports (`evaluation_figure`): "success_rate" in the simulator, else
    # "val_accuracy" / "val_loss" on the learner's held-out clips, "" when there is neither.
    eval_metric: str = "success_rate"
    eval_value: float = float("nan")

    def __post_init__(self) -> None:
        if self.eval_metric == "success_rate" and math.isnan(self.eval_value):  # a record from before
            self.eval_value = self.success_rate


class AugmentationTrainer:
    """Buffer + base data -> versioned policies. Thread-safe: `add` may run while `retrain` runs."""

    def __init__(
        self, config: TrainerConfig, learner: PolicyLearner, base_clips: list[SegmentClip] | None = None
    ) -> None:
        self.config = config
        self.learner = learner
        self.base_clips = list(base_clips or [])
        self.buffer = AugmentationBuffer(config.buffer_dir)
        self.checkpoint_dir = Path(config.checkpoint_dir)
        self.checkpoint_dir.mkdir(parents=True, exist_ok=True)
        self._lock = threading.Lock()
        self._since_retrain = 0
        self.duplicates = 0  # segments received again and not stored
        self.latest: PolicyVersion | None = self._read_latest()

    @property
    def policy_version(self) -> int:
        return self.latest.version if self.latest else 0

    def add(self, clip: SegmentClip) -> bool:
        """Store a segment durably. Returns True when a periodic retraining is due.

        A segment stored already (same episode, start, end and labelling model: a replayed episode, a
        second segmenter) is not stored again. ValueError naming the segment and feature, and nothing
        stored, when the clip lacks what the policy reads (one such clip in the buffer would fail every
        later retraining).
        """
        _check_clip(clip, self.learner.features, f"policy {self.learner.name}")
        with self._lock:
            if clip in self.buffer:
                self.duplicates += 1
                return False
            self.buffer.append(clip)
            self._since_retrain += 1
            return self.config.retrain_every > 0 and self._since_retrain >= self.config.retrain_every

    def training_clips(self) -> list[SegmentClip]:
        """The base clips and every buffered clip at or above the confidence threshold."""
        with self._lock:
            extracted = [
                clip for clip in self.buffer if clip.segment.confidence >= self.config.min_confidence
            ]
            self._since_retrain = 0
        return self.base_clips + extracted

    def retrain(self, progress: bool = False) -> PolicyVersion:
        """Train a new policy version on base + buffer, evaluate it, write its checkpoint."""
        clips = self.training_clips()
        if not clips:
            raise PlaysegError("no segments to train on: the buffer and the annotated data are empty")
        model, report = self.learner.train(clips, progress=progress)
        result = self.evaluate(model)
        success = result.success_rate if result else float("nan")
        metric, value = evaluation_figure(result, report)
        version = self.policy_version + 1
        path = self.checkpoint_dir / f"policy-v{version:04d}.pt"
        meta = {"version": version, "success_rate": success, metric or "eval": value, "segments": len(clips)}
        if result is not None:  # episode by episode, so that two versions compare on the same episodes
            meta["episode_success"] = "".join("01"[bool(ok)] for ok in result.episode_success)
        self.learner.save(path, model, meta)
        latest = PolicyVersion(
            version=version,
            checkpoint=str(path),
            success_rate=success,
            eval_episodes=result.num_episodes if result else 0,
            train_loss=report.final_loss,
            num_base_segments=len(self.base_clips),
            num_buffer_segments=len(clips) - len(self.base_clips),
            eval_metric=metric,
            eval_value=value,
        )
        _write_json_atomically(self.checkpoint_dir / "latest.json", latest.__dict__)
        self.latest = latest
        return latest

    def evaluate(self, model: object | None = None, episodes: int | None = None) -> PolicyEvaluation | None:
        """Evaluate ``model`` (default: the latest version) in the domain's simulator; None without one."""
        if model is None:
            if self.latest is None:
                raise PlaysegError("no policy trained yet")
            model = self.learner.load(Path(self.latest.checkpoint))[0]
        return self.learner.evaluate(model, episodes or self.config.eval_episodes, self.config.eval_seed)

    def close(self) -> None:
        self.buffer.close()

    def _read_latest(self) -> PolicyVersion | None:
        path = self.checkpoint_dir / "latest.json"
        if not path.exists():
            return None
        try:
            return PolicyVersion(**json.loads(path.read_text()))
        except (ValueError, TypeError) as exc:
            raise PlaysegError(f"{path}: not a policy version record: {exc}") from exc


def evaluation_figure(result: PolicyEvaluation | None, report: PolicyTrainReport) -> tuple[str, float]:
    """(metric, value) a policy version reports: its simulator success rate when its domain has a
    simulator, else its accuracy (discrete actions) or loss on the learner's held-out clips; ("", NaN)
    when there is neither."""
    if result is not None:
        return "success_rate", result.success_rate
    if report.val_accuracy is not None:
        return "val_accuracy", report.val_accuracy
    if report.val_loss is not None:
        return "val_loss", report.val_loss
    return "", float("nan")


def _write_json_atomically(path: Path, data: dict) -> None:
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(data, indent=2))
    os.replace(tmp, path)


def export_buffer_dataset(
    buffer: AugmentationBuffer,
    path: str | Path,
    instructions: Iterable[str] = (),
    features: Features | None = None,
    domain: str | None = None,
) -> int:
    """Write every buffered segment as a one-segment episode of a playseg dataset (split 'train').

    Episode ids are ``<source episode>:<start>-<end>``; segment confidence and log-score are kept. The
    dataset's instruction list is ``instructions`` followed by any other instruction the buffer holds;
    ``features`` is its schema (default: taken from the first clip), ``domain`` the domain it comes
    from (so its step encoders apply when training on it). Returns the number of segments
    written. The dataset appears at ``path`` only when complete.
    """
    from playseg_core.data.dataset import DatasetWriter

    clips = list(buffer)
    known = list(dict.fromkeys(instructions))
    known += sorted({clip.segment.instruction for clip in clips} - set(known))
    meta = {"source": f"augmentation buffer {buffer.path}"}
    with DatasetWriter(path, known, meta, features=features, domain=domain) as writer:
        for clip in clips:
            seg = clip.segment
            writer.add(
                clip.as_episode(f"{clip.episode_id}:{seg.start}-{seg.end}"), "train", {"source": clip.source}
            )
    return len(clips)
