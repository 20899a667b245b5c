"""Training of the PS model and the labelling model on annotated segments (samples: samples.py).

nanoGPT-style: the configuration, the losses and one explicit loop (`_fit`); the learning rate follows a
one-cycle schedule; the best epoch on the annotated val split is kept.
"""

from __future__ import annotations

import copy
import sys
import time
from collections.abc import Iterable, Sequence
from dataclasses import asdict, dataclass, replace

import numpy as np
import torch
import torch.nn.functional as F
from tqdm import tqdm

from playseg_core.data.episode import Episode
from playseg_core.data.features import Features
from playseg_core.domains import load_domain
from playseg_core.ps.encoders import StepEncoders, choose_encoders, feature_statistics
from playseg_core.ps.fixed_features import FixedFeatureCache
from playseg_core.ps.model import LabelModel, ModelConfig, PSModel, TrunkConfig
from playseg_core.ps.samples import (
    Batch,
    ClipSymmetries,
    camera_symmetries,
    label_index,
    make_batch,
)


@dataclass
class TrainConfig:
    seed: int = 0
    epochs: int = 16
    # Small datasets train for more epochs, up to at least this many optimizer steps: a fixed epoch count
    # gives too few steps to learn the labels on small data (measured: docs/segmentation.md "Training").
    min_steps: int = 3200
    segments_per_batch: int = 16  # drawn from all annotated episodes; small batches = more steps
    lr: float = 3e-3
    weight_decay: float = 1e-4
    k_max: int = 5  # negatives shift by 1..k_max steps
    dense_prefix_negatives: bool = True
    dense_window_negatives: bool = False  # windows starting off a true start: every position is "no end"
    augment: bool = False  # each training clip under a random symmetry (`training_symmetries`; see docs)
    domain: str | None = None  # the data's domain, whose `CLIP_SYMMETRIES` augment applies if it has any
    label_weight: float = 1.0
    frame_label_weight: float = 1.0  # auxiliary label loss on the end observation's encoding
    end_pos_weight: float = 4.0  # weight of the end head's positives in the BCE (ends are rare)
    num_threads: int = 2
    progress: bool = True  # tqdm bars
    log_epochs: bool = True  # one line per epoch and split


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

    A domain's ``SEGMENT_BOUNDS`` if it has them; else derived from the annotated lengths: L_max = the
    longest x 1.25 (segments a bit longer than any annotated one can still be cut), L_min = half the
    shortest, k_max = a quarter of the median length (negatives move a boundary by up to a quarter
    segment: by a few steps for short tasks, by more for long ones). Each given value wins.
    """
    measured = dict(getattr(load_domain(domain), "SEGMENT_BOUNDS", {}) if domain else {})
    source = f"domain {domain}" if measured else "annotated segments"
    if not measured:
        lengths = np.array([seg.length for ep in episodes for seg in ep.segments])
        if lengths.size == 0:
            raise ValueError("segment bounds: the training episodes have no annotated segments")
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
        raise ValueError(f"segment bounds need 1 <= min_len <= max_len and k_max >= 1, got {bounds}")
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
    end_grounding: int | None = None,
) -> ModelConfig:
    """The default model for data with ``features`` (step encoders by `choose_encoders`; the state and a
    continuous action standardised with ``episodes``' statistics, computed only when read; the label
    head ``label_head``, else the domain's ``LABEL_HEAD``, else "linear"; the end head's lookahead
    ``end_lookahead``, else the domain's ``END_LOOKAHEAD``, else 0, the paper's; the grounded end
    head's attention heads ``end_grounding``, else the domain's ``END_GROUNDING``, else 0: none)."""
    needs = [f.name for f in (features.state, features.action) if f is not None and not f.is_discrete]
    episodes = list(episodes)
    statistics = feature_statistics(episodes, needs) if episodes and needs else {}
    encoders = choose_encoders(features, domain, statistics, read_actions, overrides)
    observed = [features[spec.feature] for spec in encoders if spec.feature != features.action.name]
    # The action is always recorded (what the model was trained on), read or not.
    read = Features.of([*observed, features.action], features.fps)
    if label_head is None:
        label_head = getattr(load_domain(domain), "LABEL_HEAD", "linear") if domain else "linear"
    if end_lookahead is None:
        end_lookahead = int(getattr(load_domain(domain), "END_LOOKAHEAD", 0)) if domain else 0
    if end_grounding is None:
        end_grounding = int(getattr(load_domain(domain), "END_GROUNDING", 0)) if domain else 0
    return ModelConfig(
        encoders,
        read,
        num_classes,
        TrunkConfig(max_len=max_len),
        min_len=min_len,
        label_head=label_head,
        end_lookahead=end_lookahead,
        end_grounding=end_grounding,
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
    needed = torch.minimum(batch.needed_len, torch.tensor(num_pos))
    for members, length in _length_groups(needed):
        length = min(length, num_pos)
        # The end head also reads `lookahead` positions past each supervised one.
        windows = _gather_windows(features, batch.window_index[members, : length + model.lookahead])
        hidden = model.trunk(windows, batch.starts_episode[members])
        logits = model.raw_end_logits(hidden, windows)  # without end_bias: that is for segmenting only
        target, weight = batch.end_target[members, :length], batch.end_weight[members, :length]
        bce = F.binary_cross_entropy_with_logits(
            logits, target, reduction="none", pos_weight=logits.new_tensor(cfg.end_pos_weight)
        )
        end_sum = end_sum + (bce * weight).sum()
        if model.grounded_end is not None:  # also told the label where an annotated segment starts
            known = batch.window_labels[members] >= 0
            if known.any():
                told = model.told_end_logits(
                    hidden[known], windows[known], batch.window_labels[members][known]
                )
                bce = F.binary_cross_entropy_with_logits(
                    told, target[known], reduction="none", pos_weight=told.new_tensor(cfg.end_pos_weight)
                )
                end_sum = end_sum + (bce * weight[known]).sum()
        end_correct += int((((logits > 0).float() == target) & (weight > 0)).sum())
        # Label head: hidden state at the end of each positive whose window is in this group.
        slot = torch.full((num_windows,), -1, dtype=torch.long)
        slot[members] = torch.arange(len(members))
        here = slot[batch.label_window] >= 0
        if here.any():
            chosen = hidden[slot[batch.label_window[here]], batch.label_position[here]]
            label_hidden = label_hidden.index_put((torch.nonzero(here).squeeze(1),), chosen)
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


# ----------------------------------------------------------------------------------------------------
# Training loops


@dataclass
class EpochReport:
    epoch: int
    loss: float
    end_accuracy: float
    label_accuracy: float

    def line(self, prefix: str) -> str:
        return (
            f"{prefix} epoch {self.epoch}: loss {self.loss:.4f} end acc {self.end_accuracy:.4f} "
            f"label acc {self.label_accuracy:.4f}"
        )


def _summarise(epoch: int, stats: list[BatchStats]) -> EpochReport:
    end_count = sum(s.end_count for s in stats)
    label_count = sum(s.label_count for s in stats)
    weights = [max(s.end_count, s.label_count) for s in stats]
    return EpochReport(
        epoch=epoch,
        loss=sum(s.loss * w for s, w in zip(stats, weights, strict=True)) / max(1, sum(weights)),
        end_accuracy=sum(s.end_correct for s in stats) / max(1, end_count),
        label_accuracy=sum(s.label_correct for s in stats) / max(1, label_count),
    )


def clip_symmetries_of(domain: str | None) -> ClipSymmetries | None:
    """The ``CLIP_SYMMETRIES`` of ``domain`` (playseg_core/domains), or None: `augment` then turns camera
    frames only."""
    return getattr(load_domain(domain), "CLIP_SYMMETRIES", None) if domain else None


def training_symmetries(cfg: TrainConfig, encoders: StepEncoders) -> ClipSymmetries | None:
    """What `augment` trains on: the domain's symmetries, else the camera frames' rotations and mirrors
    (for models that read no actions: a mirror would swap left and right turns); None without augment."""
    if not cfg.augment:
        return None
    symmetries = clip_symmetries_of(cfg.domain)
    if symmetries is not None:
        return symmetries
    if encoders.reads_actions:
        raise ValueError(
            "augment: the camera frames' rotations leave the actions as they are; only for models that "
            "read no actions, or for a domain whose symmetries turn them too (its CLIP_SYMMETRIES)"
        )
    return camera_symmetries(encoders.cameras)


def _annotated(episodes: Sequence[Episode]) -> list[Episode]:
    return [ep for ep in episodes if ep.segments]


def _run_epoch(loss_fn, model, episodes, classes, cfg, rng, optimizer, epoch, desc, fixed) -> EpochReport:
    """One pass over `episodes` in batches; trains when an optimizer is given, else evaluates. ``fixed``:
    the outputs of the encoders that learn nothing, kept between epochs."""
    training = optimizer is not None
    model.train(training)
    items = [(ep, seg) for ep in episodes for seg in ep.segments]
    order = rng.permutation(len(items)) if training else np.arange(len(items))
    size = cfg.segments_per_batch
    symmetries = training_symmetries(cfg, model.encoders) if training else None
    batches = [order[i : i + size] for i in range(0, len(order), size)]
    stats: list[BatchStats] = []
    bar = tqdm(batches, desc=desc, file=sys.stderr, disable=not cfg.progress, leave=False)
    for chosen in bar:
        batch = make_batch(
            [items[i] for i in chosen],
            classes,
            model.encoders,
            model.max_len,
            cfg.k_max,
            rng,
            negatives=isinstance(model, PSModel),
            dense_prefix_negatives=cfg.dense_prefix_negatives,
            dense_window_negatives=cfg.dense_window_negatives,
            symmetries=symmetries,
            fixed=fixed,
            lookahead=model.lookahead,
        )
        if batch.labels.numel() == 0:
            continue
        with torch.set_grad_enabled(training):
            loss, batch_stats = loss_fn(model, batch)
        if training:
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            torch.nn.utils.clip_grad_norm_(model.parameters(), 5.0)
            optimizer.step()
        stats.append(batch_stats)
        bar.set_postfix(loss=f"{batch_stats.loss:.3f}")
    return _summarise(epoch, stats)


@dataclass
class TrainResult:
    model: torch.nn.Module
    history: list[dict]  # per epoch: train and val reports
    seconds: float


def epochs_to_train(cfg: TrainConfig, steps_per_epoch: int) -> int:
    """`cfg.epochs`, or more when that many epochs would stay below `cfg.min_steps` optimizer steps."""
    return max(cfg.epochs, -(-cfg.min_steps // max(1, steps_per_epoch)))


def _fit(model, loss_fn, train_eps, val_eps, instructions, cfg: TrainConfig, name: str) -> TrainResult:
    torch.set_num_threads(cfg.num_threads)
    torch.manual_seed(cfg.seed)
    rng = np.random.default_rng(cfg.seed)
    classes = label_index(instructions)
    train_eps, val_eps = _annotated(train_eps), _annotated(val_eps)
    if not train_eps:
        raise ValueError("no annotated training episodes (episodes with segments)")
    optimizer = torch.optim.AdamW(model.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    num_segments = sum(len(ep.segments) for ep in train_eps)
    steps_per_epoch = -(-num_segments // cfg.segments_per_batch)
    epochs = epochs_to_train(cfg, steps_per_epoch)
    schedule = torch.optim.lr_scheduler.OneCycleLR(
        optimizer, max_lr=cfg.lr, total_steps=epochs * steps_per_epoch, pct_start=0.05
    )

    class _Stepper:  # the schedule advances once per optimizer step
        def zero_grad(self, set_to_none: bool = True) -> None:
            optimizer.zero_grad(set_to_none=set_to_none)

        def step(self) -> None:
            optimizer.step()
            schedule.step()

    history: list[dict] = []
    best_key, best_state = None, None
    began = time.perf_counter()
    fixed = FixedFeatureCache(model.encoders)
    fixed = fixed if fixed.features else None
    for epoch in range(1, epochs + 1):
        train_report = _run_epoch(
            loss_fn, model, train_eps, classes, cfg, rng, _Stepper(), epoch, f"{name} {epoch}", fixed
        )
        entry = {"train": asdict(train_report)}
        if val_eps:
            # Fixed negatives for validation: the same rng seed every epoch.
            val_report = _run_epoch(
                loss_fn, model, val_eps, classes, cfg, np.random.default_rng(12345), None, epoch, "val", fixed
            )
            entry["val"] = asdict(val_report)
            key = val_report.loss
            if best_key is None or key < best_key:
                best_key, best_state = key, copy.deepcopy(model.state_dict())
            if cfg.log_epochs:
                print(val_report.line(f"[{name}] val"), file=sys.stderr, flush=True)
        if cfg.log_epochs:
            print(train_report.line(f"[{name}] train"), file=sys.stderr, flush=True)
        history.append(entry)
    if best_state is not None:
        model.load_state_dict(best_state)
    model.eval()
    return TrainResult(model, history, time.perf_counter() - began)


def train_ps(
    train_episodes: Sequence[Episode],
    val_episodes: Sequence[Episode],
    instructions: Sequence[str],
    cfg: TrainConfig,
    model_cfg: ModelConfig,
) -> TrainResult:
    """Train a PS model (end head + label head) on the annotated segments; keeps the best val epoch."""
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
    # it labels given segments: no end head to look ahead or ground
    model_cfg = replace(model_cfg, end_lookahead=0, end_grounding=0)
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
