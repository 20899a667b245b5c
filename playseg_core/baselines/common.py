"""What every segmentation method shares: the training inputs and options, the `Segmenter` interface,
windows of step features, the training loop of the window models, and per-episode randomness.

A segmenter turns one episode into sorted, disjoint labelled `Segment`s, as PS does, so the same writer,
bags and metrics (ps/metrics.py) serve every method. ``tiles`` says whether its segments cover the whole
trajectory (PS, random windows, changepoints) or are single segments cropped out of windows (UnLoc,
TriDet): for the latter only precision and label accuracy mean anything (the paper reports no recall).
"""

from __future__ import annotations

import math
import sys
import time
import zlib
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from types import MappingProxyType
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from playseg_core.data.episode import Episode, Segment
from playseg_core.data.features import Features
from playseg_core.ps.calibration import LABEL_ACCURACY_TARGET, check_target_accuracy
from playseg_core.ps.encoders import EncoderSpec, StepEncoders, as_tensors
from playseg_core.ps.labelling import KeepRule
from playseg_core.ps.metrics import LabelCounts, label_accuracy


@dataclass
class TrainingData:
    """The annotated episodes a method learns from, and how the data is read.

    features: the features to build step encoders for (the action possibly re-declared, see
        `playseg train --actions`); read_actions False leaves the previous action unread.
    augment: each training segment under a random symmetry of the domain's world (its
        ``CLIP_SYMMETRIES``), else with its camera frames rotated/mirrored (only for models that read no
        actions, and only where labels and ends do not depend on orientation); PS and the labelling model.
    bounds: command-line overrides of min_len / max_len / k_max (None: derived, ps.training.segment_bounds).
    """

    train: list[Episode]
    val: list[Episode]
    instructions: list[str]
    features: Features
    domain: str | None = None
    read_actions: bool = True
    encoder_overrides: dict[str, str] = field(default_factory=dict)
    bounds: dict[str, int | None] = field(default_factory=dict)
    # A trained PS or labelling checkpoint whose step encoders the window methods read, frozen (the
    # paper gives TriDet the labelling model's features and UnLoc frozen CLIP features). None: their own,
    # trained with them.
    encoders_from: str | None = None
    augment: bool = False

    def annotated(self) -> list[Episode]:
        episodes = [episode for episode in self.train if episode.segments]
        if not episodes:
            raise ValueError("no annotated training episodes (episodes with segments)")
        return episodes


@dataclass
class TrainOptions:
    """Budget and optimiser of a training run. ``steps`` optimizer steps (None: the method's default, or
    ``epochs`` passes over the annotated segments when given); ``max_seconds`` stops earlier."""

    seed: int = 0
    steps: int | None = None
    epochs: int | None = None
    batch_size: int | None = None
    lr: float | None = None
    max_seconds: float | None = None
    num_threads: int | None = None  # torch threads while training (None: as set)
    log_every: int = 0  # print a loss line every so many steps (0: never)
    # the held-out label accuracy a calibrated confidence threshold is chosen for (methods that calibrate)
    label_accuracy: float = LABEL_ACCURACY_TARGET

    def __post_init__(self) -> None:
        check_target_accuracy(self.label_accuracy, "label accuracy target")

    def steps_for(self, num_segments: int, batch_size: int, default_steps: int) -> int:
        if self.steps is not None:
            return max(1, self.steps)
        if self.epochs is not None:
            return max(1, self.epochs * math.ceil(num_segments / batch_size))
        return default_steps


@dataclass
class SegmentOptions:
    """Segmentation-time settings: the shortest segment kept (None: the checkpoint's) and the seed of
    the random windows (each episode draws from its own stream, so results do not depend on order)."""

    min_len: int | None = None
    seed: int = 0


class Segmenter:
    """A trained segmentation method. Subclasses set the attributes and implement `segment`."""

    method: str = ""
    tiles: bool = True
    instructions: list[str]
    features: Features  # what the model reads, as its training data declared it
    feature_names: list[str]  # the features it actually reads
    # The checkpoint's meta, whose calibration records (PS: "calibration", "own_cuts_calibration") the
    # keep rules' thresholds come from; none: keep by label at threshold 0 (all).
    checkpoint_meta: Mapping[str, Any] = MappingProxyType({})
    source: str = "the checkpoint"  # its path, for errors

    def keep_rule(self, kind: str) -> KeepRule:
        """Which of its segments to use (ps/labelling.py `KEEP_RULES`), with this checkpoint's threshold;
        ValueError naming the checkpoint when it has no calibration for ``kind``."""
        return KeepRule.of_checkpoint(kind, self.checkpoint_meta, self.source)

    @property
    def label_threshold(self) -> float:
        """The label confidence a segment needs to be used (the paper's filter; 0 when uncalibrated)."""
        return self.keep_rule("label").threshold

    def check_features(self, data: Features, what: str) -> None:
        """FeatureError naming the first feature the method reads that ``data`` lacks or declares otherwise."""
        self.features.check_compatible(data, self.feature_names, what)

    def segment(self, episode: Episode) -> list[Segment]:
        raise NotImplementedError


@dataclass
class TrainedSegmenter:
    """The result of training a method: ``save`` writes its checkpoint, ``report`` is a one-line summary."""

    segmenter: Segmenter
    save: Callable[[Path, dict[str, Any]], Path]
    seconds: float
    report: str


def ps_training_setup(data: TrainingData, options: TrainOptions) -> tuple[list[Episode], Any, Any]:
    """(annotated training episodes, TrainConfig, ModelConfig) for training a PS or labelling model on
    ``data`` as `playseg train` would (ps/training.py defaults), with the options' budget where given."""
    from dataclasses import replace

    from playseg_core.ps.training import TrainConfig, model_config_for, segment_bounds

    train_eps = data.annotated()
    bounds = segment_bounds(train_eps, data.domain, **data.bounds)
    threads = options.num_threads or torch.get_num_threads()
    cfg = TrainConfig(seed=options.seed, k_max=bounds.k_max, num_threads=threads, progress=False)
    cfg = replace(cfg, log_epochs=bool(options.log_every), augment=data.augment, domain=data.domain)
    if options.epochs is not None:
        cfg = replace(cfg, epochs=options.epochs, min_steps=0)
    if options.steps is not None:
        cfg = replace(cfg, epochs=1, min_steps=options.steps)
    if options.batch_size is not None:
        cfg = replace(cfg, segments_per_batch=options.batch_size)
    if options.lr is not None:
        cfg = replace(cfg, lr=options.lr)
    model_cfg = model_config_for(
        data.features,
        data.domain,
        len(data.instructions),
        max_len=bounds.max_len,
        read_actions=data.read_actions,
        episodes=train_eps,
        overrides=data.encoder_overrides,
        min_len=bounds.min_len,
    )
    return train_eps, cfg, model_cfg


def episode_rng(seed: int, episode_id: str) -> np.random.Generator:
    """Randomness of one episode's windows: depends on the seed and the episode, not on the order."""
    return np.random.default_rng([seed, zlib.crc32(episode_id.encode())])


def annotated_lengths(episodes: Iterable[Episode]) -> np.ndarray:
    lengths = np.array([seg.length for episode in episodes for seg in episode.segments], np.int64)
    if lengths.size == 0:
        raise ValueError("the training episodes have no annotated segments")
    return lengths


# ----------------------------------------------------------------------------------------------------
# Step features of windows


@torch.no_grad()
def encode_episode(encoders: StepEncoders, episode: Episode, chunk: int = 512) -> torch.Tensor:
    """(T+1, step_dim) step features of every observation row of ``episode``."""
    inputs = encoders.episode_inputs(episode)
    rows = episode.num_steps + 1
    return torch.cat([encoders(as_tensors(inputs, slice(c, c + chunk))) for c in range(0, rows, chunk)])


def window_rows(
    features: torch.Tensor, windows: Sequence[tuple[int, int]]
) -> tuple[torch.Tensor, torch.Tensor]:
    """Rows o_start..o_end of each step window [start, end) -> (B, P, d) right-padded with zeros, and
    (B, P-1) True at the steps inside the window (P = 1 + the longest window)."""
    width = max(end - start for start, end in windows) + 1
    batch = features.new_zeros(len(windows), width, features.shape[1])
    valid = torch.zeros(len(windows), width - 1, dtype=torch.bool)
    for row, (start, end) in enumerate(windows):
        batch[row, : end - start + 1] = features[start : end + 1]
        valid[row, : end - start] = True
    return batch, valid


def training_window_rows(
    encoders: StepEncoders, items: Sequence[tuple[Episode, int, int]]
) -> tuple[torch.Tensor, torch.Tensor]:
    """As `window_rows` for windows of several episodes, encoded with gradients (training): only the
    rows of the windows themselves are read and encoded."""
    width = max(end - start for _, start, end in items) + 1
    inputs: dict[str, list[np.ndarray]] = {spec.feature: [] for spec in encoders.specs}
    valid = torch.zeros(len(items), width - 1, dtype=torch.bool)
    for row, (episode, start, end) in enumerate(items):
        for name, array in encoders.episode_inputs(episode).items():
            clip = np.array(array[start : end + 1])
            # Pad by repeating the last row (any valid input works: padded steps are masked).
            pad = np.repeat(clip[-1:], width - len(clip), axis=0)
            inputs[name].append(np.concatenate([clip, pad]))
        valid[row, : end - start] = True
    tensors = {name: torch.from_numpy(np.concatenate(parts)) for name, parts in inputs.items()}
    features = encoders(tensors).reshape(len(items), width, -1)
    return features * torch.cat([torch.ones(len(items), 1, dtype=torch.bool), valid], 1)[..., None], valid


def transition_tokens(rows: torch.Tensor) -> torch.Tensor:
    """(B, P, d) observation rows -> (B, P-1, 2d): step t is the transition o_t -> o_{t+1}, which holds
    a_t (read by row t+1's action encoder) and its effect; a segment [s, e) is steps s..e-1."""
    return torch.cat([rows[:, :-1], rows[:, 1:]], dim=-1)


def fixed_windows(num_steps: int, width: int, rng: np.random.Generator) -> list[tuple[int, int]]:
    """Back-to-back windows of ``width`` steps from a random offset in [0, width): disjoint, so the one
    segment cut from each window never overlaps another's. An episode shorter than ``width`` is one
    window."""
    if num_steps <= width:
        return [(0, num_steps)] if num_steps else []
    offset = int(rng.integers(0, min(width, num_steps - width + 1)))
    return [(start, start + width) for start in range(offset, num_steps - width + 1, width)]


# ----------------------------------------------------------------------------------------------------
# Metrics of segmenters whose segments do not cover the trajectory


def covered_label_accuracy(pred: Sequence[Segment], truth: Sequence[Segment], num_steps: int) -> LabelCounts:
    """Label accuracy over the steps the predicted segments cover (ps.metrics.label_accuracy counts the
    steps no prediction covers as wrong, which says more about coverage than labels for a segmenter that
    leaves steps uncovered)."""
    covered = np.zeros(num_steps, bool)
    for seg in pred:
        covered[seg.start : seg.end] = True
    pieces = []
    for seg in truth:
        inside = np.flatnonzero(covered[seg.start : seg.end]) + seg.start
        # Runs of covered steps inside the true segment, each a piece of the truth with its label.
        for run in np.split(inside, np.flatnonzero(np.diff(inside) > 1) + 1):
            if run.size:
                pieces.append(Segment(int(run[0]), int(run[-1]) + 1, seg.instruction))
    return label_accuracy(pred, pieces, num_steps)


# ----------------------------------------------------------------------------------------------------
# The training loop of the window models (UnLoc, TriDet)


@dataclass
class FitReport:
    steps: int
    seconds: float
    train_loss: float  # mean over the last 50 steps
    val_loss: float | None
    history: list[dict[str, float]]


def fit(
    model: nn.Module,
    loss_of_batch: Callable[[np.random.Generator, bool], torch.Tensor],
    options: TrainOptions,
    steps: int,
    lr: float,
    name: str,
    val_batches: int = 0,
) -> FitReport:
    """AdamW with warm-up and cosine decay for ``steps`` steps (or until ``max_seconds``). ``loss_of_batch
    (rng, training)`` draws a batch and returns its loss; with ``training`` False, from the val split.
    The val loss (``val_batches`` fixed batches) is measured at the end."""
    if options.num_threads:
        torch.set_num_threads(options.num_threads)
    rng = np.random.default_rng(options.seed)
    optimizer = torch.optim.AdamW(model.parameters(), lr=lr, weight_decay=1e-4)
    warmup = max(1, steps // 20)

    def factor(step: int) -> float:  # linear warm-up over 5% of the steps, then a cosine to zero
        if step < warmup:
            return (step + 1) / warmup
        return 0.5 * (1 + math.cos(math.pi * (step - warmup) / max(1, steps - warmup)))

    schedule = torch.optim.lr_scheduler.LambdaLR(optimizer, factor)
    began, losses, history = time.perf_counter(), [], []
    model.train()
    done = 0
    for step in range(1, steps + 1):
        loss = loss_of_batch(rng, True)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        nn.utils.clip_grad_norm_(model.parameters(), 5.0)
        optimizer.step()
        schedule.step()
        losses.append(float(loss.detach()))
        done = step
        if options.log_every and step % options.log_every == 0:
            mean = float(np.mean(losses[-options.log_every :]))
            history.append({"step": step, "loss": mean})
            print(f"[{name}] step {step}/{steps}: loss {mean:.4f}", file=sys.stderr, flush=True)
        if options.max_seconds is not None and time.perf_counter() - began > options.max_seconds:
            break
    seconds = time.perf_counter() - began
    model.eval()
    val_loss = None
    if val_batches:
        val_rng = np.random.default_rng(12345)  # the same val batches every run
        with torch.no_grad():
            val_loss = float(np.mean([float(loss_of_batch(val_rng, False)) for _ in range(val_batches)]))
    return FitReport(done, seconds, float(np.mean(losses[-50:])), val_loss, history)


def masked_cross_entropy(logits: torch.Tensor, target: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """Mean CE of (B, P, C) logits against (B, P) targets over the valid positions."""
    return F.cross_entropy(logits[valid], target[valid])


def step_encoders_for(data: TrainingData) -> tuple[list[EncoderSpec], Features]:
    """The step encoders PS would read ``data`` with (ps.encoders.choose_encoders via model_config_for),
    and the features they read (the action always recorded), as a checkpoint stores them; with
    ``data.encoders_from``, that checkpoint's (`freeze_pretrained_encoders` then loads their weights)."""
    from playseg_core.ps.model import load_model
    from playseg_core.ps.training import model_config_for

    if data.encoders_from:
        model, _ = load_model(data.encoders_from, kinds=("ps", "labeller"))
        model.cfg.check_features(data.features, f"--encoders-from {data.encoders_from}")
        return model.cfg.encoders, model.cfg.features

    config = model_config_for(
        data.features,
        data.domain,
        len(data.instructions),
        read_actions=data.read_actions,
        episodes=data.train,
        overrides=data.encoder_overrides,
    )
    return config.encoders, config.features


def covered_metrics(
    pred_by_episode: Mapping[str, Sequence[Segment]],
    truth_by_episode: Mapping[str, Sequence[Segment]],
    num_steps_by_episode: Mapping[str, int],
) -> dict[str, float | int]:
    """``covered_label_accuracy`` and ``covered_steps`` over episodes (micro-averaged), as
    ps.metrics.evaluate reports the rest."""
    total = LabelCounts(0, 0)
    for episode_id, truth in truth_by_episode.items():
        pred = pred_by_episode.get(episode_id, [])
        total += covered_label_accuracy(pred, truth, num_steps_by_episode[episode_id])
    return {"covered_label_accuracy": total.accuracy, "covered_steps": total.total}


def freeze_pretrained_encoders(encoders: StepEncoders, data: TrainingData) -> None:
    """With ``data.encoders_from``: load that checkpoint's step-encoder weights into ``encoders`` and
    freeze them (built from the same specs by `step_encoders_for`)."""
    if not data.encoders_from:
        return
    from playseg_core.ps.model import load_model

    model, _ = load_model(data.encoders_from, kinds=("ps", "labeller"))
    encoders.load_state_dict(model.encoders.state_dict())
    encoders.requires_grad_(False)
