"""The networks of Play Segmentation: frame encoder, labelling model and PS model, in one file.

Shapes: a frame is (64, 64, 3) uint8; an episode has T+1 frames and T actions. Frames are encoded once
each (no temporal mixing in the encoder); everything temporal happens on the (T+1, d) feature sequence.

The PS trunk is causal in time *from the segment start*: for a window starting at step i, position p
(frame o_{i+p}) sees only o_i .. o_{i+p}, the start frame's features and the offset p. One pass over the
window therefore scores every candidate end j = i+p at once, and all T windows of an episode go through
the trunk as one batch (see `PSModel.end_logits`).

Step features: row t of the sequence the trunk reads is the frame features of o_t, followed (when the
model reads actions, ``ModelConfig.num_actions > 0``) by an embedding of a_{t-1}, the action that led to
o_t (row 0: a "no action" embedding). Frames alone often cannot tell a turn towards an object from a step
up to it, and in BabyAI play that decides whether facing an object ends a task (see
docs/segmentation.md "Reading the actions").
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn


@dataclass
class EncoderConfig:
    image_size: int = 64
    tile_size: int = 8  # BabyAI renders a grid of 8x8-pixel tiles: the first conv reads one tile
    tile_channels: int = 64
    object_dim: int = 32  # per-tile "what is here" embedding
    look_heads: int = 2  # attention maps over tiles ("the tile the agent faces", ...)
    feature_dim: int = 128


@dataclass
class TrunkConfig:
    hidden_dim: int = 64
    num_layers: int = 2
    kernel_size: int = 5
    max_len: int = 25  # L_max: the longest segment (in actions) the model can score


@dataclass
class ModelConfig:
    """Configuration of a PS model or a labelling model (same parts, different heads).

    num_actions: size of the discrete action space the model reads (BabyAI: 7); 0 = frames only.
    action_dim: size of the action embedding appended to each step's frame features.
    """

    encoder: EncoderConfig
    trunk: TrunkConfig
    num_classes: int = 36
    num_actions: int = 0
    action_dim: int = 16

    @staticmethod
    def from_dict(raw: dict) -> ModelConfig:
        return ModelConfig(
            encoder=EncoderConfig(**raw["encoder"]),
            trunk=TrunkConfig(**raw["trunk"]),
            num_classes=int(raw["num_classes"]),
            # Checkpoints written before actions were read have neither key: frames only.
            num_actions=int(raw.get("num_actions", 0)),
            action_dim=int(raw.get("action_dim", 16)),
        )

    @property
    def step_dim(self) -> int:
        """Width of a step feature row: frame features (+ action embedding)."""
        return self.encoder.feature_dim + (self.action_dim if self.num_actions else 0)


def previous_actions(actions: np.ndarray, num_actions: int, where: str = "actions") -> np.ndarray:
    """(T, 1) discrete action indices -> (T+1,) int64 index of a_{t-1} per observation o_t.

    Row 0 holds ``num_actions`` ("no action led here"). Raises ValueError naming `where` when an action
    is not a single integer in 0..num_actions-1.
    """
    actions = np.asarray(actions)
    if actions.ndim != 2 or actions.shape[1] != 1:
        raise ValueError(f"{where}: a model reading discrete actions needs shape (T, 1), got {actions.shape}")
    values = actions[:, 0]
    whole = np.isfinite(values) & (values == np.round(values))
    if not whole.all() or (values < 0).any() or (values >= num_actions).any():
        bad = int(np.flatnonzero(~whole | (values < 0) | (values >= num_actions))[0])
        raise ValueError(
            f"{where}[{bad}] = {float(values[bad])}: not a discrete action index in 0..{num_actions - 1}"
        )
    return np.concatenate([[num_actions], values.astype(np.int64)])


class FrameEncoder(nn.Module):
    """Per-frame CNN over the tile grid; translation-equivariant up to attention and sum pooling.

    The tile conv (kernel = stride = tile size) embeds each tile (object type and colour, the agent and
    its direction). Two per-tile maps come from it: `what` (the tile's content) and `look` (a 3x3 conv:
    "this tile is in front of the agent", from the neighbouring agent tile and its direction). Softmax
    attention of `look` over the tiles reads out the content of the faced tile; the product of that with
    the summed contents counts how many tiles hold the same thing (the article "the" vs "a"). Nothing
    depends on where things are, so the model cannot memorise room layouts, and "what is faced" is a
    product of where and what, so it holds for objects never faced in training.
    """

    def __init__(self, cfg: EncoderConfig) -> None:
        super().__init__()
        self.tile = nn.Conv2d(3, cfg.tile_channels, cfg.tile_size, stride=cfg.tile_size)
        self.tile_mix = nn.Conv2d(cfg.tile_channels, cfg.tile_channels, 1)
        self.what = nn.Conv2d(cfg.tile_channels, cfg.object_dim, 1)
        self.look = nn.Conv2d(cfg.tile_channels, cfg.look_heads, 3, padding=1)
        self.what_norm = nn.LayerNorm(cfg.object_dim)
        # Per head: how sharply "looks like the faced tile" falls off with the embedding distance.
        self.log_sharpness = nn.Parameter(torch.full((cfg.look_heads,), 2.0))
        faced_dim = cfg.look_heads * cfg.object_dim
        self.proj = nn.Sequential(
            nn.Linear(faced_dim + cfg.look_heads, cfg.feature_dim),
            nn.GELU(),
            nn.Linear(cfg.feature_dim, cfg.feature_dim),
        )

    def forward(self, frames: torch.Tensor) -> torch.Tensor:
        """(N, H, W, 3) uint8 -> (N, feature_dim)."""
        x = frames.permute(0, 3, 1, 2).float() / 255.0
        tiles = F.relu(self.tile_mix(F.relu(self.tile(x))))
        what = self.what_norm(self.what(tiles).flatten(2).transpose(1, 2))  # (N, tiles, object_dim)
        look = torch.softmax(self.look(tiles).flatten(2), dim=-1)  # (N, heads, tiles)
        faced = look @ what  # (N, heads, object_dim)
        # Identical tiles have identical embeddings: count the tiles that look like the faced one.
        distance = (what[:, None] - faced[:, :, None]).square().mean(-1)  # (N, heads, tiles)
        count = torch.exp(-distance * self.log_sharpness.exp()[:, None]).sum(-1)
        return self.proj(torch.cat([faced.flatten(1), count], dim=1))


class CausalConvBlock(nn.Module):
    """Pre-norm residual block: LayerNorm -> causal Conv1d over time -> GELU -> Linear (small init)."""

    def __init__(self, dim: int, kernel_size: int) -> None:
        super().__init__()
        self.norm = nn.LayerNorm(dim)
        self.conv = nn.Conv1d(dim, dim, kernel_size)
        self.out = nn.Linear(dim, dim)
        nn.init.normal_(self.out.weight, std=0.02)  # the residual stream starts as the frame content
        nn.init.zeros_(self.out.bias)
        self.pad = kernel_size - 1

    def forward(self, h: torch.Tensor) -> torch.Tensor:
        """(B, P, dim) -> (B, P, dim); output p depends on inputs <= p only."""
        x = self.norm(h).transpose(1, 2)
        x = self.conv(F.pad(x, (self.pad, 0)))  # left padding only: causal
        return h + self.out(F.gelu(x.transpose(1, 2)))


class StartCausalTrunk(nn.Module):
    """Windows of frame features -> per-position hidden states, causal from the window start.

    Every position also gets the start frame's features and its offset p from the start: "have I reached
    the goal, given where the segment started and how long it took" is the question both heads answer.
    A window starting the episode is flagged: its start frame is a reset, not the end of a previous
    segment, which the negatives teach the model to look for.
    """

    def __init__(self, step_dim: int, cfg: TrunkConfig) -> None:
        super().__init__()
        self.in_proj = nn.Linear(3 * step_dim, cfg.hidden_dim)
        self.in_norm = nn.LayerNorm(cfg.hidden_dim)
        self.offset = nn.Embedding(cfg.max_len + 1, cfg.hidden_dim)
        nn.init.normal_(self.offset.weight, std=0.02)
        self.episode_start = nn.Parameter(torch.zeros(cfg.hidden_dim))
        self.blocks = nn.ModuleList(
            CausalConvBlock(cfg.hidden_dim, cfg.kernel_size) for _ in range(cfg.num_layers)
        )
        self.memory_norm = nn.LayerNorm(cfg.hidden_dim)
        self.memory = nn.Linear(cfg.hidden_dim, cfg.hidden_dim)
        nn.init.normal_(self.memory.weight, std=0.02)
        nn.init.zeros_(self.memory.bias)
        self.norm = nn.LayerNorm(cfg.hidden_dim)

    def forward(self, windows: torch.Tensor, starts_episode: torch.Tensor | None = None) -> torch.Tensor:
        """(B, P, d) features of o_i .. o_{i+P-1}, P <= max_len + 1 -> (B, P, hidden).

        starts_episode: (B,) bool, True where i = 0.
        """
        num_pos = windows.shape[1]
        start = windows[:, :1].expand_as(windows)
        h = self.in_norm(self.in_proj(torch.cat([windows, start, windows - start], dim=-1)))
        h = h + self.offset.weight[:num_pos]
        if starts_episode is not None:
            h = h + starts_episode.to(h.dtype)[:, None, None] * self.episode_start
        for block in self.blocks:
            h = block(h)
        # A running max since the start: "did something happen earlier in this segment" (e.g. an end
        # already passed) is visible at every later position, beyond the convolutions' reach.
        h = h + torch.cummax(self.memory(self.memory_norm(h)), dim=1).values
        return self.norm(h)


def _class_names(instructions: list[str] | None, num_classes: int) -> list[str]:
    """The instruction string of each class (placeholders when none are given)."""
    names = [f"class {i}" for i in range(num_classes)] if instructions is None else list(instructions)
    if len(names) != num_classes:
        raise ValueError(f"{len(names)} instructions for a model with {num_classes} classes")
    return names


def episode_windows(features: torch.Tensor, window_len: int) -> torch.Tensor:
    """(T+1, d) -> (T, window_len, d): the window starting at every step, zero-padded past the end."""
    num_steps = features.shape[0] - 1
    padded = F.pad(features, (0, 0, 0, window_len - 1))
    return padded.unfold(0, window_len, 1)[:num_steps].transpose(1, 2)


class StepModel(nn.Module):
    """The parts PS and the labelling model share: frame encoder, action embedding, start-causal trunk."""

    def __init__(self, cfg: ModelConfig, instructions: list[str] | None = None) -> None:
        super().__init__()
        self.cfg = cfg
        self.instructions = _class_names(instructions, cfg.num_classes)
        self.encoder = FrameEncoder(cfg.encoder)
        # Index num_actions = "no action" (the first observation of an episode).
        self.action_embedding = None
        if cfg.num_actions:
            self.action_embedding = nn.Embedding(cfg.num_actions + 1, cfg.action_dim)
            # Small at first, as the offset embedding: with unit-scale action vectors the trunk leaned on
            # the actions from the start and the encoder learnt "what is faced" far more slowly.
            nn.init.normal_(self.action_embedding.weight, std=0.02)
        self.trunk = StartCausalTrunk(cfg.step_dim, cfg.trunk)

    @property
    def max_len(self) -> int:
        return self.cfg.trunk.max_len

    @property
    def reads_actions(self) -> bool:
        return self.action_embedding is not None

    def encode_frames(self, frames: torch.Tensor) -> torch.Tensor:
        """(N, 64, 64, 3) uint8 -> (N, feature_dim): the frame encoder alone."""
        return self.encoder(frames)

    def encode_steps(self, frames: torch.Tensor, prev_actions: torch.Tensor | None = None) -> torch.Tensor:
        """(N, 64, 64, 3) uint8 frames, (N,) index of the action that led to each -> (N, step_dim).

        prev_actions comes from `previous_actions` (index num_actions = none); a frames-only model
        ignores it. Encode an episode once and reuse the rows: each depends on its own step only.
        """
        features = self.encoder(frames)
        if self.action_embedding is None:
            return features
        if prev_actions is None:
            raise ValueError("this model reads actions: encode_steps needs prev_actions")
        if prev_actions.shape != (frames.shape[0],):
            raise ValueError(
                f"prev_actions must have shape ({frames.shape[0]},), got {tuple(prev_actions.shape)}"
            )
        return torch.cat([features, self.action_embedding(prev_actions.long())], dim=-1)

    def frame_part(self, features: torch.Tensor) -> torch.Tensor:
        """The frame-encoder columns of step features."""
        return features[..., : self.cfg.encoder.feature_dim]


class PSModel(StepModel):
    """Play Segmentation: p_seg(segment [i, j) ends at j | o_i..o_j) and p(label | o_i..o_j)."""

    def __init__(self, cfg: ModelConfig, instructions: list[str] | None = None) -> None:
        super().__init__(cfg, instructions)
        self.end_head = nn.Linear(cfg.trunk.hidden_dim, 1)
        self.label_head = nn.Linear(cfg.trunk.hidden_dim, cfg.num_classes)
        # Training only: the label from the end frame's features alone, an auxiliary loss that teaches
        # the encoder "what is faced" directly (the trunk's mixing slows that down a lot at first).
        self.frame_label_head = nn.Linear(cfg.encoder.feature_dim, cfg.num_classes)
        # Added to the end logit when segmenting, never in training: set after training to correct for
        # the positives' weight in the loss (calibration.py). Part of the state dict, so every path that
        # segments with this checkpoint (offline, streaming, nodes) cuts the same way.
        self.register_buffer("end_bias", torch.zeros(()))

    def end_logit(self, hidden: torch.Tensor) -> torch.Tensor:
        """(..., hidden) -> (...): logit that the segment ends at that position, end bias included."""
        return self.end_head(hidden).squeeze(-1) + self.end_bias

    def window_hidden(self, features: torch.Tensor) -> torch.Tensor:
        """(T+1, d) -> (T, L_max+1, hidden): trunk states of the window starting at every step."""
        starts_episode = torch.arange(features.shape[0] - 1) == 0
        return self.trunk(episode_windows(features, self.max_len + 1), starts_episode)

    def end_logits_from_hidden(self, hidden: torch.Tensor) -> torch.Tensor:
        """(T, L_max+1, hidden) -> (T, L_max); position 0 (an empty segment) is dropped."""
        return self.end_logit(hidden[:, 1:])

    def end_logits(self, features: torch.Tensor) -> torch.Tensor:
        """(T+1, d) -> (T, L_max): [i, k] = logit that the segment [i, i+k+1) ends at i+k+1.

        Entries with i+k+1 > T are computed on zero padding and must be ignored (decoding.py does).
        """
        return self.end_logits_from_hidden(self.window_hidden(features))

    def end_column(self, features_window: torch.Tensor, first_is_episode_start: bool) -> torch.Tensor:
        """Features of o_{t-n+1} .. o_t (n <= L_max+1 rows) -> (L_max,) for the online decoder.

        [k] = logit that the segment [t-k-1, t) ends at t (the diagonal end_logits[t-k-1, k]); starts
        before the window (k >= n-1) get -inf: such a segment cannot be scored from this window.
        first_is_episode_start: the window's first row is o_0.
        """
        n = features_window.shape[0]
        column = torch.full((self.max_len,), float("-inf"), dtype=features_window.dtype)
        if n < 2:
            return column
        # Window for start t-k-1 holds the last k+2 rows; right-pad with zeros (causal: no effect).
        lengths = torch.arange(2, n + 1)
        windows = torch.zeros(n - 1, n, features_window.shape[1], dtype=features_window.dtype)
        for row, length in enumerate(lengths.tolist()):
            windows[row, :length] = features_window[n - length :]
        starts_episode = (lengths == n) & first_is_episode_start
        hidden = self.trunk(windows, starts_episode)
        logits = self.end_logit(hidden[torch.arange(n - 1), lengths - 1])
        column[: n - 1] = logits
        return column

    def label_logits(self, features: torch.Tensor, start: int, end: int) -> torch.Tensor:
        """(T+1, step_dim) features, segment [start, end) -> (num_classes,) label logits at its end."""
        if not 0 < end - start <= self.max_len:
            raise ValueError(f"segment [{start}, {end}) must have 1..{self.max_len} steps")
        hidden = self.trunk(features[start : end + 1].unsqueeze(0), torch.tensor([start == 0]))
        return self.label_head(hidden[0, -1])


class LabelModel(StepModel):
    """Labelling model p_LM(instruction | o_i..o_j): encoder + start-causal trunk + mean/last pooling."""

    def __init__(self, cfg: ModelConfig, instructions: list[str] | None = None) -> None:
        super().__init__(cfg, instructions)
        self.head = nn.Linear(2 * cfg.trunk.hidden_dim, cfg.num_classes)
        # Training only, as PSModel's: without it the encoder never learnt "what is faced" through the
        # pooled trunk (val accuracy at chance, 0.04, after 16 epochs at the paper scale).
        self.frame_label_head = nn.Linear(cfg.encoder.feature_dim, cfg.num_classes)

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
            raise ValueError(f"segment [{start}, {end}) must have 1..{self.max_len} steps")
        window = features[start : end + 1].unsqueeze(0)
        return self.logits_from_windows(window, torch.tensor([end - start]), torch.tensor([start == 0]))[0]
