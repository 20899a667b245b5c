"""Step encoders: each turns one feature of an observation row into a fixed-width vector.

Row t of the sequence the PS trunk reads is the concatenation, in the model configuration's order, of
every step encoder's output for observation o_t. An encoder of an observation feature (a camera, the
state) reads that feature's row t; an encoder of the ``action`` feature reads a_{t-1}, the action that
led to o_t (row 0: "no action yet"). Each row depends on its own step only, so an episode is encoded
once and its rows are reused by every window.

Encoders are chosen by the data's features (`choose_encoders`) and recorded in the checkpoint as
`EncoderSpec` (kind, feature, configuration). Kinds are registered by name: generic ones here, a domain's
own under ``<domain>.<name>``, registered when its package (playseg_core.domains.<domain>) is imported;
`build_encoder` imports it on first use, as a plugin.
"""

from __future__ import annotations

from collections.abc import Callable, Collection, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch
from torch import nn

from playseg_core.data.episode import Episode
from playseg_core.data.features import ACTION, Feature, FeatureError, Features, check_discrete_actions
from playseg_core.domains import load_domain
from playseg_core.errors import PlaysegError
from playseg_core.registry import Registry


@dataclass(frozen=True)
class EncoderSpec:
    """One step encoder of a model: its registered kind, the feature it reads, its hyperparameters."""

    kind: str
    feature: str
    config: dict[str, Any] = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        return {"kind": self.kind, "feature": self.feature, "config": dict(self.config)}

    @classmethod
    def from_json(cls, raw: Mapping[str, Any]) -> EncoderSpec:
        return cls(str(raw["kind"]), str(raw["feature"]), dict(raw.get("config", {})))


class StepEncoder(nn.Module):
    """Reads one feature: ``forward`` maps (N, *row_shape) input rows to (N, out_dim)."""

    out_dim: int
    # False when ``forward`` has nothing learnt (its output is a function of the input row alone):
    # training then encodes each row once (ps/fixed_features.py), not in every batch that reads it
    learns: bool = True

    @property
    def measured_columns(self) -> range:
        """The output columns that are values measured from the input row, not learnt features (all of
        them for an encoder that learns nothing): what PS's trunk may read through periodic embeddings."""
        return range(0) if self.learns else range(self.out_dim)

    @property
    def position_columns(self) -> list[tuple[int, int]]:
        """The (x, y) output columns of each thing whose position this encoder measures (blocks found in
        a camera frame): what PS's trunk may read the distances between (`PairDistanceEmbedding`)."""
        return []

    def input_rows(self, episode: Episode, where: str) -> np.ndarray:
        """The encoder's input for every observation o_0..o_T of ``episode`` (T+1 rows)."""
        raise NotImplementedError


class ObservationEncoder(StepEncoder):
    """An encoder of an observation feature (a camera or the state).

    A camera encoder may also give the things it sees as entities (``entity_dim`` > 0): a feature vector
    and an image position each (the cells of a convolution map, or objects it found). That is what a
    model looking for the thing an instruction names attends over, see `encode_with_entities`.
    """

    entity_dim: int = 0  # width of the entities `encode_with_entities` gives; 0: this encoder has none

    def __init__(self, feature: Feature) -> None:
        super().__init__()
        self.feature = feature

    def input_rows(self, episode: Episode, where: str) -> np.ndarray:
        rows = episode.images.get(self.feature.name) if self.feature.kind == "image" else episode.state
        if rows is None:
            raise FeatureError(
                f"{where}: the model reads feature {self.feature.name!r}, the episode lacks it"
            )
        return rows

    def encode_with_entities(
        self, rows: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor | None, torch.Tensor | None]:
        """(N, out_dim) as ``forward``, with (N, E, entity_dim) entities and their (N, E, 2) image positions
        (x, y in [-1, 1]; None without entities), from one pass."""
        return self(rows), None, None


def cell_centres(height: int, width: int) -> torch.Tensor:
    """(height * width, 2) image positions of a map's cells, row by row: x from left to right, y from top
    to bottom, both in [-1, 1]."""
    ys, xs = torch.meshgrid(
        torch.linspace(-1.0, 1.0, height), torch.linspace(-1.0, 1.0, width), indexing="ij"
    )
    return torch.stack([xs.flatten(), ys.flatten()], dim=-1)


def cell_entities(cells: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """A (N, C, H, W) convolution map as entities: (N, H * W, C) cell features and their (N, H * W, 2)
    `cell_centres`."""
    batch, _, height, width = cells.shape
    positions = cell_centres(height, width).expand(batch, -1, -1)
    return cells.flatten(2).transpose(1, 2), positions


class PreviousActionEncoder(StepEncoder):
    """An encoder of a_{t-1}: its input rows come from `previous_action_rows`."""

    def previous_action_rows(self, actions: np.ndarray, where: str) -> np.ndarray:
        """(T, ...) actions a_0..a_{T-1} -> T+1 input rows: "none" for o_0, then a_0 .. a_{T-1}."""
        raise NotImplementedError

    def input_rows(self, episode: Episode, where: str) -> np.ndarray:
        return self.previous_action_rows(episode.actions, f"{where} {ACTION}")


EncoderFactory = Callable[[Feature, dict[str, Any]], StepEncoder]
STEP_ENCODERS: Registry[EncoderFactory] = Registry("step encoder kind")
"""Step encoder classes (or factories) by kind; a domain's kinds are ``<domain>.<name>``."""


def register_encoder(kind: str) -> Callable[[EncoderFactory], EncoderFactory]:
    """Register a step encoder class (or factory) under ``kind`` (`STEP_ENCODERS`), as a decorator."""
    return STEP_ENCODERS.add(kind)


def build_encoder(spec: EncoderSpec, feature: Feature) -> StepEncoder:
    """The encoder ``spec`` describes, reading ``feature``; ValueError naming the kind when unknown."""
    if spec.kind not in STEP_ENCODERS and "." in spec.kind:
        load_domain(spec.kind.split(".", 1)[0])  # a domain registers its encoders on import
    return STEP_ENCODERS[spec.kind](feature, dict(spec.config))


@register_encoder("discrete_action")
class DiscreteActionEncoder(PreviousActionEncoder):
    """A learnt embedding of a discrete a_{t-1}; index ``num_values`` means "no action" (o_0)."""

    def __init__(self, feature: Feature, config: dict[str, Any]) -> None:
        super().__init__()
        if not feature.is_discrete:
            raise FeatureError(f"discrete_action encoder: feature {feature.name!r} is not a discrete action")
        self.num_values = feature.num_values
        self.out_dim = int(config.get("dim", 16))
        self.embedding = nn.Embedding(self.num_values + 1, self.out_dim)
        # Small at first, as the trunk's offset embedding: the trunk should not lean on the actions before
        # the observation encoders have learnt anything (docs/segmentation.md "Reading the actions").
        nn.init.normal_(self.embedding.weight, std=0.02)

    def previous_action_rows(self, actions: np.ndarray, where: str) -> np.ndarray:
        values = check_discrete_actions(actions, self.num_values, where)
        return np.concatenate([[self.num_values], values]).astype(np.int64)

    def forward(self, rows: torch.Tensor) -> torch.Tensor:
        return self.embedding(rows.long())


def _normaliser(config: dict[str, Any], size: int, name: str) -> tuple[torch.Tensor, torch.Tensor]:
    """The (mean, std) a state or continuous-action encoder standardises with (from the training data)."""
    mean = torch.tensor(config.get("mean", [0.0] * size), dtype=torch.float32)
    std = torch.tensor(config.get("std", [1.0] * size), dtype=torch.float32)
    if mean.shape != (size,) or std.shape != (size,) or bool((std <= 0).any()):
        raise PlaysegError(f"step encoder of {name!r}: mean/std must be {size} values (std > 0)")
    return mean, std


def pixels(frames: torch.Tensor) -> torch.Tensor:
    """(N, H, W, 3) uint8 frames -> (N, 3, H, W) floats in [0, 1] for a convolution, channels innermost in
    memory as the frames have them (the convolutions' fast layout on the CPU). Scaled in place in a copy:
    one pass less over the frames, which outgrow the cache."""
    return frames.permute(0, 3, 1, 2).to(torch.float32, copy=True).div_(255.0)


@register_encoder("image_cnn")
class ImageEncoder(ObservationEncoder):
    """A small CNN for a camera of any size, trained from scratch (no download).

    Strided convolutions, then an adaptive average pool to a fixed grid (``pool`` x ``pool``) so any frame
    size gives the same width; the grid keeps coarse "where" (what is left or right, near or far), which a
    global pool would lose. One per camera: each camera's features are its own columns of the step row.
    """

    def __init__(self, feature: Feature, config: dict[str, Any]) -> None:
        super().__init__(feature)
        channels = [int(c) for c in config.get("channels", (16, 32, 64))]
        pool = int(config.get("pool", 4))
        self.out_dim = int(config.get("dim", 128))
        layers: list[nn.Module] = []
        previous = 3
        for index, width in enumerate(channels):
            kernel = 5 if index == 0 else 3
            layers += [nn.Conv2d(previous, width, kernel, stride=2, padding=kernel // 2), nn.GELU()]
            previous = width
        self.convs = nn.Sequential(*layers, nn.AdaptiveAvgPool2d(pool))
        self.proj = nn.Sequential(nn.Flatten(), nn.Linear(previous * pool * pool, self.out_dim), nn.GELU())
        self.entity_dim = previous

    def forward(self, frames: torch.Tensor) -> torch.Tensor:
        """(N, H, W, 3) uint8 -> (N, dim)."""
        return self.proj(self.convs(pixels(frames)))

    def encode_with_entities(
        self, frames: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor | None, torch.Tensor | None]:
        """(N, dim), and the last convolution's cells (before the pool) as entities."""
        cells = self.convs[:-1](pixels(frames))
        return self.proj(self.convs[-1](cells)), *cell_entities(cells)


@register_encoder("state_mlp")
class StateEncoder(ObservationEncoder):
    """An MLP over the (flattened) state vector, standardised with the training data's mean and std.

    With ``measured`` (config; `choose_encoders` sets it for a model whose trunk reads measured values),
    the standardised state itself comes first in the output, as measured values (`measured_columns`),
    then the MLP's features.
    """

    def __init__(self, feature: Feature, config: dict[str, Any]) -> None:
        super().__init__(feature)
        dim = int(config.get("dim", 64))
        mean, std = _normaliser(config, feature.size, feature.name)
        self.register_buffer("mean", mean)
        self.register_buffer("std", std)
        hidden = int(config.get("hidden", 128))
        self.mlp = nn.Sequential(nn.Linear(feature.size, hidden), nn.GELU(), nn.Linear(hidden, dim))
        self.measured = bool(config.get("measured", False))
        self.out_dim = dim + (feature.size if self.measured else 0)

    @property
    def measured_columns(self) -> range:
        return range(self.mean.numel() if self.measured else 0)

    def forward(self, rows: torch.Tensor) -> torch.Tensor:
        state = (rows.reshape(rows.shape[0], -1).float() - self.mean) / self.std
        return torch.cat([state, self.mlp(state)], dim=1) if self.measured else self.mlp(state)


@register_encoder("continuous_action")
class ContinuousActionEncoder(PreviousActionEncoder):
    """A linear embedding of a continuous a_{t-1}, standardised with the training data's mean and std,
    plus a "no action yet" flag for o_0."""

    def __init__(self, feature: Feature, config: dict[str, Any]) -> None:
        super().__init__()
        if feature.is_discrete:
            raise FeatureError(f"continuous_action encoder: feature {feature.name!r} is discrete")
        self.size = feature.size
        self.out_dim = int(config.get("dim", 16))
        mean, std = _normaliser(config, self.size, feature.name)
        self.register_buffer("mean", mean)
        self.register_buffer("std", std)
        self.embed = nn.Linear(self.size + 1, self.out_dim)
        nn.init.normal_(self.embed.weight, std=0.02)  # small at first, as discrete_action's
        nn.init.zeros_(self.embed.bias)

    def previous_action_rows(self, actions: np.ndarray, where: str) -> np.ndarray:
        values = np.asarray(actions, np.float32)
        # No action yet (o_0 of a stream) arrives as an empty array of any width.
        values = values.reshape(len(values), -1) if len(values) else np.zeros((0, self.size), np.float32)
        if values.shape[1] != self.size:
            raise FeatureError(f"{where}: actions of {values.shape[1]} values, the model reads {self.size}")
        if not np.isfinite(values).all():
            step = int(np.flatnonzero(~np.isfinite(values).all(axis=1))[0])
            raise FeatureError(f"{where}[{step}]: NaN or inf in a continuous action")
        rows = np.zeros((len(values) + 1, self.size + 1), np.float32)
        rows[0, -1] = 1.0  # o_0: no action led here
        rows[1:, :-1] = (values - self.mean.numpy()) / self.std.numpy()
        return rows

    def forward(self, rows: torch.Tensor) -> torch.Tensor:
        return self.embed(rows.float())


class StepEncoders(nn.Module):
    """The step encoders of a model, in order; ``forward`` concatenates their outputs per row."""

    def __init__(self, specs: Sequence[EncoderSpec], features: Features) -> None:
        super().__init__()
        if not specs:
            raise PlaysegError("a model needs at least one step encoder")
        self.specs = list(specs)
        self.encoders = nn.ModuleList(build_encoder(spec, features[spec.feature]) for spec in specs)

    @property
    def step_dim(self) -> int:
        return sum(encoder.out_dim for encoder in self.encoders)

    @property
    def observation_dim(self) -> int:
        """Width of the observation encoders' columns (they come before the action's, see `choose_encoders`)."""
        return sum(e.out_dim for e in self.encoders if not isinstance(e, PreviousActionEncoder))

    @property
    def measured_columns(self) -> list[int]:
        """The columns of step features that hold measured values (`StepEncoder.measured_columns` of the
        observation encoders: positions found in a camera frame, a state read as it is)."""
        return [
            first + column
            for first, encoder in self._observation_encoders()
            for column in encoder.measured_columns
        ]

    @property
    def position_columns(self) -> list[tuple[int, int]]:
        """The (x, y) step-feature columns of every measured position (`StepEncoder.position_columns`)."""
        return [
            (first + x, first + y)
            for first, encoder in self._observation_encoders()
            for x, y in encoder.position_columns
        ]

    def _observation_encoders(self) -> list[tuple[int, ObservationEncoder]]:
        """Each observation encoder with the step-feature column its output starts at."""
        starts = np.cumsum([0] + [encoder.out_dim for encoder in self.encoders])
        return [
            (int(first), encoder)
            for first, encoder in zip(starts[:-1], self.encoders, strict=True)
            if isinstance(encoder, ObservationEncoder)
        ]

    @property
    def reads_actions(self) -> bool:
        return any(isinstance(e, PreviousActionEncoder) for e in self.encoders)

    def episode_inputs(self, episode: Episode) -> dict[str, np.ndarray]:
        """Every encoder's input rows for o_0..o_T, by feature (memory-mapped where the episode is)."""
        where = f"episode {episode.episode_id!r}"
        return {
            spec.feature: enc.input_rows(episode, where)
            for spec, enc in zip(self.specs, self.encoders, strict=True)
        }

    def recorded_clip(
        self, episode: Episode, first: int, last: int, features: Collection[str] | None = None
    ) -> dict[str, np.ndarray]:
        """What was recorded of the observations o_first..o_last that the encoders read, by feature, and
        of the actions that led to them (a_{first-1}..a_{last-1}; from a_0 when ``first`` is 0): the
        values a domain's symmetries turn before `clip_inputs` (ps/symmetries.py `ClipSymmetries`). Only
        ``features`` when given."""
        where = f"episode {episode.episode_id!r}"
        return {
            spec.feature: episode.actions[max(first - 1, 0) : last]
            if isinstance(encoder, PreviousActionEncoder)
            else encoder.input_rows(episode, where)[first : last + 1]
            for spec, encoder in zip(self.specs, self.encoders, strict=True)
            if features is None or spec.feature in features
        }

    def clip_inputs(
        self, recorded: Mapping[str, np.ndarray], first: int, where: str
    ) -> dict[str, np.ndarray]:
        """The encoders' input rows of a `recorded_clip` that starts at o_first: `episode_inputs`' rows
        first..last, from the clip's values (for the features the clip has)."""
        inputs = {}
        for spec, encoder in zip(self.specs, self.encoders, strict=True):
            if spec.feature not in recorded:
                continue
            rows = np.asarray(recorded[spec.feature])
            if isinstance(encoder, PreviousActionEncoder):
                clip = f"{where} {spec.feature} (a clip from step {max(first - 1, 0)})"
                rows = encoder.previous_action_rows(rows, clip)
                rows = rows[1:] if first > 0 else rows  # o_first's row is a_{first-1}'s, not "none"
            inputs[spec.feature] = rows
        return inputs

    def observation_inputs(
        self, observations: Mapping[str, np.ndarray], where: str, rows: int | None = None
    ) -> dict[str, np.ndarray]:
        """Input rows for each observation encoder, by feature: one observation (``rows`` None; a row axis
        is added) or a batch of ``rows`` observations. FeatureError naming the feature when it is missing
        or has another shape (or, for a camera, another dtype than uint8)."""
        inputs = {}
        for spec, encoder in zip(self.specs, self.encoders, strict=True):
            if not isinstance(encoder, ObservationEncoder):
                continue
            if spec.feature not in observations:
                lacking = "the step" if rows is None else "the observations"
                raise FeatureError(f"{where}: the model reads feature {spec.feature!r}, {lacking} lacks it")
            array = np.asarray(observations[spec.feature])
            feature = encoder.feature
            expected = feature.shape if rows is None else (rows, *feature.shape)
            if array.shape != expected or (feature.kind == "image" and array.dtype != np.uint8):
                raise FeatureError(
                    f"{where}: feature {spec.feature!r} must be {list(expected)} {feature.dtype}, "
                    f"got {list(array.shape)} {array.dtype}"
                )
            inputs[spec.feature] = array[None] if rows is None else array
        return inputs

    @property
    def cameras(self) -> list[str]:
        """The camera features the encoders read."""
        return [
            e.feature.name
            for e in self.encoders
            if isinstance(e, ObservationEncoder) and e.feature.kind == "image"
        ]

    def previous_action_inputs(self, action: np.ndarray | None, where: str) -> dict[str, np.ndarray]:
        """The action encoders' input row (1, ...) for the observation ``action`` led to (None: o_0)."""
        earlier = (
            np.zeros((0, 1), np.float32) if action is None else np.asarray(action, np.float32).reshape(1, -1)
        )
        return {
            spec.feature: encoder.previous_action_rows(earlier, where)[-1:]
            for spec, encoder in zip(self.specs, self.encoders, strict=True)
            if isinstance(encoder, PreviousActionEncoder)
        }

    def forward(
        self, inputs: Mapping[str, torch.Tensor], encoded: Mapping[str, torch.Tensor] | None = None
    ) -> torch.Tensor:
        """Input rows by feature (N rows each) -> (N, step_dim). A feature in ``encoded`` is taken as its
        encoder's output rows already (an encoder that learns nothing, encoded once: `learns`)."""
        encoded = encoded or {}
        return torch.cat(
            [
                encoded[spec.feature] if spec.feature in encoded else enc(inputs[spec.feature])
                for spec, enc in zip(self.specs, self.encoders, strict=True)
            ],
            dim=-1,
        )


def as_tensors(inputs: Mapping[str, np.ndarray], rows: slice = slice(None)) -> dict[str, torch.Tensor]:
    """Rows of numpy inputs as tensors (copied: dataset arrays are read-only memmaps), row-major whatever
    the arrays' strides (a broadcast array copies into another layout by default): the convolutions run
    several times faster on frames whose channels are innermost."""
    return {name: torch.from_numpy(np.array(array[rows], order="C")) for name, array in inputs.items()}


def feature_statistics(
    episodes: Iterable[Episode], names: Iterable[str]
) -> dict[str, dict[str, list[float]]]:
    """Mean and std of each of ``names`` (the state, a continuous action) over ``episodes``, per value;
    std floored (a constant value standardises to 0, not to inf)."""
    names = list(names)
    sums: dict[str, np.ndarray] = {}
    squares: dict[str, np.ndarray] = {}
    counts = dict.fromkeys(names, 0)
    for episode in episodes:
        for name in names:
            rows = episode.actions if name == ACTION else episode.state
            if rows is None or len(rows) == 0:
                continue
            values = np.asarray(rows, np.float64).reshape(len(rows), -1)
            sums[name] = sums.get(name, 0.0) + values.sum(0)
            squares[name] = squares.get(name, 0.0) + np.square(values).sum(0)
            counts[name] += len(values)
    stats = {}
    for name in names:
        if not counts[name]:
            raise PlaysegError(f"statistics of feature {name!r}: no values in the training episodes")
        mean = sums[name] / counts[name]
        std = np.sqrt(np.maximum(squares[name] / counts[name] - np.square(mean), 0.0))
        stats[name] = {"mean": mean.tolist(), "std": np.where(std > 1e-6, std, 1.0).tolist()}
    return stats


ENCODER_CHOICES = ("image_cnn", "state_mlp", "discrete_action", "continuous_action", "none")
"""What ``--encoder FEATURE=KIND`` may ask for (and a domain's own kinds, ``<domain>.<name>``)."""


def _default_spec(kind: str, feature: Feature, statistics: dict[str, dict[str, list[float]]]) -> EncoderSpec:
    config: dict[str, Any] = {}
    if kind in ("state_mlp", "continuous_action"):
        if feature.name not in statistics:
            raise PlaysegError(
                f"step encoder {kind} of {feature.name!r} needs the training data's statistics"
            )
        config.update(statistics[feature.name])
    return EncoderSpec(kind, feature.name, config)


def _with_statistics(
    spec: EncoderSpec, feature: Feature, statistics: dict[str, dict[str, list[float]]]
) -> EncoderSpec:
    """A domain's spec of a generic kind that standardises (its own settings, such as a state's
    ``measured``), given the training data's statistics as the generic default gets them."""
    if spec.kind not in ("state_mlp", "continuous_action") or "mean" in spec.config:
        return spec
    default = _default_spec(spec.kind, feature, statistics)
    return EncoderSpec(spec.kind, spec.feature, {**spec.config, **default.config})


def choose_encoders(
    features: Features,
    choice: Callable[[Features], Mapping[str, EncoderSpec | None]] | None = None,
    statistics: dict[str, dict[str, list[float]]] | None = None,
    read_actions: bool = True,
    overrides: dict[str, str] | None = None,
    measured_state: bool = False,
) -> list[EncoderSpec]:
    """Step encoders for data with ``features``, in order: every camera, the state, then the previous
    action (observation encoders first: the auxiliary frame-label loss reads their columns).

    Each feature gets, in this order of preference: ``overrides[name]`` (a kind, or "none" to leave it
    unread), ``choice(features)`` (a domain's `Domain.step_encoders`: a spec, or None for "not read"),
    the generic default (``image_cnn`` per camera, ``state_mlp``, ``discrete_action`` or
    ``continuous_action``). ``read_actions`` False leaves the action unread. ``statistics``
    (`feature_statistics`) standardise the state and a continuous action. ``measured_state``: the generic
    state encoder also gives the standardised state as measured values (``measured``), for a model whose
    trunk reads them through periodic embeddings. FeatureError when nothing would be read, or an override
    names a feature the data lacks.
    """
    overrides = dict(overrides or {})
    statistics = statistics or {}
    for name in overrides:
        features[name]  # FeatureError naming a feature the data lacks
    chosen = choice(features) if choice else {}
    action = features.action
    defaults = {name: "image_cnn" for name in features.cameras}
    if features.state is not None:
        defaults[features.state.name] = "state_mlp"
    if read_actions:
        defaults[action.name] = "discrete_action" if action.is_discrete else "continuous_action"
    specs = []
    for name in [*features.cameras, *([features.state.name] if features.state else []), action.name]:
        if name in overrides:
            kind = overrides[name]
            if kind != "none":
                specs.append(_default_spec(kind, features[name], statistics))
        elif name in chosen:
            if chosen[name] is not None:
                specs.append(_with_statistics(chosen[name], features[name], statistics))
        elif name in defaults:
            specs.append(_default_spec(defaults[name], features[name], statistics))
    if measured_state and features.state is not None:
        # A state is measured values (joint angles, an effector's position) on which skills end at
        # thresholds, what the periodic embeddings sharpen (ps/model.py `PeriodicEmbedding`).
        specs = [
            EncoderSpec(s.kind, s.feature, {"measured": True, **s.config})
            if s.kind == "state_mlp" and s.feature == features.state.name
            else s
            for s in specs
        ]
    if not any(spec.feature != action.name for spec in specs):
        raise FeatureError(
            f"no observation feature would be read (the data has {', '.join(features.by_name)})"
        )
    return specs
