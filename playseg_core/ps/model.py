"""The networks of Play Segmentation: the start-causal trunk, the PS model and the labelling model.

Step features: every observation o_t of an episode (T+1 of them) becomes one row of step features, the
concatenation of the model's step encoders (ps/encoders.py: cameras, the previous action a_{t-1}, ...),
each row encoded once (no temporal mixing), followed, where encoders measure positions of things, by an
embedding of the distances between them (`PairDistanceEmbedding`); everything temporal happens on the
(T+1, step_dim) sequence.

The PS trunk is causal in time *from the segment start*: for a window starting at step i, position p
(row o_{i+p}) sees only o_i .. o_{i+p}, the start row's features and the offset p. One pass over the
window therefore scores every candidate end j = i+p at once, and all T windows of an episode go through
the trunk as one batch (see `PSModel.end_logits`).
"""

from __future__ import annotations

import re
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from playseg_core.checkpoint import Checkpoint, CheckpointError, read_checkpoint, save_checkpoint
from playseg_core.data.episode import Episode
from playseg_core.data.features import Features
from playseg_core.errors import PlaysegError
from playseg_core.ps.encoders import EncoderSpec, StepEncoders, as_tensors
from playseg_core.training.device import to_device


@dataclass
class TrunkConfig:
    """The start-causal trunk. max_len (L_max) is the longest segment, in actions, the model can score."""

    hidden_dim: int = 64
    num_layers: int = 2
    kernel_size: int = 5
    max_len: int = 25
    # Periodic embeddings (`PeriodicEmbedding`) of the measured observation values, with this many learnt
    # frequencies per value; 0: none (what a checkpoint without the setting was trained with).
    periodic_frequencies: int = 0
    # Dropout on the trunk's input and on each block's residual branch while training; 0: none (what a
    # checkpoint without the setting was trained with).
    dropout: float = 0.0
    # Periodic embeddings of the distances between measured positions (`PairDistanceEmbedding`), with
    # this many learnt frequencies; 0: none (what a checkpoint without the setting was trained with).
    pair_frequencies: int = 0


PERIODIC_FREQUENCIES = 16
"""The learnt frequencies per measured value new PS and labelling models give the trunk's periodic
embeddings unless their domain chooses otherwise (`Domain.periodic_frequencies`)."""

TRUNK_DROPOUT = 0.2
"""The trunk's dropout in new PS and labelling models unless their domain chooses otherwise
(`Domain.trunk_dropout`): a few hundred annotated segments are otherwise learnt by heart within a few
hundred steps, the held-out end loss rising while the training loss falls to nothing."""


@dataclass
class ModelConfig:
    """Configuration of a PS model or a labelling model (same parts, different heads).

    encoders: the step encoders, in the order their outputs are concatenated (observations first).
    features: the data features the model reads, as the data declared them when it was trained: a
        dataset to segment or train on must declare the same (`check_features`). A checkpoint stores
        them once, as its ``features`` (playseg_core/checkpoint.py), not in ``to_json``.
    num_classes: the number of instructions.
    min_len: L_min, the shortest segment (in actions) segmenting cuts by default; L_max is the trunk's.
    label_head: how the label heads score an instruction (`LABEL_HEADS`): "linear" (one weight row per
        instruction) or "text" (from the instruction's words, shared between instructions).
    end_lookahead: steps past a candidate end the PS end head also reads (0: the paper's model, the end
        judged from o_i .. o_j alone). With 1 it reads o_{j+1} and (a model that reads actions) the
        action a_j that led to it, the first command after the end: where a demonstrator's intent
        changes, the command does.
        Segmenting a stream then decides each end one step later.
    """

    encoders: list[EncoderSpec]
    features: Features
    num_classes: int
    trunk: TrunkConfig = field(default_factory=TrunkConfig)
    min_len: int = 1
    label_head: str = "linear"
    end_lookahead: int = 0

    def __post_init__(self) -> None:
        if self.label_head not in LABEL_HEADS:
            raise PlaysegError(f"unknown label head {self.label_head!r} (known: {', '.join(LABEL_HEADS)})")
        if not 0 <= self.end_lookahead <= MAX_END_LOOKAHEAD:
            raise PlaysegError(f"end_lookahead must be in 0..{MAX_END_LOOKAHEAD}, got {self.end_lookahead}")

    def to_json(self) -> dict[str, Any]:
        return {
            "encoders": [spec.to_json() for spec in self.encoders],
            "trunk": asdict(self.trunk),
            "num_classes": self.num_classes,
            "min_len": self.min_len,
            "label_head": self.label_head,
            "end_lookahead": self.end_lookahead,
        }

    @staticmethod
    def from_json(raw: dict[str, Any], features: Features) -> ModelConfig:
        if raw.get("end_grounding"):  # an end head grounded on the label: a study's, not this model's
            raise PlaysegError(
                f"end_grounding {raw['end_grounding']}: a PS model whose end head is grounded on the label "
                "(a study's model, not part of PS: docs/studies/, the tabletop end-grounding study); train it "
                "again without"
            )
        return ModelConfig(
            encoders=[EncoderSpec.from_json(spec) for spec in raw["encoders"]],
            features=features,
            num_classes=int(raw["num_classes"]),
            trunk=TrunkConfig(**raw["trunk"]),
            min_len=int(raw.get("min_len", 1)),
            label_head=str(raw.get("label_head", "linear")),  # checkpoints before text heads: linear
            end_lookahead=int(raw.get("end_lookahead", 0)),  # checkpoints before it: the paper's 0
        )

    @property
    def feature_names(self) -> list[str]:
        """The features the step encoders read."""
        return [spec.feature for spec in self.encoders]

    def check_features(self, data: Features, what: str) -> None:
        """FeatureError naming the first feature this model reads that ``data`` lacks or declares otherwise."""
        self.features.check_compatible(data, self.feature_names, what)


MAX_END_LOOKAHEAD = 8
"""The most steps past an end the end head may read (a stream's ends are decided that much later)."""


class CausalConvBlock(nn.Module):
    """Pre-norm residual block: LayerNorm -> causal Conv1d over time -> GELU -> Linear (small init) ->
    dropout (training only)."""

    def __init__(self, dim: int, kernel_size: int, dropout: float = 0.0) -> None:
        super().__init__()
        self.dropout = nn.Dropout(dropout)
        self.norm = nn.LayerNorm(dim)
        self.conv = nn.Conv1d(dim, dim, kernel_size)
        self.out = nn.Linear(dim, dim)
        nn.init.normal_(self.out.weight, std=0.02)  # the residual stream starts as the frame content
        nn.init.zeros_(self.out.bias)
        self.pad = kernel_size - 1

    def forward(self, h: torch.Tensor) -> torch.Tensor:
        """(B, P, dim) -> (B, P, dim); output p depends on inputs <= p only."""
        x = F.pad(self.norm(h), (0, 0, self.pad, 0))  # zeros before the first position only: causal
        # The Conv1d as a 2-D convolution over a (B, dim, 1, P) channels-last view of the (B, P, dim) rows:
        # it reads and writes them in place, where transposing to (B, dim, P) and back copies them.
        x = F.conv2d(x.unsqueeze(1).permute(0, 3, 1, 2), self.conv.weight.unsqueeze(2), self.conv.bias)
        return h + self.dropout(self.out(F.gelu(x.permute(0, 2, 3, 1).squeeze(1))))


class PeriodicEmbedding(nn.Module):
    """sin and cos of 2 pi f v for learnt frequencies f of every value v of the given columns of the
    observation o_t and of its change o_t - o_start, projected to the trunk's width.

    For measured values (`StepEncoders.measured_columns`: positions found in a camera frame, a state read
    as it is), on which tasks end at thresholds: a thing has moved so far, or is inside a region. After
    one linear projection and a LayerNorm, a threshold that must fall between two consecutive steps is too
    soft to place; a bank of frequencies makes sharp functions of each value linear (the periodic
    embeddings of numerical features in tabular deep learning, Gorishniy et al. 2022).
    """

    SCALE = 1.0  # the frequencies' initial standard deviation, per unit of the features

    def __init__(self, columns: list[int], frequencies: int, out_dim: int) -> None:
        super().__init__()
        self.register_buffer("columns", torch.tensor(columns, dtype=torch.long), persistent=False)
        self.frequency = nn.Parameter(torch.randn(2 * len(columns), frequencies) * self.SCALE)
        self.proj = nn.Linear(2 * len(columns) * 2 * frequencies, out_dim)

    def forward(self, windows: torch.Tensor, start: torch.Tensor) -> torch.Tensor:
        """(B, P, d) rows of windows and (B, P, d) their start rows -> (B, P, out_dim)."""
        values = windows[..., self.columns]
        values = torch.cat([values, values - start[..., self.columns]], dim=-1)
        angles = (2 * torch.pi) * values.unsqueeze(-1) * self.frequency
        return self.proj(torch.cat([angles.sin(), angles.cos()], dim=-1).flatten(-2))


class PairDistanceEmbedding(nn.Module):
    """Step features of the distances between measured positions (things found in a camera frame): for
    every pair, sin and cos of learnt frequencies of their distance, embedded by one projection shared by
    all pairs plus a learnt vector of the pair, then the maximum over pairs.

    A task may end when two things come within some distance of each other: a value no single position
    holds, and a function of two that the trunk's linear projection of the positions cannot make sharp.
    Sharing the projection keeps the parameters few (a pair's own vector says which pairs matter), and
    the maximum reads "some pair is this close" whichever pair it is. One row each: the trunk reads them
    at the start and now, and their change, as every step feature.
    """

    def __init__(self, positions: list[tuple[int, int]], frequencies: int, out_dim: int) -> None:
        super().__init__()
        pairs = [(a, b) for a in range(len(positions)) for b in range(a + 1, len(positions))]
        self.register_buffer("positions", torch.tensor(positions, dtype=torch.long), persistent=False)
        self.register_buffer("pairs", torch.tensor(pairs, dtype=torch.long), persistent=False)
        self.frequency = nn.Parameter(torch.randn(frequencies) * PeriodicEmbedding.SCALE)
        self.embed = nn.Linear(2 * frequencies, out_dim)
        self.pair = nn.Parameter(torch.zeros(len(pairs), out_dim))
        self.out_dim = out_dim

    def distances(self, rows: torch.Tensor) -> torch.Tensor:
        """(N, d) step features -> (N, pairs) distances between the measured positions."""
        points = rows[:, self.positions]  # (N, things, 2)
        return (points[:, self.pairs[:, 0]] - points[:, self.pairs[:, 1]]).norm(dim=-1)

    def forward(self, rows: torch.Tensor) -> torch.Tensor:
        """(N, d) step features -> (N, out_dim)."""
        angles = (2 * torch.pi) * self.distances(rows).unsqueeze(-1) * self.frequency  # (N, pairs, F)
        embedded = self.embed(torch.cat([angles.sin(), angles.cos()], dim=-1)) + self.pair
        return F.gelu(embedded).amax(dim=1)


class StartCausalTrunk(nn.Module):
    """Windows of frame features -> per-position hidden states, causal from the window start.

    Every position also gets the start frame's features and its offset p from the start: "have I reached
    the goal, given where the segment started and how long it took" is the question both heads answer.
    A window starting the episode is flagged: its start frame is a reset, not the end of a previous
    segment, which the negatives teach the model to look for.
    """

    def __init__(
        self, step_dim: int, cfg: TrunkConfig, lookahead: int = 0, periodic_columns: list[int] | None = None
    ) -> None:
        super().__init__()
        self.in_proj = nn.Linear(3 * step_dim, cfg.hidden_dim)
        self.periodic = (
            PeriodicEmbedding(periodic_columns, cfg.periodic_frequencies, cfg.hidden_dim)
            if cfg.periodic_frequencies and periodic_columns
            else None
        )
        self.in_norm = nn.LayerNorm(cfg.hidden_dim)
        self.in_dropout = nn.Dropout(cfg.dropout)
        # Positions 0 .. max_len hold a segment; ``lookahead`` more, the steps its end head reads past it.
        self.offset = nn.Embedding(cfg.max_len + 1 + lookahead, cfg.hidden_dim)
        nn.init.normal_(self.offset.weight, std=0.02)
        self.episode_start = nn.Parameter(torch.zeros(cfg.hidden_dim))
        self.blocks = nn.ModuleList(
            CausalConvBlock(cfg.hidden_dim, cfg.kernel_size, cfg.dropout) for _ in range(cfg.num_layers)
        )
        self.memory_norm = nn.LayerNorm(cfg.hidden_dim)
        self.memory = nn.Linear(cfg.hidden_dim, cfg.hidden_dim)
        nn.init.normal_(self.memory.weight, std=0.02)
        nn.init.zeros_(self.memory.bias)
        self.norm = nn.LayerNorm(cfg.hidden_dim)

    def forward(self, windows: torch.Tensor, starts_episode: torch.Tensor | None = None) -> torch.Tensor:
        """(B, P, d) features of o_i .. o_{i+P-1}, P <= max_len + 1 + lookahead -> (B, P, hidden).

        starts_episode: (B,) bool, True where i = 0.
        """
        start = windows[:, :1].expand_as(windows)
        projected = self.in_proj(torch.cat([windows, start, windows - start], dim=-1))
        if self.periodic is not None:
            projected = projected + self.periodic(windows, start)
        return self._from_projection(projected, starts_episode)

    def forward_over_steps(
        self, features: torch.Tensor, num_windows: int, width: int, starts_episode: torch.Tensor
    ) -> torch.Tensor:
        """``forward`` of the windows of ``width`` rows starting at each of the first ``num_windows`` rows
        of ``features`` (N, d), zero-padded past its end, as `episode_windows` makes them -> (num_windows,
        width, hidden); equal up to float rounding.

        The input projection of [o, o_i, o - o_i] is linear, so it splits into a part of each step, computed
        once per step here instead of once per window holding it (``width`` times), and a part of each
        window's start: segmenting reads every step in up to L_max windows. Periodic embeddings do not
        split so: with them the windows are made and go through `forward`.
        """
        if self.periodic is not None:
            return self.forward(episode_windows(features, width)[:num_windows], starts_episode)
        dim = features.shape[-1]
        weight = self.in_proj.weight
        own, start, difference = weight[:, :dim], weight[:, dim : 2 * dim], weight[:, 2 * dim :]
        per_step = F.linear(features, own + difference)
        per_start = F.linear(features[:num_windows], start - difference, self.in_proj.bias)
        projected = episode_windows(per_step, width)[:num_windows] + per_start[:, None]
        return self._from_projection(projected, starts_episode)

    def _from_projection(self, projected: torch.Tensor, starts_episode: torch.Tensor | None) -> torch.Tensor:
        num_pos = projected.shape[1]
        h = self.in_dropout(self.in_norm(projected) + self.offset.weight[:num_pos])
        if starts_episode is not None:
            h = h + starts_episode.to(h.dtype)[:, None, None] * self.episode_start
        for block in self.blocks:
            h = block(h)
        # A running max since the start: "did something happen earlier in this segment" (e.g. an end
        # already passed) is visible at every later position, beyond the convolutions' reach.
        h = h + running_max(self.memory(self.memory_norm(h)))
        return self.norm(h)


def running_max(values: torch.Tensor) -> torch.Tensor:
    """(B, P, d) -> the maximum over positions 0..p at each p; exactly ``torch.cummax(values, 1).values``.
    Without gradients it takes log2(P) vectorised maxima over shifted copies, several times faster than
    cummax's sequential scan on the CPU (segmenting runs it on every window)."""
    if torch.is_grad_enabled():
        return torch.cummax(values, dim=1).values
    out = values.clone()
    shift = 1
    while shift < out.shape[1]:
        out[:, shift:] = torch.maximum(out[:, shift:], out[:, :-shift])
        shift *= 2
    return out


def _class_names(instructions: list[str] | None, num_classes: int) -> list[str]:
    """The instruction string of each class (placeholders when none are given)."""
    names = [f"class {i}" for i in range(num_classes)] if instructions is None else list(instructions)
    if len(names) != num_classes:
        raise PlaysegError(f"{len(names)} instructions for a model with {num_classes} classes")
    return names


_WORD = re.compile(r"[a-z0-9]+")


def instruction_words(instruction: str) -> list[str]:
    """The lower-cased alphanumeric words of an instruction, in order."""
    return _WORD.findall(instruction.lower())


def instruction_tokens(instruction: str) -> list[str]:
    """The words of an instruction, each word with its position (``"1:a"``) and each adjacent pair
    (``"a next"``): with order in them, "put a next to b" and "put b next to a" differ, where their bags
    of words are the same."""
    words = instruction_words(instruction)
    pairs = [f"{a} {b}" for a, b in zip(words, words[1:], strict=False)]
    return words + [f"{i}:{w}" for i, w in enumerate(words)] + pairs


def token_bags(token_lists: list[list[str]]) -> torch.Tensor:
    """(len(token_lists), vocabulary): each row the mean of its tokens' one-hots over the sorted vocabulary
    of all the lists' tokens (every list non-empty)."""
    vocabulary = {token: i for i, token in enumerate(sorted({t for ts in token_lists for t in ts}))}
    bags = torch.zeros(len(token_lists), len(vocabulary))
    for row, tokens in enumerate(token_lists):
        for token in tokens:
            bags[row, vocabulary[token]] += 1.0 / len(tokens)
    return bags


class TextLabelHead(nn.Module):
    """Scores every instruction from its words: logit = <query(hidden), mean of its tokens' embeddings> +
    a per-instruction bias.

    Tokens are `instruction_tokens`: the words, the words with their position and adjacent word pairs.
    Instructions sharing words share parameters: with many instructions and few annotated segments each
    (compositional instruction sets), one example of "open the small door" also teaches "small door"
    and "open", where a linear head learns each instruction from its own examples only.
    """

    def __init__(self, in_dim: int, instructions: list[str], dim: int = 64) -> None:
        super().__init__()
        # an instruction without words is its own word, at position 0 (as checkpoints have it)
        tokens = token_bags([instruction_tokens(text) or [text, f"0:{text}"] for text in instructions])
        self.register_buffer("tokens", tokens, persistent=False)  # rebuilt from the instructions
        self.token_embedding = nn.Parameter(torch.randn(tokens.shape[1], dim) * dim**-0.5)
        self.query = nn.Linear(in_dim, dim)
        self.bias = nn.Parameter(torch.zeros(len(instructions)))

    def forward(self, hidden: torch.Tensor) -> torch.Tensor:
        """(..., in_dim) -> (..., num_instructions) logits."""
        return self.query(hidden) @ (self.tokens @ self.token_embedding).T + self.bias


LABEL_HEADS = ("linear", "text")


def make_label_head(kind: str, in_dim: int, instructions: list[str]) -> nn.Module:
    """A label head of ``kind`` (`LABEL_HEADS`) over ``in_dim`` features for ``instructions``."""
    if kind == "text":
        return TextLabelHead(in_dim, instructions)
    return nn.Linear(in_dim, len(instructions))


FLOAT_BYTES = 4

ENCODE_INPUT_BYTES = 2 * 2**20
"""Camera frames per encoder pass when encoding an episode, in bytes as the encoders read them (float32):
the rows per pass follow from the frames' shapes (many small frames, few large ones), bounding the
encoders' activations. Small on purpose: on the CPU, passes of a couple of MB mostly reuse the memory the
previous pass freed, where passes of tens of MB faulted in fresh pages every time and ran at half the speed
(`benchmarks/bench_robot.py throughput`; docs/segmentation.md, "Long episodes")."""

SCORE_HIDDEN_BYTES = 2 * 2**20
"""Trunk hidden states per pass when scoring an episode (windows x positions x hidden_dim, float32): the
windows per pass follow from the window length and the trunk's width, so memory stays bounded on long
episodes, long windows and wide trunks (small on purpose, as `ENCODE_INPUT_BYTES`)."""


def episode_windows(features: torch.Tensor, window_len: int) -> torch.Tensor:
    """(T+1, d) -> (T, window_len, d): the window starting at every step, zero-padded past the end."""
    num_steps = features.shape[0] - 1
    padded = F.pad(features, (0, 0, 0, window_len - 1))
    return padded.unfold(0, window_len, 1)[:num_steps].transpose(1, 2)


class StepModel(nn.Module):
    """The parts PS and the labelling model share: step encoders and the start-causal trunk."""

    def __init__(self, cfg: ModelConfig, instructions: list[str] | None = None) -> None:
        super().__init__()
        self.cfg = cfg
        self.instructions = _class_names(instructions, cfg.num_classes)
        self.encoders = StepEncoders(cfg.encoders, cfg.features)
        positions = self.encoders.position_columns
        self.pair_distances = (
            PairDistanceEmbedding(positions, cfg.trunk.pair_frequencies, cfg.trunk.hidden_dim)
            if cfg.trunk.pair_frequencies and len(positions) > 1
            else None
        )
        self.trunk = StartCausalTrunk(
            self.step_dim, cfg.trunk, self.lookahead, self.encoders.measured_columns
        )

    @property
    def max_len(self) -> int:
        return self.cfg.trunk.max_len

    @property
    def step_dim(self) -> int:
        """Width of a step's features: the step encoders' outputs, then the distances' embedding."""
        return self.encoders.step_dim + (
            self.pair_distances.out_dim if self.pair_distances is not None else 0
        )

    @property
    def lookahead(self) -> int:
        """Steps past a segment's end that scoring the end reads (`ModelConfig.end_lookahead`; 0 for the
        labelling model, which labels given segments)."""
        return 0

    @property
    def reads_actions(self) -> bool:
        return self.encoders.reads_actions

    def encode_steps(
        self, inputs: dict[str, torch.Tensor], encoded: dict[str, torch.Tensor] | None = None
    ) -> torch.Tensor:
        """Input rows by feature (N rows each, see `StepEncoders.episode_inputs`) -> (N, step_dim);
        ``encoded``: features whose encoder output rows are given (`StepEncoders.forward`).

        Encode an episode once and reuse the rows: each depends on its own step only.
        """
        rows = self.encoders(inputs, encoded)
        if self.pair_distances is None:
            return rows
        return torch.cat([rows, self.pair_distances(rows)], dim=-1)

    @torch.no_grad()
    def encode_episode(self, episode: Episode, chunk: int | None = None) -> torch.Tensor:
        """(T+1, step_dim) step features of ``episode``, ``chunk`` rows at a time (default: the rows whose
        camera frames fill `ENCODE_INPUT_BYTES`)."""
        inputs = self.encoders.episode_inputs(episode)
        rows = episode.num_steps + 1
        if chunk is None:
            row_bytes = (
                sum(int(np.prod(inputs[name].shape[1:])) for name in self.encoders.cameras) * FLOAT_BYTES
            )
            chunk = max(1, ENCODE_INPUT_BYTES // max(1, row_bytes))
        return torch.cat(
            [
                self.encode_steps(to_device(as_tensors(inputs, slice(c, c + chunk)), self.device))
                for c in range(0, rows, chunk)
            ]
        )

    def score_chunk(self, window_len: int) -> int:
        """Windows of ``window_len`` positions per trunk pass: those whose hidden states (and periodic
        embeddings, which are wider) fill `SCORE_HIDDEN_BYTES`."""
        row = self.cfg.trunk.hidden_dim
        if self.trunk.periodic is not None:
            row += self.trunk.periodic.proj.in_features
        return max(1, SCORE_HIDDEN_BYTES // (window_len * row * FLOAT_BYTES))

    @property
    def device(self) -> torch.device:
        """Where the model's weights are (inputs are moved there)."""
        return next(self.parameters()).device

    def observation_part(self, features: torch.Tensor) -> torch.Tensor:
        """The observation encoders' columns of step features (without the previous action's)."""
        return features[..., : self.encoders.observation_dim]


class PSModel(StepModel):
    """Play Segmentation: p_seg(segment [i, j) ends at j | o_i..o_{j+lookahead}) and p(label | o_i..o_j)."""

    def __init__(self, cfg: ModelConfig, instructions: list[str] | None = None) -> None:
        super().__init__(cfg, instructions)
        # The end head reads the hidden state at the end and at each of the `lookahead` steps after it.
        self.end_head = nn.Linear(cfg.trunk.hidden_dim * (1 + self.lookahead), 1)
        self.label_head = make_label_head(cfg.label_head, cfg.trunk.hidden_dim, self.instructions)
        # Training only: the label from the end observation's encoding alone, an auxiliary loss that trains
        # the observation encoders directly (through the trunk's mixing they learn slowly at first).
        self.frame_label_head = make_label_head(
            cfg.label_head, self.encoders.observation_dim, self.instructions
        )
        # Added to the end logit when segmenting, never in training: set after training to correct for
        # the positives' weight in the loss (calibration.py). Part of the state dict, so every path that
        # segments with this checkpoint (offline, streaming, nodes) cuts the same way.
        self.register_buffer("end_bias", torch.zeros(()))

    @property
    def lookahead(self) -> int:
        return self.cfg.end_lookahead

    def raw_end_logits(self, hidden: torch.Tensor) -> torch.Tensor:
        """(B, P, hidden) trunk states of windows -> (B, P - lookahead): [b, p] = logit that the window's
        segment ends at position p, from positions p .. p + lookahead; without the end bias (training)."""
        num_pos = hidden.shape[1] - self.lookahead
        read = hidden
        if self.lookahead:
            read = torch.cat([hidden[:, k : k + num_pos] for k in range(self.lookahead + 1)], dim=-1)
        return self.end_head(read).squeeze(-1)

    def end_logits(self, features: torch.Tensor, chunk: int | None = None) -> torch.Tensor:
        """(T+1, d) -> (T, L_max): [i, k] = logit that the segment [i, i+k+1) ends at i+k+1, end bias
        included.

        The windows go through the trunk ``chunk`` starts at a time (default: `score_chunk`), so
        memory is bounded by the chunk, not the episode (an episode of 100,000 steps needs only its
        (T, L_max) logits). Entries with i+k+1 > T are computed on zero padding and must be ignored
        (decoding.py does); an end's lookahead past o_T reads the same zero padding as in training.
        """
        width = self.max_len + 1 + self.lookahead
        chunk = chunk or self.score_chunk(width)
        num_steps = features.shape[0] - 1
        parts = []
        for lo in range(0, num_steps, chunk):
            hi = min(num_steps, lo + chunk)
            # Rows lo .. hi + width - 1: every window starting in [lo, hi) lies inside (zero-padded at the end).
            rows = features[lo : hi + width]
            starts = torch.arange(lo, hi, device=features.device) == 0
            hidden = self.trunk.forward_over_steps(rows, hi - lo, width, starts)
            logits = self.raw_end_logits(hidden)
            parts.append(logits[:, 1:] + self.end_bias)  # position 0: empty segment
        return torch.cat(parts) if parts else features.new_zeros(0, self.max_len)

    def segment_label_logits(
        self, features: torch.Tensor, spans: list[tuple[int, int]], chunk: int | None = None
    ) -> torch.Tensor:
        """(T+1, d) features, segments [start, end) -> (len(spans), num_classes) label logits at their ends,
        ``chunk`` segments per trunk pass (each read from the window of its start, as `label_logits`)."""
        chunk = chunk or self.score_chunk(self.max_len + 1)
        rows = []
        for lo in range(0, len(spans), chunk):
            batch = spans[lo : lo + chunk]
            width = max(end - start for start, end in batch) + 1
            windows = features.new_zeros(len(batch), width, features.shape[1])
            for row, (start, end) in enumerate(batch):
                windows[row, : end - start + 1] = features[start : end + 1]
            device = features.device
            hidden = self.trunk(windows, torch.tensor([start == 0 for start, _ in batch], device=device))
            ends = torch.tensor([end - start for start, end in batch], device=device)
            rows.append(self.label_head(hidden[torch.arange(len(batch), device=device), ends]))
        return torch.cat(rows) if rows else features.new_zeros(0, self.cfg.num_classes)

    def end_column(self, features_window: torch.Tensor, starts_episode: bool) -> torch.Tensor:
        """Features of o_{t-n+1} .. o_t (n <= L_max+1+lookahead rows) -> (L_max,) for the online decoder.

        [k] = logit that the segment [e-k-1, e) ends at e = t - lookahead (the diagonal
        end_logits[e-k-1, k]); starts before the window (k >= n-lookahead-1) get -inf: such a segment
        cannot be scored from this window. starts_episode: the window's first row is o_0. Past an
        episode's last observation, pass zero rows as the lookahead (as `end_logits` pads).
        """
        n = features_window.shape[0] - self.lookahead  # rows o_{t-n+1} .. o_e
        device = features_window.device
        column = torch.full((self.max_len,), float("-inf"), dtype=features_window.dtype, device=device)
        if n < 2:
            return column
        # Window for start e-k-1 holds the last k+2+lookahead rows; right-pad with zeros (causal: no effect).
        lengths = torch.arange(2, n + 1, device=device)
        windows = torch.zeros(
            n - 1, n + self.lookahead, features_window.shape[1], dtype=features_window.dtype, device=device
        )
        for row, length in enumerate(lengths.tolist()):
            windows[row, : length + self.lookahead] = features_window[n - length :]
        starts_episode = (lengths == n) & starts_episode
        hidden = self.trunk(windows, starts_episode)
        logits = self.raw_end_logits(hidden)[torch.arange(n - 1, device=device), lengths - 1] + self.end_bias
        column[: n - 1] = logits
        return column

    def label_logits(self, features: torch.Tensor, start: int, end: int) -> torch.Tensor:
        """(T+1, step_dim) features, segment [start, end) -> (num_classes,) label logits at its end."""
        if not 0 < end - start <= self.max_len:
            raise PlaysegError(f"segment [{start}, {end}) must have 1..{self.max_len} steps")
        hidden = self.trunk(
            features[start : end + 1].unsqueeze(0), torch.tensor([start == 0], device=features.device)
        )
        return self.label_head(hidden[0, -1])


class LabelModel(StepModel):
    """Labelling model p_LM(instruction | o_i..o_j): step encoders + start-causal trunk + mean/last pooling."""

    def __init__(self, cfg: ModelConfig, instructions: list[str] | None = None) -> None:
        super().__init__(cfg, instructions)
        self.head = make_label_head(cfg.label_head, 2 * cfg.trunk.hidden_dim, self.instructions)
        # Training only, as PSModel's: through the pooled trunk alone the observation encoders learnt
        # far more slowly (docs/segmentation.md, "The labelling model").
        self.frame_label_head = make_label_head(
            cfg.label_head, self.encoders.observation_dim, self.instructions
        )

    def logits_from_windows(
        self, windows: torch.Tensor, lengths: torch.Tensor, starts_episode: torch.Tensor | None = None
    ) -> torch.Tensor:
        """(B, P, d) right-padded windows, (B,) segment lengths in actions -> (B, num_classes)."""
        hidden = self.trunk(windows, starts_episode)
        positions = torch.arange(windows.shape[1], device=windows.device)
        inside = (positions[None, :] <= lengths[:, None]).unsqueeze(-1).to(hidden.dtype)
        mean = (hidden * inside).sum(1) / inside.sum(1)
        last = hidden[torch.arange(windows.shape[0], device=windows.device), lengths]
        return self.head(torch.cat([mean, last], dim=-1))

    def label_logits(self, features: torch.Tensor, start: int, end: int) -> torch.Tensor:
        """(T+1, d) features, segment [start, end) -> (num_classes,)."""
        if not 0 < end - start <= self.max_len:
            raise PlaysegError(f"segment [{start}, {end}) must have 1..{self.max_len} steps")
        window = features[start : end + 1].unsqueeze(0)
        device = features.device
        lengths, starts = (
            torch.tensor([end - start], device=device),
            torch.tensor([start == 0], device=device),
        )
        return self.logits_from_windows(window, lengths, starts)[0]


# ----------------------------------------------------------------------------------------------------
# Checkpoints (the format is playseg_core/checkpoint.py)

_MODEL_KINDS: dict[str, type[StepModel]] = {"ps": PSModel, "labeller": LabelModel}


def save_model(path: str | Path, model: PSModel | LabelModel, meta: dict[str, Any] | None = None) -> Path:
    """Write a PS or labelling model's checkpoint: its configuration, instructions, weights and ``meta``."""
    kind = "ps" if isinstance(model, PSModel) else "labeller"
    config = {**model.cfg.to_json(), "instructions": list(model.instructions)}
    return save_checkpoint(path, Checkpoint(kind, config, model.cfg.features, model.state_dict(), meta or {}))


def load_model(
    path: str | Path, kinds: tuple[str, ...] = ("ps", "labeller")
) -> tuple[PSModel | LabelModel, dict]:
    """-> (model in eval mode with its .instructions, meta); CheckpointError naming the file if invalid."""
    checkpoint = read_checkpoint(path, kinds)
    try:
        cfg = ModelConfig.from_json(checkpoint.config, checkpoint.features)
        model = _MODEL_KINDS[checkpoint.kind](cfg, [str(s) for s in checkpoint.config["instructions"]])
        model.load_state_dict(checkpoint.state_dict)
    except Exception as error:
        raise CheckpointError(
            f"checkpoint {path}: not a valid {checkpoint.kind} model ({error!r})"
        ) from error
    model.eval()
    return model, checkpoint.meta
