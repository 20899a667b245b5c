"""Training of the PS model and the labelling model on annotated segments (samples: samples.py).

nanoGPT-style: the configuration, the losses and one explicit loop (`_fit`); the learning rate follows a
one-cycle schedule; the best epoch on the annotated val split is kept.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from playseg_core.data.episode import Episode
from playseg_core.data.features import Features
from playseg_core.data.splits import DEFAULT_VAL_SHARE, held_out_ids
from playseg_core.domains import Domain, load_domain
from playseg_core.errors import PlaysegError
from playseg_core.ps.encoders import StepEncoders, choose_encoders, feature_statistics
from playseg_core.ps.fixed_features import FixedFeatureCache
from playseg_core.ps.model import (
    PERIODIC_FREQUENCIES,
    TRUNK_DROPOUT,
    LabelModel,
    ModelConfig,
    PSModel,
    TrunkConfig,
)
from playseg_core.ps.samples import Batch, label_index, make_batch
from playseg_core.ps.symmetries import ClipSymmetries, camera_symmetries
from playseg_core.training.device import resolve_device, to_device
from playseg_core.training.loop import (
    LoopConfig,
    LoopResult,
    TrainingTask,
    cosine_learning_rate,
    log_to_stderr,
    train_loop,
)


@dataclass
class TrainConfig:
    seed: int = 0
    # The budget (training/loop.py): at most `step_cap` optimizer steps, stopped earlier when the val
    # loss has not improved for `patience` evaluations (one every `evaluation_interval` steps).
    epochs: int | None = None  # exactly this many epochs, no early stopping
    max_steps: int | None = None  # the step cap instead of the data-scaled one
    max_minutes: float | None = None
    cap_epochs: int = 16  # the data-scaled cap: this many epochs ...
    # ... but at least this many steps: small data learns the labels late (docs/segmentation.md "Training")
    min_steps: int = 3200
    cap_steps: int = 50_000
    patience: int = 8  # evaluations without a better val measure ...
    # ... spanning at least this share of the step cap: a small val split's measure dips for a few
    # evaluations while it still improves (docs/segmentation.md "Training")
    patience_share: float = 0.15
    eval_every: int | None = None
    segments_per_batch: int = 16  # drawn from all annotated episodes; small batches = more steps
    lr: float = 3e-3
    weight_decay: float = 1e-4
    k_max: int = 5  # negatives shift by 1..k_max steps
    dense_prefix_negatives: bool = True
    augment: bool = False  # each training clip under a random symmetry (`training_symmetries`; see docs)
    domain: str | None = None  # the data's domain, whose `clip_symmetries` augment applies if it has any
    label_weight: float = 1.0
    frame_label_weight: float = 1.0  # auxiliary label loss on the end observation's encoding
    end_pos_weight: float = 4.0  # weight of the end head's positives in the BCE (ends are rare)
    num_threads: int = 2
    device: str = "auto"  # training/device.py
    progress: bool = True  # a progress bar: step / cap, loss, val loss, ETA
    log_epochs: bool = True  # one line per evaluation
    state_path: str | None = None  # the resume file (written every evaluation; removed when done)
    resume: bool = False  # continue from state_path
    fingerprint: str = ""  # identifies the run for resuming (data and settings)


@dataclass(frozen=True)
class SegmentBounds:
    """L_min and L_max (segment lengths in actions) and k_max (the negatives' shift range), and where
    they come from: the domain's measured setting, the annotated segments, or the command line."""

    min_len: int
    max_len: int
    k_max: int
    source: str

    def describe(self) -> str:
        return f"L_min {self.min_len}, L_max {self.max_len}, k_max {self.k_max} ({self.source})"


def segment_bounds(
    episodes: Iterable[Episode],
    domain: str | None = None,
    min_len: int | None = None,
    max_len: int | None = None,
    k_max: int | None = None,
) -> SegmentBounds:
    """The segment-length bounds for training on ``episodes``' annotated segments.

    A domain's ``segment_bounds`` if it has them; else derived from the annotated lengths: L_max = the
    longest x 1.25 (segments a bit longer than any annotated one can still be cut), L_min = half the
    shortest, k_max = a quarter of the median length (negatives move a boundary by up to a quarter
    segment: by a few steps for short tasks, by more for long ones). Each given value wins.
    """
    measured = dict((load_domain(domain).segment_bounds if domain else None) or {})
    source = f"domain {domain}" if measured else "annotated segments"
    if not measured:
        lengths = np.array([seg.length for ep in episodes for seg in ep.segments])
        if lengths.size == 0:
            raise PlaysegError("segment bounds: the training episodes have no annotated segments")
        measured = {
            "min_len": max(1, int(lengths.min()) // 2),
            "max_len": max(2, int(np.ceil(1.25 * lengths.max()))),
            "k_max": max(1, int(round(0.25 * float(np.median(lengths))))),
        }
    given = {"min_len": min_len, "max_len": max_len, "k_max": k_max}
    bounds = {key: int(given[key] if given[key] is not None else measured[key]) for key in given}
    if any(given[key] is not None for key in given):
        source += ", command line"
    if not 1 <= bounds["min_len"] <= bounds["max_len"] or bounds["k_max"] < 1:
        raise PlaysegError(f"segment bounds need 1 <= min_len <= max_len and k_max >= 1, got {bounds}")
    return SegmentBounds(**bounds, source=source)


def model_config_for(
    features: Features,
    domain: str | None,
    num_classes: int,
    max_len: int = 25,
    read_actions: bool = True,
    episodes: Iterable[Episode] = (),
    overrides: dict[str, str] | None = None,
    min_len: int = 1,
    label_head: str | None = None,
    end_lookahead: int | None = None,
    measured_state: bool = True,
) -> ModelConfig:
    """The default model for data with ``features`` (step encoders by `choose_encoders`; the state and a
    continuous action standardised with ``episodes``' statistics, computed only when read; the label
    head ``label_head``, else the domain's, else "linear"; the end head's lookahead ``end_lookahead``,
    else the domain's, else 0, the paper's; the trunk's periodic embeddings the domain's frequencies, else
    `PERIODIC_FREQUENCIES` (as many for the distances between measured positions), and with them, unless
    ``measured_state`` is False, the state among the measured values they read; the trunk's dropout the
    domain's, else `TRUNK_DROPOUT`; playseg_core/domains `Domain`)."""
    known = load_domain(domain) if domain else Domain("")
    frequencies = PERIODIC_FREQUENCIES if known.periodic_frequencies is None else known.periodic_frequencies
    needs = [f.name for f in (features.state, features.action) if f is not None and not f.is_discrete]
    episodes = list(episodes)
    statistics = feature_statistics(episodes, needs) if episodes and needs else {}
    encoders = choose_encoders(
        features, known.step_encoders, statistics, read_actions, overrides, measured_state and frequencies > 0
    )
    observed = [features[spec.feature] for spec in encoders if spec.feature != features.action.name]
    # The action is always recorded (what the model was trained on), read or not.
    read = Features.of([*observed, features.action], features.fps)
    return ModelConfig(
        encoders,
        read,
        num_classes,
        TrunkConfig(
            max_len=max_len,
            periodic_frequencies=frequencies,
            dropout=TRUNK_DROPOUT if known.trunk_dropout is None else known.trunk_dropout,
            pair_frequencies=frequencies,
        ),
        min_len=min_len,
        label_head=known.label_head if label_head is None else label_head,
        end_lookahead=known.end_lookahead if end_lookahead is None else end_lookahead,
    )


def _gather_windows(features: torch.Tensor, window_index: torch.Tensor) -> torch.Tensor:
    padded = torch.cat([features, features.new_zeros(1, features.shape[1])])
    return padded[window_index]


def _length_groups(needed: torch.Tensor, step: int = 6) -> list[tuple[torch.Tensor, int]]:
    """Windows grouped by needed length rounded up to `step`: short windows skip padded positions."""
    rounded = (needed + step - 1) // step * step
    return [(torch.nonzero(rounded == n).squeeze(1), int(n)) for n in torch.unique(rounded)]


@dataclass
class BatchStats:
    loss: float
    end_loss: float
    label_loss: float
    end_correct: int
    end_count: int
    label_correct: int
    label_count: int


def ps_loss(model: PSModel, batch: Batch, cfg: TrainConfig) -> tuple[torch.Tensor, BatchStats]:
    """BCE on the end head at the supervised positions + CE on the label head at positive ends."""
    features = model.encode_steps(batch.inputs, batch.encoded)
    num_windows, num_pos = batch.end_target.shape
    end_sum = features.new_zeros(())
    label_hidden = features.new_zeros(len(batch.labels), model.cfg.trunk.hidden_dim)
    end_correct = 0
    needed = batch.needed_len.clamp(max=num_pos)
    for members, length in _length_groups(needed):
        length = min(length, num_pos)
        # The end head also reads `lookahead` positions past each supervised one.
        windows = _gather_windows(features, batch.window_index[members, : length + model.lookahead])
        hidden = model.trunk(windows, batch.starts_episode[members])
        logits = model.raw_end_logits(hidden)  # without end_bias: that is for segmenting only
        target, weight = batch.end_target[members, :length], batch.end_weight[members, :length]
        bce = F.binary_cross_entropy_with_logits(
            logits, target, reduction="none", pos_weight=logits.new_tensor(cfg.end_pos_weight)
        )
        end_sum = end_sum + (bce * weight).sum()
        end_correct += int((((logits > 0).float() == target) & (weight > 0)).sum())
        # Label head: hidden state at the end of each positive whose window is in this group.
        slot = torch.full((num_windows,), -1, dtype=torch.long, device=features.device)
        slot[members] = torch.arange(len(members), device=features.device)
        here = slot[batch.label_window] >= 0
        if here.any():
            chosen = hidden[slot[batch.label_window[here]], batch.label_position[here]]
            label_hidden = label_hidden.index_put(
                (torch.nonzero(here).squeeze(1),), chosen.to(label_hidden.dtype)
            )
    end_count = int((batch.end_weight > 0).sum())
    end_loss = end_sum / max(1, end_count)
    label_logits = model.label_head(label_hidden)
    label_loss = F.cross_entropy(label_logits, batch.labels)
    loss = end_loss + cfg.label_weight * label_loss
    loss = loss + _frame_label_loss(model, batch, features, cfg)
    stats = BatchStats(
        loss=float(loss.detach()),
        end_loss=float(end_loss.detach()),
        label_loss=float(label_loss.detach()),
        end_correct=end_correct,
        end_count=end_count,
        label_correct=int((label_logits.argmax(-1) == batch.labels).sum()),
        label_count=int(batch.labels.numel()),
    )
    return loss, stats


def _frame_label_loss(
    model: PSModel | LabelModel, batch: Batch, features: torch.Tensor, cfg: TrainConfig
) -> torch.Tensor:
    """Auxiliary CE of `frame_label_head` on each positive's end-observation encoding (weighted)."""
    if cfg.frame_label_weight <= 0:
        return features.new_zeros(())
    end_rows = batch.window_index[batch.label_window, batch.label_position]
    frame_logits = model.frame_label_head(model.observation_part(features[end_rows]))
    return cfg.frame_label_weight * F.cross_entropy(frame_logits, batch.labels)


def labeller_loss(model: LabelModel, batch: Batch, cfg: TrainConfig) -> tuple[torch.Tensor, BatchStats]:
    """CE of the labelling model on the positives of the batch (one window per positive), plus the
    auxiliary CE of `frame_label_head` on each end frame's encoder features (as in `ps_loss`)."""
    features = model.encode_steps(batch.inputs, batch.encoded)
    windows = _gather_windows(features, batch.window_index[batch.label_window])
    starts_episode = batch.starts_episode[batch.label_window]
    logits = model.logits_from_windows(windows, batch.label_position, starts_episode)
    loss = F.cross_entropy(logits, batch.labels)
    loss = loss + _frame_label_loss(model, batch, features, cfg)
    correct = int((logits.argmax(-1) == batch.labels).sum())
    n = int(batch.labels.numel())
    return loss, BatchStats(float(loss.detach()), 0.0, float(loss.detach()), 0, 0, correct, n)


def clip_symmetries_of(domain: str | None) -> ClipSymmetries | None:
    """The symmetries of ``domain`` (playseg_core/domains `Domain.clip_symmetries`), or None: `augment`
    then turns camera frames only."""
    return load_domain(domain).clip_symmetries if domain else None


def training_symmetries(cfg: TrainConfig, encoders: StepEncoders) -> ClipSymmetries | None:
    """What `augment` trains on: the domain's symmetries, else the camera frames' rotations and mirrors
    (for models that read no actions: a mirror would swap left and right turns); None without augment."""
    if not cfg.augment:
        return None
    symmetries = clip_symmetries_of(cfg.domain)
    if symmetries is not None:
        return symmetries
    if encoders.reads_actions:
        raise PlaysegError(
            "augment: the camera frames' rotations leave the actions as they are; only for models that "
            "read no actions, or for a domain whose symmetries turn them too (its clip_symmetries)"
        )
    return camera_symmetries(encoders.cameras)


def _annotated(episodes: Sequence[Episode]) -> list[Episode]:
    return [ep for ep in episodes if ep.segments]


def hold_out_for_validation(
    train: Sequence[Episode], val: Sequence[Episode], share: float = DEFAULT_VAL_SHARE
) -> tuple[list[Episode], list[Episode], list[str]]:
    """(train, val, held out): ``val``'s annotated episodes when it has any; else ``share`` of the
    annotated training episodes (data/splits.py `held_out_ids`: deterministic, at least one) moved to
    val, their ids third. Nothing is held out of fewer than two annotated episodes: val is then empty,
    and the model can be neither early-stopped nor calibrated."""
    if _annotated(val):
        return list(train), list(val), []
    held = held_out_ids([ep.episode_id for ep in _annotated(train)], share)
    kept = [ep for ep in train if ep.episode_id not in held]
    moved = [ep for ep in train if ep.episode_id in held]
    return kept, moved, sorted(held)


# ----------------------------------------------------------------------------------------------------
# Training: PS and the labelling model through the one loop (playseg_core/training/loop.py)


@dataclass
class TrainResult:
    model: torch.nn.Module
    history: list[dict]  # per evaluation: step, lr, train and val figures
    seconds: float
    loop: LoopResult | None = None

    @property
    def figures(self) -> dict[str, float]:
        """The kept weights' evaluation (val figures when there was a val split), else the last one."""
        if self.loop is not None and self.loop.best:
            return self.loop.best
        return self.history[-1] if self.history else {}

    @property
    def label_accuracy(self) -> float:
        """Val label accuracy of the kept weights, or the training one without a val split."""
        figures = self.figures
        return float(figures.get("val_label_accuracy", figures.get("train_label_accuracy", float("nan"))))

    def summary(self) -> str:
        return self.loop.summary() if self.loop is not None else f"{self.seconds:.0f} s"


VAL_MEASURE = "val_error"
"""What early stopping and the best weights go by: the end head's held-out BCE plus the held-out label
error rate. Not the val loss: its label cross-entropy grows with the model's confidence on the labels
it gets wrong, long after the boundaries and the label accuracy stopped improving or while they still
improve, so on small data it kept the weights of the first evaluation."""


def steps_per_epoch(episodes: Sequence[Episode], cfg: TrainConfig) -> int:
    return max(1, -(-sum(len(ep.segments) for ep in _annotated(episodes)) // cfg.segments_per_batch))


def step_cap(cfg: TrainConfig, epoch_steps: int) -> int:
    """The most optimizer steps a run takes: ``max_steps`` when given, exactly ``epochs`` epochs when
    given, else the data-scaled budget (`cap_epochs` epochs, at least `min_steps`, at most
    `cap_steps`)."""
    if cfg.max_steps is not None:
        return cfg.max_steps
    if cfg.epochs is not None:
        return cfg.epochs * epoch_steps
    return min(cfg.cap_steps, max(cfg.min_steps, cfg.cap_epochs * epoch_steps))


def evaluation_interval(cfg: TrainConfig, epoch_steps: int) -> int:
    """Steps between evaluations: ``eval_every``, else an epoch, kept within 25..500 steps (a tiny epoch
    would spend the run evaluating, a huge one would stop late)."""
    if cfg.eval_every is not None:
        return cfg.eval_every
    return min(500, max(25, epoch_steps))


def _batch_for(model, items, chosen, classes, cfg: TrainConfig, rng, fixed, training: bool) -> Batch:
    return make_batch(
        [items[i] for i in chosen],
        classes,
        model.encoders,
        model.max_len,
        cfg.k_max,
        rng,
        negatives=isinstance(model, PSModel),
        dense_prefix_negatives=cfg.dense_prefix_negatives,
        symmetries=training_symmetries(cfg, model.encoders) if training else None,
        fixed=fixed,
        lookahead=model.lookahead,
    )


def _figures(stats: BatchStats) -> dict[str, float]:
    figures = {"loss": stats.loss, "label_accuracy": stats.label_correct / max(1, stats.label_count)}
    if stats.end_count:
        figures["end_accuracy"] = stats.end_correct / stats.end_count
    return figures


def _fit(model, loss_fn, train_eps, val_eps, instructions, cfg: TrainConfig, name: str) -> TrainResult:
    """Train ``model`` on the annotated segments of ``train_eps``: each epoch a fresh order of them in
    batches of ``segments_per_batch`` (step s's batch, negatives and symmetries drawn from the seed and s
    alone); every `evaluation_interval` steps the loss on ``val_eps`` (fixed negatives) decides the best
    weights and early stopping."""
    torch.set_num_threads(cfg.num_threads)
    torch.manual_seed(cfg.seed)
    classes = label_index(instructions)
    train_eps, val_eps = _annotated(train_eps), _annotated(val_eps)
    if not train_eps:
        raise PlaysegError("no annotated training episodes (episodes with segments)")
    device = resolve_device(cfg.device)
    items = [(ep, seg) for ep in train_eps for seg in ep.segments]
    val_items = [(ep, seg) for ep in val_eps for seg in ep.segments]
    epoch_steps = steps_per_epoch(train_eps, cfg)
    cap = step_cap(cfg, epoch_steps)
    size = cfg.segments_per_batch
    fixed = FixedFeatureCache(model.encoders)
    fixed = fixed if fixed.features else None

    def batch_at(step: int) -> Batch:
        epoch, index = divmod(step, epoch_steps)
        order = np.random.default_rng([cfg.seed, epoch]).permutation(len(items))
        chosen = order[index * size : (index + 1) * size]
        return _batch_for(
            model, items, chosen, classes, cfg, np.random.default_rng([cfg.seed, epoch, index]), fixed, True
        )

    def evaluate(trained: torch.nn.Module) -> dict[str, float]:
        rng = np.random.default_rng(12345)  # the same negatives at every evaluation
        totals: dict[str, float] = {}
        weights = 0
        for start in range(0, len(val_items), size):
            batch = _batch_for(
                trained,
                val_items,
                range(start, min(start + size, len(val_items))),
                classes,
                cfg,
                rng,
                fixed,
                False,
            )
            _, stats = loss_fn(trained, to_device(batch, device))
            weight = max(stats.end_count, stats.label_count)
            totals["loss"] = totals.get("loss", 0.0) + stats.loss * weight
            totals["end_loss"] = totals.get("end_loss", 0.0) + stats.end_loss * stats.end_count
            for key in ("end_correct", "end_count", "label_correct", "label_count"):
                totals[key] = totals.get(key, 0.0) + getattr(stats, key)
            weights += weight
        figures = {"val_loss": totals["loss"] / max(1, weights)}
        figures["val_label_accuracy"] = totals["label_correct"] / max(1.0, totals["label_count"])
        if totals["end_count"]:
            figures["val_end_accuracy"] = totals["end_correct"] / totals["end_count"]
            figures["val_end_loss"] = totals["end_loss"] / totals["end_count"]
        figures[VAL_MEASURE] = figures.get("val_end_loss", 0.0) + 1.0 - figures["val_label_accuracy"]
        return figures

    def loss(trained: torch.nn.Module, batch: Batch) -> tuple[torch.Tensor, dict[str, float]]:
        value, stats = loss_fn(trained, batch)
        return value, _figures(stats)

    task = TrainingTask(
        name=name,
        model=model,
        batch_at=batch_at,
        loss=loss,
        learning_rate=lambda step: cosine_learning_rate(step, cfg.lr, cap),
        optimizer=lambda m: torch.optim.AdamW(m.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay),
        evaluate=evaluate if val_items else None,
        measure=VAL_MEASURE,
    )
    loop_cfg = LoopConfig(
        steps=cap,
        eval_every=evaluation_interval(cfg, epoch_steps),
        patience=cfg.patience if cfg.epochs is None and val_items else 0,
        patience_steps=int(cfg.patience_share * cap),
        max_minutes=cfg.max_minutes,
        grad_clip=5.0,
        device=device,
        progress=cfg.progress,
        log=log_to_stderr if cfg.log_epochs else None,
        state_path=Path(cfg.state_path) if cfg.state_path else None,
        resume=cfg.resume,
        fingerprint=cfg.fingerprint,
    )
    result = train_loop(task, loop_cfg)
    model = result.model.to("cpu")  # checkpoints and callers hold CPU weights
    return TrainResult(model, result.history, result.seconds, replace(result, model=model))


def train_ps(
    train_episodes: Sequence[Episode],
    val_episodes: Sequence[Episode],
    instructions: Sequence[str],
    cfg: TrainConfig,
    model_cfg: ModelConfig,
) -> TrainResult:
    """Train a PS model (end head + label head) on the annotated segments; keeps the best val weights."""
    torch.manual_seed(cfg.seed)
    model = PSModel(model_cfg, list(instructions))
    return _fit(model, lambda m, b: ps_loss(m, b, cfg), train_episodes, val_episodes, instructions, cfg, "ps")


def train_labeller(
    train_episodes: Sequence[Episode],
    val_episodes: Sequence[Episode],
    instructions: Sequence[str],
    cfg: TrainConfig,
    model_cfg: ModelConfig,
) -> TrainResult:
    """Train the stand-alone labelling model on the annotated segments (positives only)."""
    torch.manual_seed(cfg.seed)
    # it labels given segments: no end head to look ahead
    model_cfg = replace(model_cfg, end_lookahead=0)
    model = LabelModel(model_cfg, list(instructions))
    return _fit(
        model,
        lambda m, b: labeller_loss(m, b, cfg),
        train_episodes,
        val_episodes,
        instructions,
        cfg,
        "labeller",
    )
