"""Training of the PS model and the labelling model on annotated segments, and their checkpoints.

Training samples follow the paper: every annotated segment [s, e) is a positive; its negatives move the
end later / earlier, widen both sides, take the window before it, and shift it left / right, by k drawn
from 1..k_max, always inside the episode and never longer than the model's L_max. Beyond the paper
(`dense_prefix_negatives`): the trunk is causal from the start, so one pass over a positive window also
yields the end logit of every proper prefix [s, s+m), m < e-s, which did *not* end — supervised as 0.
That is exactly the `log(1 - p_seg)` term of the segment score the decoder maximises.

Frames are encoded once per batch of episodes; windows are gathered from those features by index.
"""

from __future__ import annotations

import copy
import sys
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from tqdm import tqdm

from playseg_core.data.episode import Episode, Segment
from playseg_core.ps.model import (
    EncoderConfig,
    LabelModel,
    ModelConfig,
    PSModel,
    TrunkConfig,
    previous_actions,
)

NEGATIVE_KINDS = ("end_later", "end_earlier", "widened", "before", "shift_left", "shift_right")


@dataclass(frozen=True)
class Sample:
    """A training window [start, end) of one episode; is_end says whether a segment ends at `end`."""

    start: int
    end: int
    is_end: bool
    kind: str  # "positive" or one of NEGATIVE_KINDS


def _draw(rng: np.random.Generator, high: int) -> int | None:
    """k uniform in 1..high, or None when the range is empty."""
    return int(rng.integers(1, high + 1)) if high >= 1 else None


def segment_samples(
    start: int, end: int, num_steps: int, max_len: int, k_max: int, rng: np.random.Generator
) -> list[Sample]:
    """The positive [start, end) and up to six negatives; a kind that cannot fit is left out.

    A segment longer than max_len cannot be scored by the model and yields no samples at all.
    """
    length = end - start
    if not 0 < length <= max_len or end > num_steps or start < 0:
        return []
    samples = [Sample(start, end, True, "positive")]

    def add(kind: str, s: int, e: int) -> None:
        samples.append(Sample(s, e, False, kind))

    room_left, room_right, room_len = start, num_steps - end, max_len - length
    if (k := _draw(rng, min(k_max, room_right, room_len))) is not None:
        add("end_later", start, end + k)
    if (k := _draw(rng, min(k_max, length - 1))) is not None:
        add("end_earlier", start, end - k)
    if (k3 := _draw(rng, min(k_max, room_left, room_len - 1))) is not None:
        if (k4 := _draw(rng, min(k_max, room_right, room_len - k3))) is not None:
            add("widened", start - k3, end + k4)
    if (k := _draw(rng, min(k_max, room_left, max_len))) is not None:
        add("before", start - k, start)
    if (k := _draw(rng, min(k_max, room_left))) is not None:
        add("shift_left", start - k, end - k)
    if (k := _draw(rng, min(k_max, room_right))) is not None:
        add("shift_right", start + k, end + k)
    return samples


@dataclass
class TrainConfig:
    seed: int = 0
    epochs: int = 16
    # Small datasets train for more epochs, up to at least this many optimizer steps: at the demo scale
    # (100 steps per epoch) 1,600 steps often ended before the encoder learnt "what is faced".
    min_steps: int = 3200
    segments_per_batch: int = 16  # drawn from all annotated episodes; small batches = more steps
    lr: float = 3e-3
    weight_decay: float = 1e-4
    k_max: int = 5  # negatives shift by 1..k_max steps (BabyAI: 5)
    dense_prefix_negatives: bool = True
    dense_window_negatives: bool = False  # windows starting off a true start: every position is "no end"
    augment: bool = False  # random rotation/mirror per training segment (slower to learn; see docs)
    label_weight: float = 1.0
    frame_label_weight: float = 1.0  # auxiliary label loss on the end frame's features (encoder)
    end_pos_weight: float = 4.0  # weight of the end head's positives in the BCE (ends are rare)
    num_threads: int = 2
    progress: bool = True  # tqdm bars
    log_epochs: bool = True  # one line per epoch and split


def default_model_config(num_classes: int, max_len: int = 25, num_actions: int = 0) -> ModelConfig:
    """The measured default model; `num_actions` > 0 makes it read discrete actions (BabyAI: 7)."""
    return ModelConfig(EncoderConfig(), TrunkConfig(max_len=max_len), num_classes, num_actions=num_actions)


# ----------------------------------------------------------------------------------------------------
# Batches


@dataclass
class Batch:
    """Training windows of a few episodes. A window starts at one step and is supervised at positions.

    Samples that share a start share a window (the trunk is causal from the start, so one pass yields
    the end logit at every position): the positive and its end-earlier / end-later negatives all live
    in the window of the segment's true start.
    """

    frames: torch.Tensor  # (N, H, W, 3) uint8, the frames of all episodes of the batch
    prev_actions: torch.Tensor | None  # (N,) index of the action that led to each frame (None: unused)
    window_index: torch.Tensor  # (S, L_max+1) rows into features (N = a zero row past an episode end)
    starts_episode: torch.Tensor  # (S,) bool: the window starts at step 0
    end_target: torch.Tensor  # (S, L_max+1) 1 where a segment ends at that position
    end_weight: torch.Tensor  # (S, L_max+1) 1 where the end head is supervised
    label_window: torch.Tensor  # (M,) window of each positive
    label_position: torch.Tensor  # (M,) its length (the position of its end in the window)
    labels: torch.Tensor  # (M,) its class index

    @property
    def needed_len(self) -> torch.Tensor:
        """(S,) positions each window needs: 1 + the last supervised position."""
        positions = torch.arange(self.end_weight.shape[1])
        return (positions * (self.end_weight > 0)).amax(1) + 1


def label_index(instructions: Sequence[str]) -> dict[str, int]:
    return {text: index for index, text in enumerate(instructions)}


def make_batch(
    items: Sequence[tuple[Episode, Segment]],
    classes: dict[str, int],
    max_len: int,
    k_max: int,
    rng: np.random.Generator,
    negatives: bool = True,
    dense_prefix_negatives: bool = False,
    augment: bool = False,
    dense_window_negatives: bool = False,
    num_actions: int = 0,
) -> Batch:
    """The windows of the annotated segments `items` (only positives if not `negatives`).

    Only the frames each segment's samples can touch (k_max around it) are included: a batch holds
    segments from many episodes, which trains far faster than whole episodes (many rooms per step).
    With `dense_prefix_negatives`, the true-start window is also supervised as "not ended" at every
    position before the end and at every position up to k_max after it (the end-earlier and end-later
    negatives for all k at once). With `augment`, each segment's frames get one random rotation by a
    multiple of 90 degrees and an optional mirror (the whole clip alike): facing, goals and instructions
    are unchanged by them, so the model cannot lean on memorised room layouts. With `num_actions` > 0
    (a model that reads actions) the batch also carries the action that led to each frame.
    """
    if augment and num_actions:
        # A mirror swaps left and right turns: the actions would need the env's own remapping.
        raise ValueError("augment is not supported for models that read actions")
    regions = [(max(0, seg.start - k_max), min(ep.num_steps, seg.end + k_max)) for ep, seg in items]
    zero_row = sum(hi - lo + 1 for lo, hi in regions)
    num_pos = max_len + 1
    frames, prev_actions, rows, starts_episode, targets, weights = [], [], [], [], [], []
    label_window, label_position, labels = [], [], []
    offset = 0
    for (ep, seg), (lo, hi) in zip(items, regions, strict=True):
        clip = np.array(ep.frames[lo : hi + 1], dtype=np.uint8)
        if augment:
            clip = np.rot90(clip, k=int(rng.integers(4)), axes=(1, 2))
            if rng.integers(2):
                clip = clip[:, :, ::-1]
        frames.append(torch.from_numpy(np.ascontiguousarray(clip)))
        if num_actions:
            where = f"episode {ep.episode_id} actions"
            prev_actions.append(
                torch.from_numpy(previous_actions(ep.actions, num_actions, where)[lo : hi + 1])
            )
        samples = segment_samples(seg.start, seg.end, ep.num_steps, max_len, k_max, rng)
        windows: dict[int, int] = {}  # start -> row
        for sample in samples:
            if not negatives and not sample.is_end:
                continue
            if sample.start not in windows:
                windows[sample.start] = len(rows)
                steps = sample.start + np.arange(num_pos)
                rows.append(np.where(steps <= hi, offset + steps - lo, zero_row))
                starts_episode.append(sample.start == 0)
                targets.append(np.zeros(num_pos, np.float32))
                weights.append(np.zeros(num_pos, np.float32))
            row, position = windows[sample.start], sample.end - sample.start
            targets[row][position] = float(sample.is_end)
            weights[row][position] = 1.0
            if sample.is_end:
                label_window.append(row)
                label_position.append(position)
                labels.append(classes[seg.instruction])
        if negatives and dense_prefix_negatives and seg.start in windows:
            row, length = windows[seg.start], seg.end - seg.start
            last = min(length + k_max, max_len, ep.num_steps - seg.start)
            weights[row][1 : last + 1] = 1.0  # targets stay 0 except at the true end
        if negatives and dense_window_negatives:
            true_starts = {s.start for s in ep.segments}
            for start, row in windows.items():
                if start not in true_starts:  # no true segment starts here: no position is an end
                    weights[row][1 : min(max_len, hi - start) + 1] = 1.0
        offset += hi - lo + 1

    def stack(arrays: list[np.ndarray], dtype: type) -> torch.Tensor:
        return torch.from_numpy(np.array(arrays, dtype=dtype).reshape(-1, num_pos))

    return Batch(
        frames=torch.cat(frames),
        prev_actions=torch.cat(prev_actions) if num_actions else None,
        window_index=stack(rows, np.int64),
        starts_episode=torch.tensor(starts_episode, dtype=torch.bool),
        end_target=stack(targets, np.float32),
        end_weight=stack(weights, np.float32),
        label_window=torch.tensor(label_window, dtype=torch.long),
        label_position=torch.tensor(label_position, dtype=torch.long),
        labels=torch.tensor(labels, dtype=torch.long),
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
    features = model.encode_steps(batch.frames, batch.prev_actions)
    num_windows, num_pos = batch.window_index.shape
    end_sum = features.new_zeros(())
    label_hidden = features.new_zeros(len(batch.labels), model.cfg.trunk.hidden_dim)
    end_correct = 0
    needed = torch.minimum(batch.needed_len, torch.tensor(num_pos))
    for members, length in _length_groups(needed):
        length = min(length, num_pos)
        windows = _gather_windows(features, batch.window_index[members, :length])
        hidden = model.trunk(windows, batch.starts_episode[members])
        logits = model.end_head(hidden).squeeze(-1)  # the raw head: end_bias is for segmenting only
        target, weight = batch.end_target[members, :length], batch.end_weight[members, :length]
        bce = F.binary_cross_entropy_with_logits(
            logits, target, reduction="none", pos_weight=logits.new_tensor(cfg.end_pos_weight)
        )
        end_sum = end_sum + (bce * weight).sum()
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
    """Auxiliary CE of `frame_label_head` on each positive's end-frame encoder features (weighted)."""
    if cfg.frame_label_weight <= 0:
        return features.new_zeros(())
    end_frames = batch.window_index[batch.label_window, batch.label_position]
    frame_logits = model.frame_label_head(model.frame_part(features[end_frames]))
    return cfg.frame_label_weight * F.cross_entropy(frame_logits, batch.labels)


def labeller_loss(model: LabelModel, batch: Batch, cfg: TrainConfig) -> tuple[torch.Tensor, BatchStats]:
    """CE of the labelling model on the positives of the batch (one window per positive), plus the
    auxiliary CE of `frame_label_head` on each end frame's encoder features (as in `ps_loss`)."""
    features = model.encode_steps(batch.frames, batch.prev_actions)
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


def _annotated(episodes: Sequence[Episode]) -> list[Episode]:
    return [ep for ep in episodes if ep.segments]


def _run_epoch(loss_fn, model, episodes, classes, cfg, rng, optimizer, epoch, desc) -> EpochReport:
    """One pass over `episodes` in batches; trains when an optimizer is given, else evaluates."""
    training = optimizer is not None
    model.train(training)
    items = [(ep, seg) for ep in episodes for seg in ep.segments]
    order = rng.permutation(len(items)) if training else np.arange(len(items))
    size = cfg.segments_per_batch
    batches = [order[i : i + size] for i in range(0, len(order), size)]
    stats: list[BatchStats] = []
    bar = tqdm(batches, desc=desc, file=sys.stderr, disable=not cfg.progress, leave=False)
    for chosen in bar:
        batch = make_batch(
            [items[i] for i in chosen],
            classes,
            model.max_len,
            cfg.k_max,
            rng,
            negatives=isinstance(model, PSModel),
            dense_prefix_negatives=cfg.dense_prefix_negatives,
            dense_window_negatives=cfg.dense_window_negatives,
            augment=training and cfg.augment,
            num_actions=model.cfg.num_actions,
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
    for epoch in range(1, epochs + 1):
        train_report = _run_epoch(
            loss_fn, model, train_eps, classes, cfg, rng, _Stepper(), epoch, f"{name} {epoch}"
        )
        entry = {"train": asdict(train_report)}
        if val_eps:
            # Fixed negatives for validation: the same rng seed every epoch.
            val_report = _run_epoch(
                loss_fn, model, val_eps, classes, cfg, np.random.default_rng(12345), None, epoch, "val"
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
    model_cfg: ModelConfig | None = None,
) -> TrainResult:
    """Train a PS model (end head + label head) on the annotated segments; keeps the best val epoch."""
    torch.manual_seed(cfg.seed)
    model = PSModel(model_cfg or default_model_config(len(instructions)), list(instructions))
    return _fit(model, lambda m, b: ps_loss(m, b, cfg), train_episodes, val_episodes, instructions, cfg, "ps")


def train_labeller(
    train_episodes: Sequence[Episode],
    val_episodes: Sequence[Episode],
    instructions: Sequence[str],
    cfg: TrainConfig,
    model_cfg: ModelConfig | None = None,
) -> TrainResult:
    """Train the stand-alone labelling model on the annotated segments (positives only)."""
    torch.manual_seed(cfg.seed)
    model = LabelModel(model_cfg or default_model_config(len(instructions)), list(instructions))
    return _fit(
        model,
        lambda m, b: labeller_loss(m, b, cfg),
        train_episodes,
        val_episodes,
        instructions,
        cfg,
        "labeller",
    )


# ----------------------------------------------------------------------------------------------------
# Checkpoints: plain tensors and builtins only, loaded with weights_only=True (checkpoints are untrusted).

_KINDS = {"ps": PSModel, "labeller": LabelModel}


def save_checkpoint(path: str | Path, model: PSModel | LabelModel, extra: dict | None = None) -> None:
    kind = "ps" if isinstance(model, PSModel) else "labeller"
    payload = {
        "kind": kind,
        "config": asdict(model.cfg),
        "state_dict": model.state_dict(),
        "instructions": list(model.instructions),
        "extra": extra or {},
    }
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    torch.save(payload, path)


def load_checkpoint(path: str | Path) -> tuple[PSModel | LabelModel, dict]:
    """-> (model in eval mode with its .instructions, extra); ValueError naming the file if invalid."""
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"checkpoint {path}: no such file")
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as error:  # corrupt, truncated, or carrying objects weights_only refuses
        raise ValueError(f"checkpoint {path}: cannot be read safely ({error})") from error
    try:
        model_class = _KINDS[payload["kind"]]
        cfg = ModelConfig.from_dict(payload["config"])
        model = model_class(cfg, [str(s) for s in payload["instructions"]])
        state = dict(payload["state_dict"])
        if model_class is PSModel:
            state.setdefault("end_bias", torch.zeros(()))  # checkpoints from before the end bias
        model.load_state_dict(state)
    except Exception as error:
        raise ValueError(f"checkpoint {path}: not a playseg checkpoint ({error!r})") from error
    model.eval()
    return model, dict(payload.get("extra", {}))
