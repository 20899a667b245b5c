"""Imitation training of the BabyAI policy on (instruction, states, actions) segments.

Every sample is one random timestep t of one uniformly drawn segment, (state_t, instruction) -> action_t,
cross-entropy, Adam with a linear warm-up and a cosine decay of the learning rate (`learning_rate_at`),
trained through the training loop (training/loop.py: the device, its mixed precision, ``max_minutes``).
Seeded: the same seed and data give the same weights. (Evaluation: evaluation.py.)

Why the decay: at a constant rate the weights end wherever the last noisy minibatches left them.
Decaying to a small rate lets a run settle where it is. It does not decide where that is: without the
policy's relevance maps, some seeds on large sets stayed on a loss plateau either way (docs/augmentation.md).
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

from playseg_core.augment.policy import SequentialDraws, torch_threads
from playseg_core.domains.babyai.policy import (
    AGENT_TYPE,
    NUM_ACTIONS,
    PolicyConfig,
    PolicyNet,
    encode_instructions,
)
from playseg_core.errors import PlaysegError
from playseg_core.training.device import resolve_device
from playseg_core.training.loop import LoopConfig, TrainingTask, train_loop

# (instruction, states (L+1, 8, 8, 3) uint8, actions (L,) or (L, 1) discrete action indices)
Demonstration = tuple[str, np.ndarray, np.ndarray]


# ---------------------------------------------------------------------------------------------------------
# Training


@dataclass
class PolicyTrainConfig:
    steps: int = 2000  # the step cap (no held-out data, so no early stopping: all of them unless timed out)
    batch_size: int = 256
    learning_rate: float = 2e-3  # peak, after the warm-up
    warmup_steps: int = 50
    min_learning_rate: float = 1e-5  # reached at the last step (cosine decay); = learning_rate: constant
    weight_decay: float = 0.0
    grad_clip: float = 1.0
    seed: int = 0
    log_every: int = 100
    num_threads: int = 1  # torch CPU threads; more than the free cores makes a shared machine crawl
    mirror_augmentation: bool = True  # mirror half the samples (an exact symmetry of the task)
    max_minutes: float | None = None  # stop after this long (the schedule still spans `steps`)
    device: str = "auto"  # training/device.py: auto, cpu, cuda or cuda:N
    policy: PolicyConfig = field(default_factory=PolicyConfig)


@dataclass
class TrainStats:
    steps: int
    seconds: float
    num_segments: int
    num_samples: int  # (state, action) pairs available
    losses: list[tuple[int, float]]  # (step, mean loss over the preceding log interval)
    final_loss: float
    final_accuracy: float  # training-batch accuracy over the last log interval


@dataclass
class FlatSegments:
    """All segments' (state, action) pairs flattened; segment i owns rows offsets[i] : offsets[i] + lengths[i]."""

    states: torch.Tensor  # (N, H, W, 3) uint8
    actions: torch.Tensor  # (N,) int64
    offsets: np.ndarray  # (S,)
    lengths: np.ndarray  # (S,)
    instruction_index: np.ndarray  # (S,) index into the unique instructions
    word_ids: torch.Tensor  # (U, W) word ids of the unique instructions
    word_lengths: torch.Tensor  # (U,)


def flatten_segments(segments: Sequence[Demonstration], max_words: int = 16) -> FlatSegments:
    """Check and concatenate segments; the boundary state o_end is not a training input (no action)."""
    if not segments:
        raise PlaysegError("train_policy needs at least one segment")
    states, actions, lengths, instruction_index = [], [], [], []
    unique: dict[str, int] = {}
    for index, (instruction, segment_states, segment_actions) in enumerate(segments):
        segment_actions = np.asarray(segment_actions).reshape(-1)
        length = segment_actions.shape[0]
        if length < 1 or segment_states.shape[0] != length + 1 or segment_states.shape[-1] != 3:
            raise PlaysegError(
                f"segment {index}: need states (L+1, H, W, 3) and actions (L,) with L >= 1, "
                f"got {segment_states.shape} and {np.asarray(segment_actions).shape}"
            )
        action_ids = segment_actions.astype(np.int64)
        if not np.all((action_ids >= 0) & (action_ids < NUM_ACTIONS)) or np.any(
            action_ids != segment_actions
        ):
            raise PlaysegError(f"segment {index}: actions must be integers in [0, {NUM_ACTIONS})")
        states.append(np.asarray(segment_states[:length], dtype=np.uint8))
        actions.append(action_ids)
        lengths.append(length)
        instruction_index.append(unique.setdefault(instruction, len(unique)))
    lengths_array = np.array(lengths, dtype=np.int64)
    word_ids, word_lengths = encode_instructions(list(unique), max_words)
    return FlatSegments(
        states=torch.from_numpy(np.concatenate(states)),
        actions=torch.from_numpy(np.concatenate(actions)),
        offsets=np.concatenate([[0], np.cumsum(lengths_array)[:-1]]),
        lengths=lengths_array,
        instruction_index=np.array(instruction_index, dtype=np.int64),
        word_ids=word_ids,
        word_lengths=word_lengths,
    )


def mirror_samples(states: torch.Tensor, actions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Mirror the world along x: the agent's direction +x <-> -x and the turns left <-> right swap.

    GoToLocal is symmetric under this map, so a mirrored demonstration is a valid demonstration.
    """
    mirrored = states.flip(1).clone()
    is_agent = mirrored[..., 0] == AGENT_TYPE
    flipped_direction = ((2 - mirrored[..., 2].long()) % 4).to(mirrored.dtype)
    mirrored[..., 2] = torch.where(is_agent, flipped_direction, mirrored[..., 2])
    swapped = torch.where(actions == 0, 1, torch.where(actions == 1, 0, actions))
    return mirrored, swapped


def learning_rate_at(step: int, config: PolicyTrainConfig) -> float:
    """The learning rate of optimizer step ``step`` (1-based): linear warm-up to ``learning_rate`` over
    ``warmup_steps`` (at most an eighth of the run, so a short run still decays), then a cosine decay to
    ``min_learning_rate`` at step ``steps``."""
    warmup = min(config.warmup_steps, config.steps // 8)
    if step <= warmup:
        return config.learning_rate * step / max(1, warmup)
    progress = (step - warmup) / max(1, config.steps - warmup)
    cosine = 0.5 * (1.0 + math.cos(math.pi * min(1.0, progress)))
    return config.min_learning_rate + cosine * (config.learning_rate - config.min_learning_rate)


def train_policy(
    segments: Sequence[Demonstration], config: PolicyTrainConfig, progress: bool = True
) -> tuple[PolicyNet, TrainStats]:
    """Behaviour cloning on segments -> (model in eval mode, stats)."""
    with torch_threads(config.num_threads):
        return _train_policy(segments, config, progress)


@dataclass(frozen=True)
class _Batch:
    """One training step's samples: its number (1-based), states, instructions' words, target actions."""

    number: int
    states: torch.Tensor  # (B, H, W, 3) uint8
    word_ids: torch.Tensor  # (B, W)
    word_lengths: torch.Tensor  # (B,)
    targets: torch.Tensor  # (B,) int64


def _train_policy(
    segments: Sequence[Demonstration], config: PolicyTrainConfig, progress: bool
) -> tuple[PolicyNet, TrainStats]:
    device = resolve_device(config.device)
    data = flatten_segments(segments, config.policy.max_words)
    torch.manual_seed(config.seed)
    model = PolicyNet(config.policy)
    started = time.perf_counter()

    def draw(rng: np.random.Generator, step: int) -> _Batch:
        # One random timestep of one uniformly drawn segment per sample.
        segment = rng.integers(0, len(data.lengths), config.batch_size)
        timestep = (rng.random(config.batch_size) * data.lengths[segment]).astype(np.int64)
        rows = torch.from_numpy(data.offsets[segment] + timestep)
        instruction = torch.from_numpy(data.instruction_index[segment])
        states, targets = data.states[rows], data.actions[rows]
        if config.mirror_augmentation:
            mirror = torch.from_numpy(rng.random(config.batch_size) < 0.5)
            states[mirror], targets[mirror] = mirror_samples(states[mirror], targets[mirror])
        return _Batch(step + 1, states, data.word_ids[instruction], data.word_lengths[instruction], targets)

    def skip(rng: np.random.Generator, step: int) -> None:  # the draws of `draw`, without the batch
        rng.integers(0, len(data.lengths), config.batch_size)
        rng.random(config.batch_size)
        if config.mirror_augmentation:
            rng.random(config.batch_size)

    losses: list[tuple[int, float]] = []
    interval = [0.0, 0, 0]  # loss summed over samples, correct predictions, samples: since the last entry
    final_accuracy = float("nan")

    def loss(trained: nn.Module, batch: _Batch) -> tuple[torch.Tensor, dict[str, float]]:
        nonlocal final_accuracy
        logits = trained(batch.states, batch.word_ids, batch.word_lengths)
        value = F.cross_entropy(logits, batch.targets)
        mean = value.item()
        interval[0] += mean * len(batch.targets)
        interval[1] += int((logits.argmax(dim=-1) == batch.targets).sum())
        interval[2] += len(batch.targets)
        if batch.number % config.log_every == 0 or batch.number == config.steps:
            losses.append((batch.number, interval[0] / interval[2]))
            final_accuracy = interval[1] / interval[2]
            interval[:] = [0.0, 0, 0]
        return value, {"loss": mean}

    task = TrainingTask(
        name="policy",
        model=model,
        # a pure function of the step (exact when resumed), the same draws as a plain loop over one rng
        batch_at=SequentialDraws(config.seed, draw, skip),
        loss=loss,
        learning_rate=lambda step: learning_rate_at(step + 1, config),  # the loop counts from 0
        optimizer=lambda m: torch.optim.Adam(
            m.parameters(), lr=config.learning_rate, weight_decay=config.weight_decay
        ),
    )
    result = train_loop(
        task,
        LoopConfig(
            steps=config.steps,
            max_minutes=config.max_minutes,
            grad_clip=config.grad_clip,
            device=device,
            progress=progress,
        ),
    )
    if interval[2]:  # stopped by the clock between two entries
        losses.append((result.steps, interval[0] / interval[2]))
        final_accuracy = interval[1] / interval[2]
    model = result.model.to("cpu")  # checkpoints and `act` hold CPU weights
    model.eval()
    stats = TrainStats(
        steps=result.steps,
        seconds=time.perf_counter() - started,
        num_segments=len(data.lengths),
        num_samples=int(data.lengths.sum()),
        losses=losses,
        final_loss=losses[-1][1] if losses else float("nan"),
        final_accuracy=final_accuracy,
    )
    return model, stats
