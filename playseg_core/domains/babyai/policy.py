"""The instruction-conditioned BabyAI policy: a FiLM network on the 8x8x3 symbolic state.

state (B, 8, 8, 3) uint8 ──> egocentric view (agent at the centre, facing up; optional)
                         ──> per-channel embeddings (object type, colour, state), summed per cell
                         ──> + relevance maps ──> conv stem ──> residual FiLM blocks ──> flatten ──> MLP
                                                                                  ──> 7 action logits
instruction (str)        ──> word ids ──> word embeddings ──> GRU ──> relevance queries, and FiLM
                                                                      gamma/beta for every block

The instruction encoder needs no download: the vocabulary is fixed and built from the BabyAI instruction
grammar ("go to the|a {colour} {type}" plus the words of the other BabyAI missions); words outside it map
to one shared unknown id. A GRU (not a mean) pools the words so that word order can matter for richer
missions; for GoToLocal the colour and type words alone identify the goal.

The egocentric view is the one inductive bias beyond the reference's network: left/right/forward are
relative to the agent, so re-expressing the grid in the agent's frame makes the same situation look the
same wherever the agent stands and whichever way it faces. It is a fixed re-indexing (no learning) and
generalises far better from few demonstrations (see docs/policy.md for the measured difference).

The relevance maps ground the instruction where it is cheapest to learn: each is the dot product of every
cell's embedding with a query vector computed from the instruction, so a map lights up the cells that
match what the instruction names, before any convolution. With FiLM alone the instruction acts only
through the trunk's channel statistics, and on large training sets some seeds settled on a loss plateau
that grounds it only in part (docs/augmentation.md measures both).

Checkpoints: playseg_core/checkpoint.py (kind "policy", policy name "babyai.film").
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

from playseg_core.checkpoint import Checkpoint, CheckpointError, read_checkpoint, save_checkpoint
from playseg_core.data.features import ACTION, STATE, Feature, Features
from playseg_core.domains.babyai.spec import NUM_ACTIONS

# Value ranges of the grid encoding channels (minigrid constants): 11 object types, 6 colours, and the
# state channel (door state 0..2, agent direction 0..3).
NUM_OBJECT_TYPES = 11
NUM_COLOURS = 6
NUM_CELL_STATES = 4
AGENT_TYPE = 10

PAD_WORD, UNKNOWN_WORD = "<pad>", "<unk>"
COLOUR_WORDS = ("red", "green", "blue", "purple", "yellow", "grey")
OBJECT_WORDS = ("box", "ball", "key", "door")
GRAMMAR_WORDS = (
    "go", "to", "the", "a", "pick", "up", "put", "next", "open", "and", "then", "after", "you",
    "in", "front", "of", "behind", "on", "your", "left", "right",
)  # fmt: skip
VOCABULARY: tuple[str, ...] = (PAD_WORD, UNKNOWN_WORD, *GRAMMAR_WORDS, *COLOUR_WORDS, *OBJECT_WORDS)
WORD_TO_ID = {word: index for index, word in enumerate(VOCABULARY)}


@dataclass
class PolicyConfig:
    grid_size: int = 8
    channels: int = 64  # width of the conv trunk
    cell_embedding: int = 32  # per-channel embedding size of one grid cell
    word_embedding: int = 32
    instruction_dim: int = 128  # GRU hidden size = instruction embedding
    num_film_blocks: int = 2
    head_hidden: int = 128
    num_actions: int = NUM_ACTIONS
    max_words: int = 16  # longer instructions are truncated
    egocentric: bool = True  # re-index the grid into the agent's frame before the convs
    view_size: int = 11  # egocentric window (odd); 11 sees the whole interior of an 8x8 room from anywhere
    relevance_maps: int = 4  # instruction-to-cell relevance maps beside the cell embeddings (0: FiLM only)


def tokenize(instruction: str, max_words: int = 16) -> list[int]:
    """Word ids of an instruction: lower-cased, split on non-letters, unknown words -> <unk>."""
    words = re.findall(r"[a-z]+", instruction.lower())[:max_words]
    ids = [WORD_TO_ID.get(word, WORD_TO_ID[UNKNOWN_WORD]) for word in words]
    return ids or [WORD_TO_ID[UNKNOWN_WORD]]  # an empty instruction still gets one token


def encode_instructions(instructions: list[str], max_words: int = 16) -> tuple[torch.Tensor, torch.Tensor]:
    """Pad a batch of instructions -> (word ids (B, W) int64, lengths (B,) int64)."""
    token_lists = [tokenize(text, max_words) for text in instructions]
    lengths = torch.tensor([len(tokens) for tokens in token_lists], dtype=torch.long)
    ids = torch.zeros(len(token_lists), int(lengths.max()), dtype=torch.long)
    for row, tokens in enumerate(token_lists):
        ids[row, : len(tokens)] = torch.tensor(tokens, dtype=torch.long)
    return ids, lengths


class InstructionEncoder(nn.Module):
    """Word embeddings + GRU; the hidden state after the last real word is the instruction embedding."""

    def __init__(self, config: PolicyConfig):
        super().__init__()
        self.words = nn.Embedding(len(VOCABULARY), config.word_embedding, padding_idx=0)
        self.gru = nn.GRU(config.word_embedding, config.instruction_dim, batch_first=True)

    def forward(self, word_ids: torch.Tensor, lengths: torch.Tensor) -> torch.Tensor:
        outputs, _ = self.gru(self.words(word_ids))  # (B, W, D)
        last = (lengths - 1).clamp(min=0).view(-1, 1, 1).expand(-1, 1, outputs.shape[-1])
        return outputs.gather(1, last).squeeze(1)


class FiLMBlock(nn.Module):
    """conv-BN-ReLU-conv-BN, then a per-channel affine map from the instruction, ReLU, residual add."""

    def __init__(self, channels: int, instruction_dim: int):
        super().__init__()
        self.conv1 = nn.Conv2d(channels, channels, 3, padding=1, bias=False)
        self.norm1 = nn.BatchNorm2d(channels)
        self.conv2 = nn.Conv2d(channels, channels, 3, padding=1, bias=False)
        self.norm2 = nn.BatchNorm2d(channels, affine=False)  # FiLM supplies the affine part
        self.film = nn.Linear(instruction_dim, 2 * channels)
        # Start as the identity modulation (gamma = 1, beta = 0) so early training is stable.
        nn.init.zeros_(self.film.weight)
        nn.init.zeros_(self.film.bias)

    def forward(self, x: torch.Tensor, instruction: torch.Tensor) -> torch.Tensor:
        h = F.relu(self.norm1(self.conv1(x)))
        h = self.norm2(self.conv2(h))
        gamma, beta = self.film(instruction).chunk(2, dim=-1)
        h = (1.0 + gamma[:, :, None, None]) * h + beta[:, :, None, None]
        return x + F.relu(h)


def egocentric_offsets(view_size: int) -> torch.Tensor:
    """World (dx, dy) of every egocentric view cell, per agent direction: (4, view, view, 2) int64.

    View row 0 is farthest ahead of the agent and column 0 farthest to its left; the agent is at the
    centre. Minigrid directions 0..3 point +x, +y, -x, -y; the agent's right is (-dy, dx).
    """
    half = view_size // 2
    ahead, lateral = torch.meshgrid(
        torch.arange(half, -half - 1, -1), torch.arange(-half, half + 1), indexing="ij"
    )
    offsets = torch.empty(4, view_size, view_size, 2, dtype=torch.long)
    for direction, (dx, dy) in enumerate(((1, 0), (0, 1), (-1, 0), (0, -1))):
        offsets[direction, ..., 0] = ahead * dx + lateral * -dy
        offsets[direction, ..., 1] = ahead * dy + lateral * dx
    return offsets


def to_egocentric(states: torch.Tensor, offsets: torch.Tensor) -> torch.Tensor:
    """(B, W, H, 3) grid encodings indexed [x, y] -> (B, V, V, 3) in the agent's frame; outside = 0."""
    batch, width, height, _ = states.shape
    cells = states.reshape(batch, width * height, 3)
    agent_cell = (cells[..., 0] == AGENT_TYPE).float().argmax(dim=1)  # row-major index x * H + y
    direction = cells[torch.arange(batch), agent_cell, 2].clamp(0, 3)
    view_offsets = offsets[direction]  # (B, V, V, 2)
    x = (agent_cell // height)[:, None, None] + view_offsets[..., 0]
    y = (agent_cell % height)[:, None, None] + view_offsets[..., 1]
    inside = (x >= 0) & (x < width) & (y >= 0) & (y < height)
    index = (x.clamp(0, width - 1) * height + y.clamp(0, height - 1)).reshape(batch, -1, 1)
    view = cells.gather(1, index.expand(-1, -1, 3)).reshape(*view_offsets.shape[:3], 3)
    return view * inside[..., None]


class PolicyNet(nn.Module):
    """pi(action | state, instruction) for BabyAI; ``forward`` returns action logits (B, num_actions)."""

    def __init__(self, config: PolicyConfig):
        super().__init__()
        self.config = config
        c = config.channels
        self.object_embedding = nn.Embedding(NUM_OBJECT_TYPES, config.cell_embedding)
        self.colour_embedding = nn.Embedding(NUM_COLOURS, config.cell_embedding)
        self.state_embedding = nn.Embedding(NUM_CELL_STATES, config.cell_embedding)
        self.relevance_queries = (
            nn.Linear(config.instruction_dim, config.relevance_maps * config.cell_embedding)
            if config.relevance_maps
            else None
        )
        self.stem = nn.Sequential(
            nn.Conv2d(config.cell_embedding + config.relevance_maps, c, 3, padding=1, bias=False),
            nn.BatchNorm2d(c),
            nn.ReLU(),
            nn.Conv2d(c, c, 3, padding=1, bias=False),
            nn.BatchNorm2d(c),
            nn.ReLU(),
        )
        self.register_buffer("view_offsets", egocentric_offsets(config.view_size), persistent=False)
        self.instruction_encoder = InstructionEncoder(config)
        self.blocks = nn.ModuleList(
            FiLMBlock(c, config.instruction_dim) for _ in range(config.num_film_blocks)
        )
        self.head = nn.Sequential(
            nn.Flatten(),
            nn.Linear(c * self.input_size**2, config.head_hidden),
            nn.ReLU(),
            nn.Linear(config.head_hidden, config.num_actions),
        )
        self.to(memory_format=torch.channels_last)  # the conv weights in the layout of the features

    @property
    def input_size(self) -> int:
        """Side of the square the convs see: the egocentric view or the grid itself."""
        return self.config.view_size if self.config.egocentric else self.config.grid_size

    def embed_cells(self, states: torch.Tensor) -> torch.Tensor:
        """(B, H, W, 3) integer grid encodings -> (B, H', W', cell_embedding) cell embeddings (H' = W' =
        ``input_size``)."""
        states = states.long()
        if self.config.egocentric:
            states = to_egocentric(states, self.view_offsets)
        object_type = states[..., 0].clamp(0, NUM_OBJECT_TYPES - 1)
        # The agent cell's colour is arbitrary across encoders (minigrid writes red); ignore it.
        colour = torch.where(object_type == AGENT_TYPE, 0, states[..., 1].clamp(0, NUM_COLOURS - 1))
        cell_state = states[..., 2].clamp(0, NUM_CELL_STATES - 1)
        cells = self.object_embedding(object_type) + self.colour_embedding(colour)
        return cells + self.state_embedding(cell_state)

    def relevance(self, cells: torch.Tensor, instruction: torch.Tensor) -> torch.Tensor:
        """(B, H, W, E) cell embeddings, (B, D) instruction embeddings -> (B, H, W, relevance_maps): how
        well each cell matches each of the instruction's query vectors (scaled dot products)."""
        batch, height, width, size = cells.shape
        queries = self.relevance_queries(instruction).view(batch, -1, size)  # (B, K, E)
        scores = torch.bmm(cells.reshape(batch, height * width, size), queries.transpose(1, 2))
        return scores.view(batch, height, width, -1) / math.sqrt(size)

    def forward(self, states: torch.Tensor, word_ids: torch.Tensor, lengths: torch.Tensor) -> torch.Tensor:
        instruction = self.instruction_encoder(word_ids, lengths)
        cells = self.embed_cells(states)
        if self.relevance_queries is not None:
            cells = torch.cat([cells, self.relevance(cells, instruction)], dim=-1)
        # channels-last: the (B, H, W, C) layout the cells already have; the CPU convolutions run
        # ~1.25x faster on it than on the default layout (measured, 32 channels, one thread)
        x = self.stem(cells.permute(0, 3, 1, 2).contiguous(memory_format=torch.channels_last))
        for block in self.blocks:
            x = block(x, instruction)
        return self.head(x)

    @torch.no_grad()
    def act(self, observations: Mapping[str, np.ndarray], instructions: Sequence[str]) -> np.ndarray:
        """Greedy actions (B,) int64 for a batch of observations (the uint8 grid states (B, 8, 8, 3) under
        ``observation.state``) and their instructions."""
        was_training = self.training
        self.eval()
        word_ids, lengths = encode_instructions(list(instructions), self.config.max_words)
        states = np.ascontiguousarray(observations[STATE])
        logits = self(torch.from_numpy(states), word_ids, lengths)
        self.train(was_training)
        return logits.argmax(dim=-1).numpy()


POLICY_NAME = "babyai.film"


def policy_features(config: PolicyConfig) -> Features:
    """What the policy reads: the grid state; what it outputs: the discrete action."""
    return Features.of(
        [
            Feature(STATE, "state", "uint8", (config.grid_size, config.grid_size, 3)),
            Feature(ACTION, "action", "float32", (1,), num_values=config.num_actions),
        ]
    )


def save_policy(path: str | Path, model: PolicyNet, meta: dict[str, Any]) -> None:
    """Write a policy checkpoint (playseg_core/checkpoint.py) that ``load_policy`` reads back."""
    config = {"policy": POLICY_NAME, **asdict(model.config), "vocabulary": list(VOCABULARY)}
    save_checkpoint(
        path, Checkpoint("policy", config, policy_features(model.config), model.state_dict(), meta)
    )


def load_policy(path: str | Path) -> tuple[PolicyNet, dict[str, Any]]:
    """Read a checkpoint written by ``save_policy`` -> (model in eval mode, meta).

    Raises CheckpointError (naming the file) on anything that is not such a checkpoint.
    """
    checkpoint = read_checkpoint(path, kinds=("policy",))
    raw = dict(checkpoint.config)
    if raw.pop("policy", None) != POLICY_NAME:
        raise CheckpointError(f"checkpoint {path}: not a {POLICY_NAME} policy")
    if list(raw.pop("vocabulary", [])) != list(VOCABULARY):
        raise CheckpointError(f"checkpoint {path}: policy written with another word vocabulary")
    raw.setdefault("relevance_maps", 0)  # written before the relevance maps existed: FiLM only
    known = {f.name for f in fields(PolicyConfig)}
    if not set(raw) <= known:
        raise CheckpointError(f"checkpoint {path}: unknown policy settings {sorted(set(raw) - known)}")
    model = PolicyNet(PolicyConfig(**raw))
    try:
        model.load_state_dict(checkpoint.state_dict, strict=True)
    except (RuntimeError, TypeError, AttributeError) as error:
        raise CheckpointError(
            f"checkpoint {path}: policy weights do not match its config: {error}"
        ) from error
    model.eval()
    return model, checkpoint.meta
