"""A generic instruction-conditioned behaviour-cloning policy for any domain's data (policy name ``bc``).

pi(a_t | o_t, instruction): every camera of the data through ``image_cnn``, the state (when declared)
through ``state_mlp`` (ps/encoders.py, standardised with the training clips' statistics), the instruction
through a learned embedding per instruction string seen in training (``known_instructions``) plus a
hashed bag of words (so an unseen string still gets an embedding; no download), concatenated and mapped
by an MLP to the action: logits over ``num_values`` for a discrete action (cross-entropy); for a
continuous one either the standardised action (``action_head="regress"``, MSE; un-standardised when
acting) or, per dimension, logits over ``action_bins`` evenly spaced values between the declared bounds
(``"bins"``, cross-entropy; acting takes the most likely bin's value), clipped to the declared bounds
when acting. Bins keep apart the different ways a demonstrator does the same thing (round an obstacle on
the left or on the right), which a regression averages into a way nobody took. ``instruction_film`` lets
the instruction scale and shift the head's hidden units (FiLM). ``instruction_attention`` adds, for
every camera whose encoder gives entities (a convolution's cells, objects it found), where in the image
the instruction's things are (`InstructionAttention`). ``state_exclude`` names state dimensions the
policy does not read: a measured velocity, say, from which a policy learns to repeat the last command
instead of choosing it (the copycat problem of behaviour cloning). A domain may choose the step encoders
(as it does for PS).

`train` holds out a seeded share of the clips and reports the validation loss next to the loss of
predicting the training clips' mean action (the marginal action frequencies when discrete). It trains
through the training loop (training/loop.py): on ``device`` in its mixed precision, at most ``steps``
steps or ``max_minutes``, and by default evaluated once, after the last step; with ``eval_every`` and
``patience`` the held-out loss keeps the best weights and stops the run early. There is no
simulator: `evaluate` returns None. Checkpoints are playseg checkpoints of kind ``policy`` with config
``{"policy": "bc", ...}`` and the features the policy reads.
"""

from __future__ import annotations

import time
import zlib
from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

from playseg_core.augment.policy import PolicyTrainReport, SequentialDraws, torch_threads
from playseg_core.checkpoint import Checkpoint, CheckpointError, read_checkpoint, save_checkpoint
from playseg_core.data.episode import SegmentClip
from playseg_core.data.features import ACTION, STATE, FeatureError, Features, check_discrete_actions
from playseg_core.errors import PlaysegError
from playseg_core.ps.encoders import (
    EncoderSpec,
    StepEncoders,
    as_tensors,
    choose_encoders,
    feature_statistics,
)
from playseg_core.ps.model import instruction_tokens, instruction_words
from playseg_core.training.device import resolve_device
from playseg_core.training.loop import LoopConfig, TrainingTask, log_to_stderr, train_loop

POLICY_NAME = "bc"

SampleSymmetry = Callable[
    [dict[str, np.ndarray], list[str], np.ndarray, np.random.Generator],
    tuple[dict[str, np.ndarray], list[str], np.ndarray],
]


@dataclass(frozen=True)
class BCTrainConfig:
    """Settings of the ``bc`` policy and its training (all plain values: they go into the checkpoint)."""

    steps: int = 1000  # the step cap (what the run takes unless it stops early)
    batch_size: int = 64
    lr: float = 1e-3
    weight_decay: float = 0.0
    seed: int = 0
    hidden: int = 256  # width of the MLP head (the trainer node's ``channels``)
    instruction_dim: int = 32
    hash_buckets: int = 512  # bag-of-words buckets for the instruction
    instruction_dropout: float = 0.2  # share of training samples that see only the bag of words
    # a learned embedding per instruction string seen in training, beside the bag of words (False: the
    # words only, so what instructions share is all there is to learn from)
    known_instructions: bool = True
    # the words also with their positions and adjacent pairs (`instruction_tokens`): which thing is the
    # subject and which the object; False, as checkpoints written before it: a bag of words
    word_order: bool = False
    val_fraction: float = 0.1  # share of the clips held out for validation
    image_dim: int = 128
    state_dim: int = 64
    action_head: str = "regress"  # continuous actions: "regress" (MSE) or "bins" (classes per dimension)
    action_bins: int = 21
    instruction_film: bool = False
    # instruction queries over every camera's entities (0: none): where the instruction's things are
    instruction_attention: int = 0
    state_exclude: str = ""  # comma-separated names of state dimensions the policy does not read
    augment: bool = False  # training samples through the domain's symmetries (its `sample_symmetry`)
    # weight of a cross-entropy teaching the instruction's first attention query the entity that moves
    # most over the sample's segment (0: none): what an instruction names is usually what it moves, and
    # the action loss alone grounds the words slowly. Needs entities whose positions are found, not
    # learnt (a learnt position moves with the training); with `augment`, symmetries that keep each
    # entity's index (the target is read from the unturned clip).
    moved_entity_loss: float = 0.0
    # a segment whose most-moved entity moves less than this (image units: the frame spans [-1, 1])
    # moved nothing and teaches the query nothing
    moved_entity_threshold: float = 0.15
    # weight of the same for the second query (0: none): the entity the moved one ends nearest to, when
    # it came at least `moved_entity_threshold` nearer to it (what "put X next to / on Y" names second)
    related_entity_loss: float = 0.0
    log_every: int = 100
    num_threads: int = 1
    # The budget (training/loop.py): every `eval_every` steps (0: only after the last) the held-out loss
    # is computed and the best weights kept; the run stops when it has not improved for `patience`
    # evaluations (0: never early), at `steps`, or after `max_minutes`.
    eval_every: int = 0
    patience: int = 0
    max_minutes: float | None = None
    device: str = "auto"  # training/device.py: auto, cpu, cuda or cuda:N


def hashed_instruction_words(instruction: str, buckets: int, word_order: bool = False) -> list[int]:
    """The hashed bag of words of ``instruction``: its words (`instruction_words`), or with
    ``word_order`` its `instruction_tokens`, -> bucket ids (crc32, the same in every process)."""
    tokens = instruction_tokens(instruction) if word_order else instruction_words(instruction)
    return [zlib.crc32(token.encode()) % buckets for token in tokens]


def state_mask(features: Features, exclude: str) -> torch.Tensor | None:
    """1 for each state dimension the policy reads, 0 for those named in ``exclude`` (comma-separated
    `Feature.names`); None when nothing is excluded. ValueError naming an unknown dimension."""
    names = [name.strip() for name in exclude.split(",") if name.strip()]
    if not names:
        return None
    state = features.state
    known = list(state.names or ()) if state is not None else []
    unknown = [name for name in names if name not in known]
    if unknown:
        raise PlaysegError(
            f"policy {POLICY_NAME}: state_exclude names {unknown}, not dimensions of the state "
            f"(its names: {known or 'none declared'})"
        )
    return torch.tensor([0.0 if name in names else 1.0 for name in known])


class InstructionAttention(nn.Module):
    """Where the instruction's things are among a camera's entities (`encode_with_entities`), and what
    they are.

    Each of ``queries`` vectors made from the instruction weighs every entity by its dot product with the
    entity's features (a softmax over entities); the output is, per query, the weighted mean of the
    entities' image positions and of their features. Pooling the whole image first would mix the thing
    the instruction names with everything else in view, and an MLP after it would have to learn to tell
    them apart for every instruction separately; the positions say where to go directly.
    """

    def __init__(self, instruction_dim: int, entity_dim: int, queries: int) -> None:
        super().__init__()
        self.queries, self.entity_dim = queries, entity_dim
        self.query = nn.Linear(instruction_dim, queries * entity_dim)
        self.out_dim = queries * (2 + entity_dim)

    def attend(
        self, entities: torch.Tensor, positions: torch.Tensor, instruction: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """(N, E, C) entities at (N, E, 2) positions, (N, D) instruction -> (the output (N, queries *
        (2 + C)), each query's scores over the entities before the softmax (N, queries, E))."""
        batch, _, width = entities.shape
        queries = self.query(instruction).view(batch, self.queries, width)
        scores = queries @ entities.transpose(1, 2) / width**0.5
        weights = torch.softmax(scores, dim=-1)  # (N, Q, E)
        return torch.cat([weights @ positions, weights @ entities], dim=-1).flatten(1), scores

    def forward(
        self, entities: torch.Tensor, positions: torch.Tensor, instruction: torch.Tensor
    ) -> torch.Tensor:
        """(N, E, C) entities at (N, E, 2) positions, (N, D) instruction -> (N, queries * (2 + C))."""
        return self.attend(entities, positions, instruction)[0]


class BCPolicy(nn.Module):
    """The network; ``config`` (plain data) and ``features`` (what it reads) rebuild it from a checkpoint.

    config: ``policy`` ("bc"), ``settings`` (BCTrainConfig as a dict), ``encoders`` (EncoderSpec JSON),
    ``vocabulary`` (the known instruction strings), ``action_mean``/``action_std`` (continuous only).
    """

    def __init__(self, config: Mapping[str, Any], features: Features) -> None:
        super().__init__()
        self.config = dict(config)
        self.features = features
        settings = self.config["settings"]
        self.buckets = int(settings["hash_buckets"])
        self.word_order = bool(settings.get("word_order", False))
        dim = int(settings["instruction_dim"])
        hidden = int(settings["hidden"])
        self.encoders = StepEncoders(
            [EncoderSpec.from_json(raw) for raw in self.config["encoders"]], features
        )
        self.vocabulary = [str(s) for s in self.config["vocabulary"]]
        # 0: an unknown string; without known_instructions every string is read by its words only
        known = self.vocabulary if settings.get("known_instructions", True) else []
        self._index = {s: i + 1 for i, s in enumerate(known)}
        self.known = nn.Embedding(len(known) + 1, dim, padding_idx=0)
        self.words = nn.EmbeddingBag(self.buckets, dim, mode="mean")
        action = features.action
        self.discrete = action.is_discrete
        # Checkpoints written before the other heads existed regress.
        head = settings.get("action_head", "regress")
        self.bins = int(settings["action_bins"]) if head == "bins" else 0
        if self.discrete:
            out = action.num_values
        elif self.bins:
            out = self.bins * action.size
            self.register_buffer("action_low", torch.tensor(self.config["action_low"], dtype=torch.float32))
            self.register_buffer("action_high", torch.tensor(self.config["action_high"], dtype=torch.float32))
        else:
            out = action.size
        # FiLM: the instruction scales and shifts every hidden unit, so it can select which features of
        # the observation count (which object to go to) instead of only adding to them.
        self.film = nn.Linear(dim, 2 * hidden) if settings.get("instruction_film") else None
        queries = int(settings.get("instruction_attention", 0))
        self.attention = nn.ModuleDict(  # by the camera encoder's position (feature names hold dots)
            {
                str(index): InstructionAttention(dim, encoder.entity_dim, queries)
                for index, encoder in enumerate(self.encoders.encoders)
                if queries and getattr(encoder, "entity_dim", 0)
            }
        )
        if queries and not self.attention:
            raise PlaysegError(
                f"policy {POLICY_NAME}: instruction_attention needs a camera encoder that gives entities; "
                f"the encoders are {[spec.kind for spec in self.encoders.specs]}"
            )
        self.register_buffer("state_keep", state_mask(features, settings.get("state_exclude", "")), False)
        attended = sum(module.out_dim for module in self.attention.values())
        self.head = nn.Sequential(
            nn.Linear(self.encoders.step_dim + attended + dim, hidden),
            nn.GELU(),
            nn.Linear(hidden, hidden),
            nn.GELU(),
            nn.Linear(hidden, out),
        )
        if not self.discrete:
            mean, std = self.config["action_mean"], self.config["action_std"]
            self.register_buffer("action_mean", torch.tensor(mean, dtype=torch.float32))
            self.register_buffer("action_std", torch.tensor(std, dtype=torch.float32))

    @property
    def device(self) -> torch.device:
        """Where the weights are (training may run on a GPU; checkpoints and `act` hold CPU weights)."""
        return next(self.parameters()).device

    def instruction_ids(self, instructions: Sequence[str]) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(known-string ids (N,), flat word ids, bag offsets (N,)) of ``instructions``."""
        known = torch.tensor([self._index.get(s, 0) for s in instructions], dtype=torch.long)
        bags = [hashed_instruction_words(s, self.buckets, self.word_order) for s in instructions]
        flat = torch.tensor([w for bag in bags for w in bag], dtype=torch.long)
        offsets = torch.tensor(np.cumsum([0, *[len(bag) for bag in bags[:-1]]]), dtype=torch.long)
        return known, flat, offsets

    def forward(
        self,
        inputs: Mapping[str, torch.Tensor],
        known: torch.Tensor,
        words: torch.Tensor,
        offsets: torch.Tensor,
    ) -> torch.Tensor:
        """Observation rows by feature (N each) and instruction ids -> (N, out) logits or standardised
        actions."""
        return self.forward_with_attention(inputs, known, words, offsets)[0]

    def forward_with_attention(
        self,
        inputs: Mapping[str, torch.Tensor],
        known: torch.Tensor,
        words: torch.Tensor,
        offsets: torch.Tensor,
    ) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """`forward`'s output and, by attended camera (its encoder's index as text), the instruction
        queries' scores over the camera's entities (N, queries, E)."""
        instruction = self.known(known) + self.words(words, offsets)
        if self.state_keep is not None:
            inputs = {**inputs, STATE: inputs[STATE] * self.state_keep.view(self.features.state.shape)}
        scores: dict[str, torch.Tensor] = {}
        if self.attention:
            parts = []
            for index, (spec, encoder) in enumerate(
                zip(self.encoders.specs, self.encoders.encoders, strict=True)
            ):
                if str(index) in self.attention:
                    pooled, entities, positions = encoder.encode_with_entities(inputs[spec.feature])
                    attended, scores[str(index)] = self.attention[str(index)].attend(
                        entities, positions, instruction
                    )
                    parts += [pooled, attended]
                else:
                    parts.append(encoder(inputs[spec.feature]))
            observed = torch.cat(parts, dim=-1)
        else:
            observed = self.encoders(inputs)
        hidden = self.head[:2](torch.cat([observed, instruction], dim=-1))
        if self.film is not None:
            scale, shift = self.film(instruction).chunk(2, dim=-1)
            hidden = hidden * (1.0 + scale) + shift
        return self.head[2:](hidden), scores

    @torch.no_grad()
    def moved_entities(self, clips: Sequence[SegmentClip], threshold: float) -> dict[str, np.ndarray]:
        """By attended camera, for each clip (rows) the index of the entity that moves most between its
        first and last frame (column 0; -1 where none moves ``threshold`` image units or more) and of the
        entity that one ends nearest to (column 1; -1 unless it came ``threshold`` or more nearer).
        Read in eval mode (an encoder's dropout or batch statistics must not move the targets)."""
        was_training = self.training
        self.eval()
        try:
            return self._moved_entities(clips, threshold)
        finally:
            self.train(was_training)

    def _moved_entities(self, clips: Sequence[SegmentClip], threshold: float) -> dict[str, np.ndarray]:
        moved: dict[str, np.ndarray] = {}
        for index in self.attention:
            encoder = self.encoders.encoders[int(index)]
            feature = self.encoders.specs[int(index)].feature
            targets = np.full((len(clips), 2), -1, np.int64)
            for start in range(0, len(clips), 256):
                chunk = clips[start : start + 256]
                ends = np.stack([clip.images[feature][[0, -1]] for clip in chunk])  # (n, 2, *frame)
                frames = torch.from_numpy(ends.reshape(-1, *ends.shape[2:])).to(self.device)
                found = encoder.encode_with_entities(frames)
                positions = found[2].float().view(len(chunk), 2, *found[2].shape[1:])  # (n, first/last, E, 2)
                shift, entity = (positions[:, 1] - positions[:, 0]).norm(dim=-1).max(dim=-1)
                rows = torch.arange(len(chunk), device=positions.device)
                gaps = (positions - positions[rows, :, entity][:, :, None]).norm(dim=-1)  # (n, 2, E)
                gaps[rows, :, entity] = float("inf")
                gap, nearest = gaps[:, 1].min(dim=-1)
                came = gaps[rows, 0, nearest] - gap >= threshold
                moves = shift >= threshold
                targets[start : start + len(chunk), 0] = torch.where(moves, entity, -1).cpu().numpy()
                targets[start : start + len(chunk), 1] = torch.where(moves & came, nearest, -1).cpu().numpy()
            moved[index] = targets
        return moved

    def observation_inputs(
        self, observations: Mapping[str, np.ndarray], rows: int
    ) -> dict[str, torch.Tensor]:
        """The batch of observations as input tensors; FeatureError naming a missing or mis-shaped one."""
        return as_tensors(self.encoders.observation_inputs(observations, f"policy {POLICY_NAME}", rows))

    def action_bin(self, actions: torch.Tensor) -> torch.Tensor:
        """(N, D) actions -> (N, D) indices of their nearest bin centres."""
        share = (actions - self.action_low) / (self.action_high - self.action_low)
        return (share * (self.bins - 1)).round().long().clamp(0, self.bins - 1)

    def bin_centres(self, bins: torch.Tensor) -> torch.Tensor:
        """(N, D) bin indices -> (N, D) actions."""
        return self.action_low + bins.float() / (self.bins - 1) * (self.action_high - self.action_low)

    @torch.no_grad()
    def act(self, observations: Mapping[str, np.ndarray], instructions: Sequence[str]) -> np.ndarray:
        """Actions for a batch: (N,) int64 indices for a discrete action (the argmax), (N, *shape) float32
        for a continuous one (the prediction un-standardised, clipped to the declared bounds)."""
        instructions = list(instructions)
        was_training = self.training
        self.eval()
        try:
            out = self(
                self.observation_inputs(observations, len(instructions)), *self.instruction_ids(instructions)
            )
        finally:
            self.train(was_training)
        if self.discrete:
            return out.argmax(dim=-1).numpy()
        if self.bins:
            out = self.bin_centres(out.reshape(len(out), -1, self.bins).argmax(dim=-1))
        else:
            out = out * self.action_std + self.action_mean
        action = self.features.action
        values = out.numpy().astype(np.float32)
        if action.low is not None or action.high is not None:
            low = None if action.low is None else np.asarray(action.low, np.float32)
            high = None if action.high is None else np.asarray(action.high, np.float32)
            values = np.clip(values, low, high)
        return values.reshape(len(instructions), *action.shape)


_VALIDATION_FIGURES = (
    "val_loss",
    "val_accuracy",
    "baseline_val_loss",
    "val_moved_entity_accuracy",
    "val_related_entity_accuracy",
)
"""What `BCPolicyLearner._validate` gives: the report's held-out figures."""


@dataclass(frozen=True)
class _Batch:
    """One training step's samples: its number (1-based), (observations, instructions, actions), which
    samples see only the instruction's words, and per attended camera their moved-entity targets."""

    number: int
    samples: tuple[dict[str, np.ndarray], list[str], np.ndarray]
    drop: np.ndarray
    moved: dict[str, np.ndarray]


class _Steps:
    """Every (clip, step) of some clips, gathered into batches of observations, instructions, actions."""

    def __init__(self, clips: Sequence[SegmentClip], names: Sequence[str], discrete: int) -> None:
        self.clips = list(clips)
        self.names = list(names)
        self.pairs = np.array(
            [(c, t) for c, clip in enumerate(self.clips) for t in range(clip.segment.length)], np.int64
        ).reshape(-1, 2)
        actions = []
        for clip in self.clips:
            where = f"segment {clip.episode_id}[{clip.segment.start}, {clip.segment.end}) {ACTION}"
            a = np.asarray(clip.actions, np.float32).reshape(len(clip.actions), -1)
            actions.append(check_discrete_actions(a, discrete, where) if discrete else a)
        self.actions = np.concatenate(actions) if actions else np.zeros((0,))

    def __len__(self) -> int:
        return len(self.pairs)

    def batch(self, which: np.ndarray) -> tuple[dict[str, np.ndarray], list[str], np.ndarray]:
        pairs = self.pairs[which]
        observations = {}
        for name in self.names:
            rows = [
                (self.clips[c].state if name == STATE else self.clips[c].images[name])[t] for c, t in pairs
            ]
            observations[name] = np.stack(rows)
        instructions = [self.clips[c].segment.instruction for c, _ in pairs]
        return observations, instructions, self.actions[which]


def _setting(name: str, kind: type, value: Any) -> Any:
    """``value`` as the setting's type; a flag also from the words true/false (command lines give text);
    a setting that may be unset (``max_minutes``) a number, or None from None or the word none."""
    if kind is type(None):
        if value is None or (isinstance(value, str) and value.strip().lower() in ("", "none")):
            return None
        kind = float
    if kind is bool and isinstance(value, str):
        if value.lower() not in ("true", "false", "1", "0"):
            raise PlaysegError(f"policy {POLICY_NAME}: {name} must be true or false, got {value!r}")
        return value.lower() in ("true", "1")
    try:
        return kind(value)
    except (TypeError, ValueError):
        raise PlaysegError(
            f"policy {POLICY_NAME}: {name} must be of type {kind.__name__}, got {value!r}"
        ) from None


@dataclass
class BCPolicyLearner:
    """`augment.policy.PolicyLearner` of the ``bc`` policy for data with ``data_features``."""

    data_features: Features
    settings: BCTrainConfig = BCTrainConfig()
    name: str = POLICY_NAME
    # features -> step encoder per feature (a domain's choice, as ps/encoders.py `choose_encoders`
    # takes it); None: the generic encoders
    encoder_choice: Callable[[Features], dict[str, EncoderSpec | None]] | None = None
    # (observations, instructions, actions, rng) -> the same samples, each under a symmetry of the
    # domain's world drawn at random (`augment`); None: the data has none declared
    sample_symmetry: SampleSymmetry | None = None

    @classmethod
    def from_config(
        cls,
        config: Mapping[str, Any],
        features: Features | None,
        encoder_choice: Callable[[Features], dict[str, EncoderSpec | None]] | None = None,
        sample_symmetry: SampleSymmetry | None = None,
    ) -> BCPolicyLearner:
        """From plain settings (any field of BCTrainConfig; ``channels`` is ``hidden``; ``eval_max_steps``
        is accepted and unused: there is no simulator), the data's features, and from a domain its choice
        of step encoders (None: the generic ones) and its symmetries (for ``augment``); ValueError naming
        an unknown or bad setting, FeatureError when the features are missing or hold nothing to read."""
        config = dict(config)
        if "channels" in config:
            config["hidden"] = config.pop("channels")
        config.pop("eval_max_steps", None)
        known = {f.name for f in fields(BCTrainConfig)}
        unknown = sorted(set(config) - known)
        if unknown:
            raise PlaysegError(f"policy {POLICY_NAME}: unknown settings {unknown} (known: {sorted(known)})")
        types = {f.name: type(getattr(BCTrainConfig(), f.name)) for f in fields(BCTrainConfig)}
        settings = BCTrainConfig(**{k: _setting(k, types[k], v) for k, v in config.items()})
        if settings.steps <= 0 or settings.batch_size <= 0 or not 0.0 <= settings.val_fraction < 1.0:
            raise PlaysegError(
                f"policy {POLICY_NAME}: steps and batch_size must be > 0, val_fraction in [0, 1)"
            )
        if (
            min(settings.eval_every, settings.patience) < 0
            or settings.log_every <= 0
            or (settings.max_minutes is not None and not settings.max_minutes > 0)
        ):
            raise PlaysegError(
                f"policy {POLICY_NAME}: eval_every and patience must be >= 0, log_every > 0 and "
                f"max_minutes > 0 (or unset), got {settings.eval_every}, {settings.patience}, "
                f"{settings.log_every} and {settings.max_minutes}"
            )
        if settings.action_head not in ("regress", "bins") or settings.action_bins < 2:
            raise PlaysegError(
                f"policy {POLICY_NAME}: action_head must be 'regress' or 'bins' and action_bins >= 2, got "
                f"{settings.action_head!r} and {settings.action_bins}"
            )
        if features is None:
            raise FeatureError(f"policy {POLICY_NAME} needs the data's declared features (none were given)")
        if settings.action_head != "regress" and features.action.is_discrete:
            raise PlaysegError(
                f"policy {POLICY_NAME}: action_head {settings.action_head!r} needs a continuous action; "
                f"{features.action.name!r} is discrete"
            )
        if settings.instruction_attention < 0:
            raise PlaysegError(
                f"policy {POLICY_NAME}: instruction_attention must be >= 0, got {settings.instruction_attention}"
            )
        if (
            min(settings.moved_entity_loss, settings.related_entity_loss) < 0
            or settings.moved_entity_threshold <= 0
        ):
            raise PlaysegError(
                f"policy {POLICY_NAME}: moved_entity_loss and related_entity_loss must be >= 0 and "
                f"moved_entity_threshold > 0, got {settings.moved_entity_loss}, "
                f"{settings.related_entity_loss} and {settings.moved_entity_threshold}"
            )
        if settings.moved_entity_loss and not settings.instruction_attention:
            raise PlaysegError(
                f"policy {POLICY_NAME}: moved_entity_loss teaches the instruction's attention, which "
                "instruction_attention=0 turns off"
            )
        if settings.related_entity_loss and settings.instruction_attention < 2:
            raise PlaysegError(
                f"policy {POLICY_NAME}: related_entity_loss teaches the instruction's second query; "
                f"instruction_attention is {settings.instruction_attention}"
            )
        state_mask(features, settings.state_exclude)  # ValueError naming an unknown dimension
        if settings.augment and sample_symmetry is None:
            raise PlaysegError(
                f"policy {POLICY_NAME}: augment needs the symmetries of the data's world, which only a "
                "domain's policy declares"
            )
        return cls(features, settings, encoder_choice=encoder_choice, sample_symmetry=sample_symmetry)

    @property
    def features(self) -> Features:
        """The cameras, the state when declared, and the action."""
        names = [
            *self.data_features.cameras,
            *([STATE] if self.data_features.state is not None else []),
            ACTION,
        ]
        if names == [ACTION]:
            raise FeatureError(f"policy {POLICY_NAME}: the data has no camera and no state to read")
        return Features.of([self.data_features[n] for n in names], self.data_features.fps)

    def _split(self, clips: Sequence[SegmentClip]) -> tuple[list[SegmentClip], list[SegmentClip]]:
        """(training, validation) clips: a seeded ``val_fraction`` of them held out (none of fewer than 2)."""
        order = np.random.default_rng(self.settings.seed).permutation(len(clips))
        held = int(round(self.settings.val_fraction * len(clips)))
        held = min(max(held, 1 if self.settings.val_fraction > 0 else 0), len(clips) - 1)
        return [clips[i] for i in sorted(order[held:])], [clips[i] for i in sorted(order[:held])]

    def build(self, clips: Sequence[SegmentClip]) -> BCPolicy:
        """A fresh network for ``clips``: statistics, known instructions and encoders from them."""
        features = self.features
        action = features.action
        episodes = [clip.as_episode(f"clip{i}") for i, clip in enumerate(clips)]
        names = ([STATE] if features.state is not None else []) + ([] if action.is_discrete else [ACTION])
        statistics = feature_statistics(episodes, names)
        specs = choose_encoders(features, self.encoder_choice, statistics, read_actions=False)
        dims = {"image_cnn": self.settings.image_dim, "state_mlp": self.settings.state_dim}
        for spec in specs:
            if spec.kind in dims:  # a domain's own encoder keeps its own settings
                spec.config["dim"] = dims[spec.kind]
        config: dict[str, Any] = {
            "policy": POLICY_NAME,
            "settings": asdict(self.settings),
            "encoders": [spec.to_json() for spec in specs],
            "vocabulary": sorted({clip.segment.instruction for clip in clips}),
        }
        if not action.is_discrete:
            config["action_mean"] = statistics[ACTION]["mean"]
            config["action_std"] = statistics[ACTION]["std"]
        if self.settings.action_head == "bins":  # the declared bounds, else the clips' own range
            seen = np.concatenate(
                [np.asarray(c.actions, np.float32).reshape(len(c.actions), -1) for c in clips]
            )
            low = np.broadcast_to(action.low if action.low is not None else seen.min(0), (action.size,))
            high = np.broadcast_to(action.high if action.high is not None else seen.max(0), (action.size,))
            config["action_low"] = [float(v) for v in low]
            config["action_high"] = [float(v) for v in np.maximum(high, low + 1e-6)]
        return BCPolicy(config, features)

    def _loss(
        self,
        model: BCPolicy,
        batch: tuple[dict[str, np.ndarray], list[str], np.ndarray],
        drop: np.ndarray | None,
        moved: Mapping[str, np.ndarray] | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, list[torch.Tensor]]:
        """(mean action loss, per-sample correct flags or nothing, the moved- and related-entity losses
        weighted and summed (0 without ``moved``: by attended camera, each sample's
        `BCPolicy.moved_entities` targets), per query the flags of its best-scored entity being its
        target (samples that have one)) of one batch, on the model's device."""
        observations, instructions, actions = batch
        device = model.device

        def tensor(array: np.ndarray) -> torch.Tensor:
            return torch.from_numpy(array).to(device)

        known, words, offsets = model.instruction_ids(instructions)
        if drop is not None:
            known = known.masked_fill(torch.from_numpy(drop), 0)
        known, words, offsets = known.to(device), words.to(device), offsets.to(device)
        inputs = {name: tensor(array) for name, array in observations.items()}
        out, scores = model.forward_with_attention(inputs, known, words, offsets)
        weights = (self.settings.moved_entity_loss, self.settings.related_entity_loss)
        moved_loss, moved_hits = out.new_zeros(()), [out.new_zeros(0), out.new_zeros(0)]
        for index, targets in (moved or {}).items():
            for query, weight in enumerate(weights[: scores[index].shape[1]]):
                target = tensor(targets[:, query])
                has = target >= 0
                if weight and has.any():
                    chosen = scores[index][:, query][has]
                    moved_loss = moved_loss + weight * F.cross_entropy(chosen, target[has])
                    hits = (chosen.argmax(-1) == target[has]).float()
                    moved_hits[query] = torch.cat([moved_hits[query], hits])
        if model.discrete:
            target = tensor(actions)
            loss, hits = F.cross_entropy(out, target), (out.argmax(-1) == target).float()
        elif model.bins:
            target = model.action_bin(tensor(actions))
            logits = out.reshape(len(out), -1, model.bins)
            loss = F.cross_entropy(logits.transpose(1, 2), target)
            hits = (logits.argmax(-1) == target).float().mean(-1)
        else:
            target = (tensor(actions) - model.action_mean) / model.action_std
            loss, hits = F.mse_loss(out, target), out.new_zeros(0)
        return loss, hits, moved_loss, moved_hits

    def _validate(
        self, model: BCPolicy, steps: _Steps, train: _Steps, moved: Mapping[str, np.ndarray] | None
    ) -> dict[str, float]:
        """Validation loss (and accuracy), the loss of the mean-action (marginal) predictor, and with
        ``moved`` (per clip) how often each taught query scores its target best (over held-out samples,
        i.e. steps, whose segment has one)."""
        model.eval()
        total, correct, found, targeted = 0.0, 0.0, np.zeros(2), np.zeros(2)
        with torch.no_grad():
            for start in range(0, len(steps), 1024):
                which = np.arange(start, min(start + 1024, len(steps)))
                per_sample = {k: v[steps.pairs[which, 0]] for k, v in (moved or {}).items()}
                loss, hits, _, moved_hits = self._loss(model, steps.batch(which), None, per_sample)
                total += float(loss) * len(which)
                correct += float(hits.sum())
                found += [float(hits.sum()) for hits in moved_hits]
                targeted += [len(hits) for hits in moved_hits]
        model.train()
        result = {"val_loss": total / len(steps)}
        if targeted[0]:
            result["val_moved_entity_accuracy"] = float(found[0] / targeted[0])
        if targeted[1]:
            result["val_related_entity_accuracy"] = float(found[1] / targeted[1])
        if model.bins:  # per dimension: the marginal bin frequencies of the training actions
            result["val_accuracy"] = correct / len(steps)
            bins = [
                model.action_bin(torch.from_numpy(s.actions).to(model.device)).cpu().numpy()
                for s in (train, steps)
            ]
            log_p = [
                np.log(np.bincount(bins[0][:, d], minlength=model.bins) + 1.0)
                - np.log(len(bins[0]) + model.bins)
                for d in range(bins[0].shape[1])
            ]
            result["baseline_val_loss"] = float(
                -np.mean([log_p[d][bins[1][:, d]].mean() for d in range(len(log_p))])
            )
        elif model.discrete:
            num_values = model.features.action.num_values
            counts = np.bincount(train.actions, minlength=num_values) + 1.0  # add-one: no log(0)
            log_p = np.log(counts / counts.sum())
            result["val_accuracy"] = correct / len(steps)
            result["baseline_val_loss"] = float(-log_p[steps.actions].mean())
        else:
            z = (steps.actions - model.action_mean.cpu().numpy()) / model.action_std.cpu().numpy()
            result["baseline_val_loss"] = float(np.square(z).mean())
        return result

    def train(
        self, clips: Sequence[SegmentClip], progress: bool = False
    ) -> tuple[BCPolicy, PolicyTrainReport]:
        """Train a fresh policy on ``clips`` through the training loop (training/loop.py): AdamW at the
        constant ``lr``, gradients clipped to norm 1, at most ``steps`` steps; the held-out clips' figures
        (`_validate`) every ``eval_every`` steps and after the last decide which weights are kept and
        whether it stops early (``patience``). Returns (the policy on the CPU, in eval mode, its report)."""
        if not clips:
            raise PlaysegError(f"policy {POLICY_NAME}: no clips to train on")
        s = self.settings
        started = time.perf_counter()
        device = resolve_device(s.device)
        train_clips, val_clips = self._split(list(clips)) if len(clips) > 1 else (list(clips), [])
        features = self.features
        names = [*features.cameras, *([STATE] if features.state is not None else [])]
        discrete = features.action.num_values
        with torch_threads(s.num_threads), torch.random.fork_rng(devices=[]):
            torch.manual_seed(s.seed)
            model = self.build(train_clips)
            train_steps = _Steps(train_clips, names, discrete)
            val_steps = _Steps(val_clips, names, discrete)
            moved = self._moved_entities(model, train_clips)

            def skip(rng: np.random.Generator, step: int) -> None:
                rng.integers(0, len(train_steps), size=s.batch_size)
                rng.random(s.batch_size)

            def draw(rng: np.random.Generator, step: int) -> _Batch:
                # one generator drawn step after step, as the loop of old did: the same batches
                which = rng.integers(0, len(train_steps), size=s.batch_size)
                drop = rng.random(s.batch_size) < s.instruction_dropout
                batch = train_steps.batch(which)
                if s.augment and self.sample_symmetry is not None:
                    batch = self.sample_symmetry(*batch, rng)
                per_sample = {k: v[train_steps.pairs[which, 0]] for k, v in (moved or {}).items()}
                return _Batch(step + 1, batch, drop, per_sample)

            augmenting = s.augment and self.sample_symmetry is not None
            losses: list[tuple[int, float]] = []
            running: list[float] = []  # the action losses since the last entry of `losses`

            def log_losses(step: int) -> None:
                losses.append((step, sum(running) / len(running)))
                if progress:
                    print(f"policy {POLICY_NAME} step {step}/{s.steps}: loss {losses[-1][1]:.4f}")
                running.clear()

            def loss(trained: nn.Module, batch: _Batch) -> tuple[torch.Tensor, dict[str, float]]:
                action_loss, _, moved_loss, _ = self._loss(trained, batch.samples, batch.drop, batch.moved)
                value = action_loss.item()  # logged: the action loss, as `val_loss`
                running.append(value)
                if batch.number % s.log_every == 0 or batch.number == s.steps:
                    log_losses(batch.number)
                return action_loss + moved_loss, {"loss": value}

            def evaluate(trained: nn.Module) -> dict[str, float]:
                return self._validate(
                    trained, val_steps, train_steps, self._moved_entities(trained, val_clips)
                )

            task = TrainingTask(
                name=f"policy {POLICY_NAME}",
                model=model,
                # a pure function of the step (exact when resumed), the same draws as a plain loop
                batch_at=SequentialDraws(s.seed, draw, None if augmenting else skip),
                loss=loss,
                learning_rate=lambda step: s.lr,
                optimizer=lambda m: torch.optim.AdamW(m.parameters(), lr=s.lr, weight_decay=s.weight_decay),
                evaluate=evaluate if val_clips else None,
            )
            result = train_loop(
                task,
                LoopConfig(
                    steps=s.steps,
                    eval_every=s.eval_every,
                    patience=s.patience,
                    max_minutes=s.max_minutes,
                    grad_clip=1.0,
                    device=device,
                    log=log_to_stderr if progress else None,
                ),
            )
            if running:  # stopped early, between two entries
                log_losses(result.steps)
        model = result.model.to("cpu")  # checkpoints and `act` hold CPU weights
        model.eval()
        # the figures of the kept weights (the last evaluation's when none was finite)
        figures = result.best or (result.history[-1] if result.history else {})
        report = PolicyTrainReport(
            steps=result.steps,
            seconds=time.perf_counter() - started,
            num_segments=len(clips),
            final_loss=losses[-1][1],
            losses=losses,
            num_val_segments=len(val_clips),
            **{key: value for key, value in figures.items() if key in _VALIDATION_FIGURES},
        )
        return model, report

    def _moved_entities(self, model: BCPolicy, clips: Sequence[SegmentClip]) -> dict[str, np.ndarray] | None:
        """`BCPolicy.moved_entities` of ``clips`` when a moved- or related-entity loss is on, else None."""
        if not (self.settings.moved_entity_loss or self.settings.related_entity_loss) or not clips:
            return None
        return model.moved_entities(clips, self.settings.moved_entity_threshold)

    def evaluate(self, policy: BCPolicy, num_episodes: int, seed: int) -> None:
        """No simulator: nothing to evaluate in."""
        return None

    def save(self, path: Path, policy: BCPolicy, meta: dict[str, Any]) -> None:
        save_bc_policy(path, policy, meta)

    def load(self, path: Path) -> tuple[BCPolicy, dict[str, Any]]:
        return load_bc_policy(path)


def save_bc_policy(path: str | Path, policy: BCPolicy, meta: dict[str, Any]) -> None:
    """A playseg checkpoint of kind ``policy``: config, the features the policy reads, weights, meta."""
    save_checkpoint(path, Checkpoint("policy", policy.config, policy.features, policy.state_dict(), meta))


def load_bc_policy(path: str | Path) -> tuple[BCPolicy, dict[str, Any]]:
    """(policy in eval mode, meta); CheckpointError naming the file when it is not a usable ``bc`` one."""
    checkpoint = read_checkpoint(path, kinds=("policy",))
    if checkpoint.config.get("policy") != POLICY_NAME:
        raise CheckpointError(
            f"checkpoint {path}: a {checkpoint.config.get('policy')!r} policy, expected {POLICY_NAME!r}"
        )
    try:
        policy = BCPolicy(checkpoint.config, checkpoint.features)
        policy.load_state_dict(checkpoint.state_dict)
    except (KeyError, TypeError, ValueError, RuntimeError) as error:
        raise CheckpointError(f"checkpoint {path}: not a usable {POLICY_NAME} policy ({error})") from None
    return policy.eval(), checkpoint.meta


__all__ = [
    "BCPolicy",
    "BCPolicyLearner",
    "BCTrainConfig",
    "InstructionAttention",
    "hashed_instruction_words",
    "load_bc_policy",
    "save_bc_policy",
    "state_mask",
]
