"""UnLoc-style action segmentation (the paper's adaptation of UnLoc, appendix "UnLoc").

Every step of a window is classified over the instructions plus a background class. For each class k,
its text embedding is appended to the window's step tokens as one more token and a small self-attention
encoder scores every step for k (c^k_t); a softmax over the classes' scores gives p(class | step). So
the cost grows with the number of instructions, as the paper says. The original reads CLIP frame and
text embeddings; here the steps come from our step encoders (trained with the model) and an instruction's
embedding is the mean of learnt word embeddings (a bag of words: instructions sharing words share parts).

Training windows: an annotated segment padded with 1..k background steps on each side (k = k_max of
the data). Segmenting: back-to-back windows of the training sizes (an annotated length plus the two
paddings, drawn at random), classified step by step; background is cropped from both ends and the rest
is kept only if it is one class and at least the minimum length (`crop_background`).
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
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
    freeze_pretrained_encoders,
    masked_cross_entropy,
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

KIND = "unloc"
BACKGROUND_WORD = "<background>"


@dataclass
class UnlocConfig:
    """Hyperparameters; ``length_counts`` (annotated length -> count) and ``pad_max`` (k) give the
    window sizes of training and segmenting."""

    dim: int = 64
    heads: int = 4
    layers: int = 2  # the paper's N for its short-segment data
    pad_max: int = 5
    min_len: int = 1
    closed_crop: bool = True  # keep only runs with background on both sides in the window (crop_background)
    length_counts: dict[int, int] | None = None

    @property
    def longest_window(self) -> int:
        return max(self.length_counts or {1: 1}) + 2 * self.pad_max


def _words(text: str) -> list[str]:
    return text.lower().split() or [text]


class UnlocModel(nn.Module):
    def __init__(
        self, encoders: list[EncoderSpec], features: Features, instructions: Sequence[str], cfg: UnlocConfig
    ) -> None:
        super().__init__()
        self.cfg = cfg
        self.features = features
        self.instructions = list(instructions)
        self.encoders = StepEncoders(encoders, features)
        self.step_proj = nn.Sequential(nn.Linear(2 * self.encoders.step_dim, cfg.dim), nn.LayerNorm(cfg.dim))
        self.position = nn.Embedding(cfg.longest_window + 1, cfg.dim)
        # Class texts: the instructions, then the background class (its own word).
        texts = [_words(text) for text in self.instructions] + [[BACKGROUND_WORD]]
        vocabulary = sorted({word for words in texts for word in words})
        index = {word: i for i, word in enumerate(vocabulary)}
        width = max(len(words) for words in texts)
        word_ids = torch.zeros(len(texts), width, dtype=torch.long)
        word_mask = torch.zeros(len(texts), width)
        for row, words in enumerate(texts):
            word_ids[row, : len(words)] = torch.tensor([index[w] for w in words])
            word_mask[row, : len(words)] = 1.0
        self.register_buffer("word_ids", word_ids)
        self.register_buffer("word_mask", word_mask)
        self.words = nn.Embedding(len(vocabulary), cfg.dim)
        self.text_type = nn.Parameter(torch.zeros(cfg.dim))  # marks the text token
        layer = nn.TransformerEncoderLayer(
            cfg.dim, cfg.heads, 2 * cfg.dim, dropout=0.0, batch_first=True, norm_first=True
        )
        self.attention = nn.TransformerEncoder(layer, cfg.layers, enable_nested_tensor=False)
        self.score = nn.Linear(cfg.dim, 1)

    @property
    def num_classes(self) -> int:
        """The instructions plus background (the last class)."""
        return len(self.instructions) + 1

    @property
    def background(self) -> int:
        return len(self.instructions)

    def class_embeddings(self) -> torch.Tensor:
        """(C+1, dim): mean word embedding of each class text."""
        words = self.words(self.word_ids) * self.word_mask[..., None]
        return words.sum(1) / self.word_mask.sum(1, keepdim=True) + self.text_type

    def step_logits(self, rows: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
        """(B, P, d) observation rows of windows, (B, P-1) valid steps -> (B, P-1, C+1) class scores."""
        steps = self.step_proj(transition_tokens(rows))
        batch, length, dim = steps.shape
        steps = steps + self.position.weight[:length]
        classes = self.class_embeddings()
        count = len(classes)
        # One sequence per (window, class): the window's steps followed by the class's text token.
        tokens = torch.cat(
            [
                steps[:, None].expand(batch, count, length, dim),
                classes[None, :, None].expand(batch, count, 1, dim),
            ],
            dim=2,
        ).reshape(batch * count, length + 1, dim)
        padding = torch.cat([~valid, torch.zeros(batch, 1, dtype=torch.bool, device=valid.device)], 1)
        padding = padding[:, None].expand(batch, count, length + 1).reshape(batch * count, length + 1)
        hidden = self.attention(tokens, src_key_padding_mask=padding)
        scores = self.score(hidden[:, :length]).reshape(batch, count, length)
        return scores.transpose(1, 2)


def crop_background(
    step_classes: Sequence[int], background: int, min_len: int, closed: bool = True
) -> tuple[int, int, int] | None:
    """The paper's cropping: drop background steps from both ends of a window's per-step classes; the
    rest (start, end, class) is kept only if it is one non-background class and has >= ``min_len``
    steps, else None. ``closed``: also None when the rest touches an end of the window (it may go on
    beyond the window: every training window has background on both sides of its segment)."""
    inside = [i for i, c in enumerate(step_classes) if c != background]
    if not inside:
        return None
    start, end = inside[0], inside[-1] + 1
    kept = set(step_classes[start:end])
    if len(kept) != 1 or end - start < min_len:
        return None
    if closed and (start == 0 or end == len(step_classes)):
        return None
    return start, end, int(step_classes[start])


# ----------------------------------------------------------------------------------------------------
# Training


def _training_window(
    episode: Episode, seg: Segment, pad_max: int, rng: np.random.Generator
) -> tuple[int, int]:
    """[seg.start - k1, seg.end + k2), k1 and k2 drawn from 1..pad_max (fewer at an episode's edges)."""
    left = min(int(rng.integers(1, pad_max + 1)), seg.start)
    right = min(int(rng.integers(1, pad_max + 1)), episode.num_steps - seg.end)
    return seg.start - left, seg.end + right


def train_unloc(
    data: TrainingData, options: TrainOptions, cfg: UnlocConfig | None = None
) -> TrainedSegmenter:
    """Train the UnLoc-style model on the annotated segments of ``data``."""
    from playseg_core.ps.training import segment_bounds

    began = time.perf_counter()
    torch.manual_seed(options.seed)
    train_eps = data.annotated()
    bounds = segment_bounds(train_eps, data.domain, **data.bounds)
    lengths = annotated_lengths(train_eps)
    values, counts = np.unique(lengths, return_counts=True)
    cfg = cfg or UnlocConfig()
    cfg.pad_max, cfg.min_len = bounds.k_max, bounds.min_len
    cfg.length_counts = {int(v): int(c) for v, c in zip(values, counts, strict=True)}
    specs, features = step_encoders_for(data)
    model = UnlocModel(specs, features, data.instructions, cfg)
    freeze_pretrained_encoders(model.encoders, data)
    fixed = FixedFeatureCache(model.encoders)
    classes = {text: i for i, text in enumerate(data.instructions)}
    items = {True: [(e, s) for e in train_eps for s in e.segments]}
    longest = max(cfg.length_counts)  # the position embeddings reach this far
    items[False] = [(e, s) for e in data.val for s in e.segments if s.length <= longest] or items[True]
    batch_size = options.batch_size or 32

    def choose(rng: np.random.Generator, training: bool) -> list[tuple[Episode, Segment, int, int]]:
        pool = items[training]
        chosen = [pool[i] for i in rng.integers(0, len(pool), size=batch_size)]
        return [(e, s, *_training_window(e, s, cfg.pad_max, rng)) for e, s in chosen]

    def build(windows: list[tuple[Episode, Segment, int, int]]) -> dict[str, Any]:
        batch_windows = window_inputs(
            model.encoders, [(e, start, end) for e, _, start, end in windows], fixed
        )
        target = torch.full(batch_windows.valid.shape, model.background, dtype=torch.long)
        for row, (_, seg, start, _) in enumerate(windows):
            target[row, seg.start - start : seg.end - start] = classes[seg.instruction]
        return {"windows": batch_windows, "target": target}

    def loss(trained: nn.Module, batch: dict[str, Any]) -> torch.Tensor:
        rows = encode_windows(trained.encoders, batch["windows"])
        valid = batch["windows"].valid
        return masked_cross_entropy(trained.step_logits(rows, valid), batch["target"], valid)

    steps = options.step_cap(len(items[True]), batch_size, default_steps=WINDOW_STEP_CAP)
    report = fit(model, WindowBatches(choose, build, loss), options, steps, options.lr or 1e-3, "unloc")
    meta = {"train": asdict(options), **report.meta(), "encoders_from": data.encoders_from}
    segmenter = UnlocSegmenter(model)

    def save(path: Path, extra: dict[str, Any]) -> Path:
        return save_unloc(path, model, {**meta, **extra})

    seconds = time.perf_counter() - began
    return TrainedSegmenter(segmenter, save, seconds, f"UnLoc-style model: {report.summary()}")


# ----------------------------------------------------------------------------------------------------
# Segmenting


class UnlocSegmenter(Segmenter):
    method = "unloc"
    tiles = False

    def __init__(self, model: UnlocModel, options: SegmentOptions | None = None) -> None:
        options = options or SegmentOptions()
        self.model = model.to(resolve_device(options.device)).eval()
        self.instructions = model.instructions
        self.features = model.features
        self.feature_names = [spec.feature for spec in model.encoders.specs]
        self.min_len = options.min_len or model.cfg.min_len
        self.seed = options.seed
        lengths = model.cfg.length_counts or {1: 1}
        self._lengths = np.array(list(lengths), np.int64)
        self._weights = np.array(list(lengths.values()), np.float64) / sum(lengths.values())

    def windows(self, num_steps: int, rng: np.random.Generator) -> list[tuple[int, int]]:
        """Back-to-back windows of training sizes (annotated length + 1..k + 1..k), from a random offset."""
        pad = self.model.cfg.pad_max

        def size() -> int:
            return int(rng.choice(self._lengths, p=self._weights) + rng.integers(1, pad + 1, size=2).sum())

        windows, start = [], int(rng.integers(0, size()))
        while start < num_steps:
            end = min(num_steps, start + size())
            windows.append((start, end))
            start = end
        if not windows and num_steps:
            windows = [(0, num_steps)]
        return windows

    @torch.no_grad()
    def segment(self, episode: Episode) -> list[Segment]:
        if episode.num_steps == 0:
            return []
        features = encode_episode(self.model.encoders, episode)
        windows = self.windows(episode.num_steps, episode_rng(self.seed, episode.episode_id))
        segments = []
        for lo in range(0, len(windows), 64):  # bounded memory on long episodes
            chunk = windows[lo : lo + 64]
            rows, valid = window_rows(features, chunk)
            probs = torch.softmax(self.model.step_logits(rows, valid).double(), dim=-1).cpu()
            for row, (start, end) in enumerate(chunk):
                window_probs = probs[row, : end - start]
                cropped = crop_background(
                    window_probs.argmax(-1).tolist(), self.model.background, self.min_len
                )
                if cropped is None:
                    continue
                first, last, label = cropped
                confidence = float(window_probs[first:last, label].mean())
                segments.append(Segment(start + first, start + last, self.instructions[label], confidence))
        return segments


# ----------------------------------------------------------------------------------------------------
# Checkpoints


def save_unloc(path: str | Path, model: UnlocModel, meta: dict[str, Any]) -> Path:
    config = {
        "encoders": [spec.to_json() for spec in model.encoders.specs],
        "instructions": list(model.instructions),
        "model": {
            **asdict(model.cfg),
            "length_counts": {str(k): v for k, v in model.cfg.length_counts.items()},
        },
    }
    return save_checkpoint(path, Checkpoint(KIND, config, model.features, model.state_dict(), meta))


def load_unloc(path: str | Path) -> tuple[UnlocModel, dict[str, Any]]:
    """-> (model in eval mode, meta); CheckpointError naming the file when it is not a valid UnLoc model."""
    checkpoint = read_checkpoint(path, (KIND,))
    try:
        raw = dict(checkpoint.config["model"])
        raw["length_counts"] = {int(k): int(v) for k, v in raw["length_counts"].items()}
        cfg = UnlocConfig(**raw)
        specs = [EncoderSpec.from_json(spec) for spec in checkpoint.config["encoders"]]
        model = UnlocModel(
            specs, checkpoint.features, [str(s) for s in checkpoint.config["instructions"]], cfg
        )
        model.load_state_dict(checkpoint.state_dict)
    except Exception as error:
        raise CheckpointError(f"checkpoint {path}: not a valid {KIND} model ({error!r})") from error
    return model.eval(), checkpoint.meta


def load_unloc_segmenter(path: str | Path, options: SegmentOptions) -> UnlocSegmenter:
    model, _ = load_unloc(path)
    return UnlocSegmenter(model, options)
