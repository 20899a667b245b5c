"""TriDet-style temporal action localisation (the paper's adaptation of TriDet, appendix "TriDet").

A window of a fixed number of steps (32 for data whose segments fit in 25 steps; otherwise 1.25 x the
longest annotated segment, rounded up to the pyramid's stride) goes through a temporal feature pyramid
(level l: one cell per 2^l steps). Heads shared by every level give, per cell, a score for each
instruction and the trident head's boundaries: the start (end) is a distribution over relative bins
0..B, the distance to the cell in units of the level's stride, whose logits are the start (end)
response of the cell that far away plus the cell's own offset logits; the boundary is the expectation.
Each annotated segment is assigned to one level by its length; the cells whose centre lies inside it are
its positives (sigmoid focal loss for the scores; a distribution loss on the bins and an IoU loss on the
expected segment for the boundaries). The original reads I3D features (the paper: the labelling model's);
here the steps come from our step encoders, trained with the model.

Training windows hold one annotated segment at a random place. Segmenting: back-to-back windows of the
same size from a random offset; the top-1 detection of each window (the cell and instruction with the
highest score, with that cell's boundaries) is kept if it is at least the minimum length (`top1_detection`).
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from playseg_core.baselines.common import (
    WINDOW_STEP_CAP,
    Segmenter,
    SegmentOptions,
    TrainedSegmenter,
    TrainingData,
    TrainOptions,
    WindowBatches,
    annotated_lengths,
    encode_episode,
    encode_windows,
    episode_rng,
    fit,
    fixed_windows,
    freeze_pretrained_encoders,
    step_encoders_for,
    transition_tokens,
    window_inputs,
    window_rows,
)
from playseg_core.checkpoint import Checkpoint, CheckpointError, read_checkpoint, save_checkpoint
from playseg_core.data.episode import Episode, Segment
from playseg_core.data.features import Features
from playseg_core.ps.encoders import EncoderSpec, StepEncoders
from playseg_core.ps.fixed_features import FixedFeatureCache
from playseg_core.training.device import resolve_device

KIND = "tridet"
SHORT_WINDOW = 32  # the paper's window for short-segment data (segments of up to ~25 steps)


@dataclass
class TridetConfig:
    window: int = SHORT_WINDOW
    levels: int = 3  # strides 1, 2, 4
    num_bins: int = 8  # boundary distances 0..num_bins strides
    dim: int = 64
    min_len: int = 1
    # Every annotated segment wholly inside a training window is a target, not only the one the window
    # was drawn around (TAL training reads all ground truth of a clip; marking known segments as
    # background would teach the model to suppress them). False: the drawn segment only.
    supervise_all: bool = True

    @staticmethod
    def for_lengths(longest: int, min_len: int = 1) -> TridetConfig:
        """Window, pyramid and bins for annotated segments of up to ``longest`` steps: at least
        SHORT_WINDOW and 1.25 x the longest; levels up to a stride of about window/8; the top level's
        bins reach across the whole window."""
        wanted = max(SHORT_WINDOW, math.ceil(1.25 * longest))
        levels = max(1, math.ceil(math.log2(wanted / 4)))
        top = 2 ** (levels - 1)
        window = math.ceil(wanted / top) * top
        return TridetConfig(window=window, levels=levels, num_bins=window // top, min_len=min_len)

    def level_of(self, length: int) -> int:
        """The pyramid level responsible for a segment of ``length`` steps: up to 4 steps level 0, up to
        8 level 1, ... (each level's cells are 2^l steps)."""
        return min(self.levels - 1, max(0, math.ceil(math.log2(max(length, 1) / 4))))


class ConvBlock(nn.Module):
    """Pre-norm residual temporal convolution, padded positions kept at zero."""

    def __init__(self, dim: int) -> None:
        super().__init__()
        self.norm = nn.LayerNorm(dim)
        self.conv = nn.Conv1d(dim, dim, 3, padding=1)
        self.out = nn.Linear(dim, dim)

    def forward(self, h: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
        x = self.conv(self.norm(h).transpose(1, 2)).transpose(1, 2)
        return (h + self.out(F.gelu(x))) * valid[..., None]


class Head(nn.Module):
    def __init__(self, dim: int, out: int) -> None:
        super().__init__()
        self.net = nn.Sequential(
            nn.Conv1d(dim, dim, 3, padding=1), nn.GELU(), nn.Conv1d(dim, out, 3, padding=1)
        )

    def forward(self, h: torch.Tensor) -> torch.Tensor:
        return self.net(h.transpose(1, 2)).transpose(1, 2)


@dataclass
class LevelOutput:
    """One pyramid level for a batch of windows: cells of ``stride`` steps."""

    stride: int
    valid: torch.Tensor  # (B, N) cells inside the window
    class_logits: torch.Tensor  # (B, N, C)
    start_logits: torch.Tensor  # (B, N, bins+1): distance of the start, in strides, to the cell's left edge
    end_logits: torch.Tensor  # (B, N, bins+1): distance of the end to the cell's right edge

    def expected(self) -> tuple[torch.Tensor, torch.Tensor]:
        """(B, N) expected start and end, in steps from the window start (float32, also under autocast)."""
        start_logits, end_logits = self.start_logits.float(), self.end_logits.float()
        bins = torch.arange(start_logits.shape[-1], dtype=start_logits.dtype, device=start_logits.device)
        start_bins = (torch.softmax(start_logits, -1) * bins).sum(-1)
        end_bins = (torch.softmax(end_logits, -1) * bins).sum(-1)
        cells = torch.arange(self.valid.shape[1], dtype=bins.dtype, device=bins.device)
        return (cells - start_bins) * self.stride, (cells + 1 + end_bins) * self.stride

    def cpu(self) -> LevelOutput:
        """The level with its tensors on the CPU (one transfer, not one per window's detection)."""
        tensors = (self.valid, self.class_logits, self.start_logits, self.end_logits)
        return LevelOutput(self.stride, *(tensor.cpu() for tensor in tensors))


def _shifted(response: torch.Tensor, bins: int, direction: int) -> torch.Tensor:
    """(B, N) boundary responses -> (B, N, bins+1): [i, b] = response[i + direction * b], -inf outside."""
    batch, cells = response.shape
    steps = torch.arange(bins + 1, device=response.device)
    index = torch.arange(cells, device=response.device)[:, None] + direction * steps[None, :]
    inside = (index >= 0) & (index < cells)
    gathered = response[:, index.clamp(0, cells - 1)]
    return gathered.masked_fill(~inside, float("-inf"))


class TridetModel(nn.Module):
    def __init__(
        self, encoders: list[EncoderSpec], features: Features, instructions: Sequence[str], cfg: TridetConfig
    ) -> None:
        super().__init__()
        self.cfg = cfg
        self.features = features
        self.instructions = list(instructions)
        self.encoders = StepEncoders(encoders, features)
        dim = cfg.dim
        self.proj = nn.Sequential(nn.Linear(2 * self.encoders.step_dim, dim), nn.LayerNorm(dim))
        self.stem = nn.ModuleList([ConvBlock(dim), ConvBlock(dim)])
        self.down = nn.ModuleList(ConvBlock(dim) for _ in range(cfg.levels - 1))
        self.classify = Head(dim, len(self.instructions))
        nn.init.constant_(self.classify.net[-1].bias, -4.0)  # focal-loss prior: positives are rare
        self.start_response = Head(dim, 1)
        self.end_response = Head(dim, 1)
        self.offsets = Head(dim, 2 * (cfg.num_bins + 1))

    def forward(self, rows: torch.Tensor, valid: torch.Tensor) -> list[LevelOutput]:
        """(B, window+1, d) observation rows, (B, window) valid steps -> one output per pyramid level."""
        h = self.proj(transition_tokens(rows)) * valid[..., None]
        for block in self.stem:
            h = block(h, valid)
        outputs, bins = [], self.cfg.num_bins
        for level in range(self.cfg.levels):
            if level:
                h = F.max_pool1d(h.transpose(1, 2), 2).transpose(1, 2)
                valid = valid[:, ::2]
                h = self.down[level - 1](h, valid)
            offsets = self.offsets(h)
            start = _shifted(self.start_response(h).squeeze(-1), bins, -1) + offsets[..., : bins + 1]
            end = _shifted(self.end_response(h).squeeze(-1), bins, +1) + offsets[..., bins + 1 :]
            outputs.append(LevelOutput(2**level, valid, self.classify(h), start, end))
        return outputs


@dataclass(frozen=True)
class Detection:
    start: int  # steps from the window start
    end: int
    label: int
    score: float


def top1_detection(levels: Sequence[LevelOutput], row: int, num_steps: int, min_len: int) -> Detection | None:
    """The paper's cropping: the cell of the pyramid with the highest class score in window ``row``,
    its class and boundaries (rounded, clipped to the window's ``num_steps``); None when shorter than
    ``min_len``."""
    best: tuple[float, int, int, int] | None = None
    for index, level in enumerate(levels):
        scores = torch.sigmoid(level.class_logits[row]).masked_fill(~level.valid[row, :, None], -1.0)
        value, flat = scores.flatten().max(0)
        if best is None or float(value) > best[0]:
            best = (float(value), index, int(flat) // scores.shape[1], int(flat) % scores.shape[1])
    if best is None:
        return None
    score, index, cell, label = best
    starts, ends = levels[index].expected()
    start = int(np.clip(round(float(starts[row, cell])), 0, num_steps))
    end = int(np.clip(round(float(ends[row, cell])), 0, num_steps))
    if end - start < min_len:
        return None
    return Detection(start, end, label, score)


# ----------------------------------------------------------------------------------------------------
# Training


def _two_hot_loss(logits: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Distribution loss: CE against the two bins around a fractional target (their weights sum to 1)."""
    low = target.floor().long().clamp(0, logits.shape[-1] - 1)
    high = (low + 1).clamp(max=logits.shape[-1] - 1)
    weight_high = (target - low.to(target.dtype)).clamp(0, 1)
    log_probs = torch.log_softmax(logits, -1).clamp(min=-1e4)  # a bin off the window is -inf (weight 0)
    picked_low = log_probs.gather(-1, low[:, None]).squeeze(-1)
    picked_high = log_probs.gather(-1, high[:, None]).squeeze(-1)
    return -((1 - weight_high) * picked_low + weight_high * picked_high).mean()


def tridet_loss(
    model: TridetModel, levels: list[LevelOutput], spans: Sequence[Sequence[tuple[int, int, int]]]
) -> torch.Tensor:
    """Focal loss of the class scores over all cells + boundary losses at the positives; ``spans[row]``
    holds window ``row``'s segments as (start, end, class) in steps from the window start. The positives
    are found on the CPU (they depend on the spans alone); the losses are computed in float32 on the
    levels' device."""
    cfg = model.cfg
    focal_sum, positives = 0.0, 0
    boundary_losses = []
    for level_index, level in enumerate(levels):
        device, num_cells = level.class_logits.device, level.valid.shape[1]
        centres = (torch.arange(num_cells) + 0.5) * level.stride
        rows, cells, labels, starts, ends = [], [], [], [], []
        for row, start, end, label in ((r, *span) for r, window in enumerate(spans) for span in window):
            if cfg.level_of(end - start) != level_index:
                continue
            inside = torch.nonzero((centres >= start) & (centres < end)).squeeze(1).tolist()
            if not inside:  # a short segment between two centres: the cell of its middle
                inside = [min(int((start + end) / 2 / level.stride), num_cells - 1)]
            rows += [row] * len(inside)
            cells += inside
            labels += [label] * len(inside)
            starts += [start] * len(inside)
            ends += [end] * len(inside)
        class_logits = level.class_logits.float()
        target = torch.zeros_like(class_logits)
        if rows:
            row_t = torch.tensor(rows, device=device)
            cell_t = torch.tensor(cells, device=device)
            target[row_t, cell_t, torch.tensor(labels, device=device)] = 1.0
        focal = sigmoid_focal_loss(class_logits[level.valid], target[level.valid])
        focal_sum = focal_sum + focal
        positives += len(rows)
        if rows:
            start_t = torch.tensor(starts, dtype=torch.float32, device=device)
            end_t = torch.tensor(ends, dtype=torch.float32, device=device)
            stride, bins = level.stride, cfg.num_bins
            start_bins = (cell_t - start_t / stride).clamp(0, bins)
            end_bins = (end_t / stride - cell_t - 1).clamp(0, bins)
            dfl = _two_hot_loss(level.start_logits[row_t, cell_t].float(), start_bins) + _two_hot_loss(
                level.end_logits[row_t, cell_t].float(), end_bins
            )
            pred_start, pred_end = (x[row_t, cell_t] for x in level.expected())
            overlap = (torch.minimum(pred_end, end_t) - torch.maximum(pred_start, start_t)).clamp(min=0)
            union = torch.maximum(pred_end, end_t) - torch.minimum(pred_start, start_t)
            iou = overlap / union.clamp(min=1e-6)
            boundary_losses.append(dfl + (1 - iou).mean())
    if boundary_losses:
        boundary = torch.stack(boundary_losses).mean()
    else:
        boundary = torch.zeros((), device=levels[0].class_logits.device)
    return focal_sum / max(1, positives) + boundary


def sigmoid_focal_loss(
    logits: torch.Tensor, target: torch.Tensor, alpha: float = 0.25, gamma: float = 2.0
) -> torch.Tensor:
    """Sigmoid focal loss (RetinaNet), summed."""
    probs = torch.sigmoid(logits)
    ce = F.binary_cross_entropy_with_logits(logits, target, reduction="none")
    p_t = probs * target + (1 - probs) * (1 - target)
    weight = alpha * target + (1 - alpha) * (1 - target)
    return (weight * ce * (1 - p_t) ** gamma).sum()


def _training_window(
    episode: Episode, seg: Segment, window: int, rng: np.random.Generator
) -> tuple[int, int]:
    """A window of ``window`` steps holding ``seg`` at a random place (the whole episode when shorter)."""
    if episode.num_steps <= window:
        return 0, episode.num_steps
    low, high = max(0, seg.end - window), min(seg.start, episode.num_steps - window)
    start = int(rng.integers(low, high + 1))
    return start, start + window


def _padded(rows: torch.Tensor, valid: torch.Tensor, window: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Rows and validity padded to the full window (an episode shorter than the window)."""
    missing = window - valid.shape[1]
    if missing <= 0:
        return rows, valid
    return F.pad(rows, (0, 0, 0, missing)), F.pad(valid, (0, missing), value=False)


def train_tridet(
    data: TrainingData, options: TrainOptions, cfg: TridetConfig | None = None
) -> TrainedSegmenter:
    """Train the TriDet-style model on windows holding one annotated segment each."""
    from playseg_core.ps.training import segment_bounds

    began = time.perf_counter()
    torch.manual_seed(options.seed)
    train_eps = data.annotated()
    bounds = segment_bounds(train_eps, data.domain, **data.bounds)
    lengths = annotated_lengths(train_eps)
    cfg = cfg or TridetConfig.for_lengths(int(lengths.max()), bounds.min_len)
    specs, features = step_encoders_for(data)
    model = TridetModel(specs, features, data.instructions, cfg)
    freeze_pretrained_encoders(model.encoders, data)
    fixed = FixedFeatureCache(model.encoders)
    classes = {text: i for i, text in enumerate(data.instructions)}
    fits = lambda seg: seg.length <= cfg.window  # noqa: E731 - a longer segment fits no window
    items = {True: [(e, s) for e in train_eps for s in e.segments if fits(s)]}
    items[False] = [(e, s) for e in data.val for s in e.segments if fits(s)] or items[True]
    batch_size = options.batch_size or 32

    def choose(rng: np.random.Generator, training: bool) -> list[tuple[Episode, Segment, int, int]]:
        pool = items[training]
        chosen = [pool[i] for i in rng.integers(0, len(pool), size=batch_size)]
        return [(e, s, *_training_window(e, s, cfg.window, rng)) for e, s in chosen]

    def build(windows: list[tuple[Episode, Segment, int, int]]) -> dict[str, Any]:
        batch_windows = window_inputs(
            model.encoders, [(e, start, end) for e, _, start, end in windows], fixed
        )
        spans = [
            [
                (seg.start - start, seg.end - start, classes[seg.instruction])
                for seg in (episode.segments if cfg.supervise_all else [drawn])
                if start <= seg.start and seg.end <= end
            ]
            for episode, drawn, start, end in windows
        ]
        return {"windows": batch_windows, "spans": spans}

    def loss(trained: nn.Module, batch: dict[str, Any]) -> torch.Tensor:
        rows = encode_windows(trained.encoders, batch["windows"])
        return tridet_loss(
            trained, trained(*_padded(rows, batch["windows"].valid, cfg.window)), batch["spans"]
        )

    steps = options.step_cap(len(items[True]), batch_size, default_steps=WINDOW_STEP_CAP)
    report = fit(model, WindowBatches(choose, build, loss), options, steps, options.lr or 1e-3, "tridet")
    meta = {"train": asdict(options), **report.meta(), "encoders_from": data.encoders_from}

    def save(path: Path, extra: dict[str, Any]) -> Path:
        return save_tridet(path, model, {**meta, **extra})

    text = f"TriDet-style model (window {cfg.window}, {cfg.levels} levels): {report.summary()}"
    return TrainedSegmenter(TridetSegmenter(model), save, time.perf_counter() - began, text)


# ----------------------------------------------------------------------------------------------------
# Segmenting


class TridetSegmenter(Segmenter):
    method = "tridet"
    tiles = False

    def __init__(self, model: TridetModel, options: SegmentOptions | None = None) -> None:
        options = options or SegmentOptions()
        self.model = model.to(resolve_device(options.device)).eval()
        self.instructions = model.instructions
        self.features = model.features
        self.feature_names = [spec.feature for spec in model.encoders.specs]
        self.min_len = options.min_len or model.cfg.min_len
        self.seed = options.seed

    @torch.no_grad()
    def segment(self, episode: Episode) -> list[Segment]:
        if episode.num_steps == 0:
            return []
        window = self.model.cfg.window
        features = encode_episode(self.model.encoders, episode)
        windows = fixed_windows(episode.num_steps, window, episode_rng(self.seed, episode.episode_id))
        segments = []
        for lo in range(0, len(windows), 64):
            chunk = windows[lo : lo + 64]
            levels = [level.cpu() for level in self.model(*_padded(*window_rows(features, chunk), window))]
            for row, (start, end) in enumerate(chunk):
                found = top1_detection(levels, row, end - start, self.min_len)
                if found is not None:
                    segments.append(
                        Segment(
                            start + found.start,
                            start + found.end,
                            self.instructions[found.label],
                            found.score,
                        )
                    )
        return segments


# ----------------------------------------------------------------------------------------------------
# Checkpoints


def save_tridet(path: str | Path, model: TridetModel, meta: dict[str, Any]) -> Path:
    config = {
        "encoders": [spec.to_json() for spec in model.encoders.specs],
        "instructions": list(model.instructions),
        "model": asdict(model.cfg),
    }
    return save_checkpoint(path, Checkpoint(KIND, config, model.features, model.state_dict(), meta))


def load_tridet(path: str | Path) -> tuple[TridetModel, dict[str, Any]]:
    """-> (model in eval mode, meta); CheckpointError naming the file when it is not a valid TriDet model."""
    checkpoint = read_checkpoint(path, (KIND,))
    try:
        cfg = TridetConfig(**checkpoint.config["model"])
        specs = [EncoderSpec.from_json(spec) for spec in checkpoint.config["encoders"]]
        model = TridetModel(
            specs, checkpoint.features, [str(s) for s in checkpoint.config["instructions"]], cfg
        )
        model.load_state_dict(checkpoint.state_dict)
    except Exception as error:
        raise CheckpointError(f"checkpoint {path}: not a valid {KIND} model ({error!r})") from error
    return model.eval(), checkpoint.meta


def load_tridet_segmenter(path: str | Path, options: SegmentOptions) -> TridetSegmenter:
    model, _ = load_tridet(path)
    return TridetSegmenter(model, options)
