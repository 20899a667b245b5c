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

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch
from torch import nn

from playseg_core.data.episode import Episode
from playseg_core.data.features import ACTION, Feature, FeatureError, Features, check_discrete_actions
from playseg_core.domains import load_domain


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

    def input_rows(self, episode: Episode, where: str) -> np.ndarray:
        """The encoder's input for every observation o_0..o_T of ``episode`` (T+1 rows)."""
        raise NotImplementedError


class ObservationEncoder(StepEncoder):
    """An encoder of an observation feature (a camera or the state)."""

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


class PreviousActionEncoder(StepEncoder):
    """An encoder of a_{t-1}: its input rows come from `previous_action_rows`."""

    def previous_action_rows(self, actions: np.ndarray, where: str) -> np.ndarray:
        """(T, ...) actions a_0..a_{T-1} -> T+1 input rows: "none" for o_0, then a_0 .. a_{T-1}."""
        raise NotImplementedError

    def input_rows(self, episode: Episode, where: str) -> np.ndarray:
        return self.previous_action_rows(episode.actions, f"{where} {ACTION}")


EncoderFactory = Callable[[Feature, dict[str, Any]], StepEncoder]
_REGISTRY: dict[str, EncoderFactory] = {}


def register_encoder(kind: str) -> Callable[[EncoderFactory], EncoderFactory]:
    """Register a step encoder class (or factory) under ``kind``; a domain's kinds are ``<domain>.<name>``."""

    def register(factory: EncoderFactory) -> EncoderFactory:
        if kind in _REGISTRY and _REGISTRY[kind] is not factory:
            raise ValueError(f"step encoder kind {kind!r} is registered twice")
        _REGISTRY[kind] = factory
        return factory

    return register


def build_encoder(spec: EncoderSpec, feature: Feature) -> StepEncoder:
    """The encoder ``spec`` describes, reading ``feature``; ValueError naming the kind when unknown."""
    if spec.kind not in _REGISTRY and "." in spec.kind:
        load_domain(spec.kind.split(".", 1)[0])  # a domain registers its encoders on import
    if spec.kind not in _REGISTRY:
        raise ValueError(f"unknown step encoder kind {spec.kind!r} (known: {', '.join(sorted(_REGISTRY))})")
    return _REGISTRY[spec.kind](feature, dict(spec.config))


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


class StepEncoders(nn.Module):
    """The step encoders of a model, in order; ``forward`` concatenates their outputs per row."""

    def __init__(self, specs: Sequence[EncoderSpec], features: Features) -> None:
        super().__init__()
        if not specs:
            raise ValueError("a model needs at least one step encoder")
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
    def reads_actions(self) -> bool:
        return any(isinstance(e, PreviousActionEncoder) for e in self.encoders)

    def episode_inputs(self, episode: Episode) -> dict[str, np.ndarray]:
        """Every encoder's input rows for o_0..o_T, by feature (memory-mapped where the episode is)."""
        where = f"episode {episode.episode_id!r}"
        return {
            spec.feature: enc.input_rows(episode, where)
            for spec, enc in zip(self.specs, self.encoders, strict=True)
        }

    def observation_inputs(self, observation: Mapping[str, np.ndarray], where: str) -> dict[str, np.ndarray]:
        """One observation's input row (1, ...) for each observation encoder, by feature; FeatureError
        naming the feature when the observation lacks it or it has another shape (or, for a camera,
        another dtype than uint8)."""
        inputs = {}
        for spec, encoder in zip(self.specs, self.encoders, strict=True):
            if not isinstance(encoder, ObservationEncoder):
                continue
            if spec.feature not in observation:
                raise FeatureError(f"{where}: the model reads feature {spec.feature!r}, the step lacks it")
            row = np.asarray(observation[spec.feature])[None]
            feature = encoder.feature
            if row.shape[1:] != feature.shape or (feature.kind == "image" and row.dtype != np.uint8):
                raise FeatureError(
                    f"{where}: feature {spec.feature!r} must be {list(feature.shape)} {feature.dtype}, "
                    f"got {list(row.shape[1:])} {row.dtype}"
                )
            inputs[spec.feature] = row
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

    def forward(self, inputs: Mapping[str, torch.Tensor]) -> torch.Tensor:
        """Input rows by feature (N rows each) -> (N, step_dim)."""
        return torch.cat(
            [enc(inputs[spec.feature]) for spec, enc in zip(self.specs, self.encoders, strict=True)], dim=-1
        )


def as_tensors(inputs: Mapping[str, np.ndarray], rows: slice = slice(None)) -> dict[str, torch.Tensor]:
    """Rows of numpy inputs as tensors (copied: dataset arrays are read-only memmaps)."""
    return {name: torch.from_numpy(np.array(array[rows])) for name, array in inputs.items()}


def choose_encoders(features: Features, domain: str | None, read_actions: bool = True) -> list[EncoderSpec]:
    """Step encoders for data with ``features``: every camera (by the domain's encoder for it), then the
    previous action when ``read_actions`` and the action is discrete.

    Observation encoders come first: the auxiliary frame-label loss reads their columns. FeatureError
    naming the feature when no encoder can read a camera.
    """
    specs = []
    for camera in features.cameras:
        image_encoder = getattr(load_domain(domain), "image_encoder", None) if domain else None
        spec = image_encoder(features[camera]) if image_encoder else None
        if spec is None:
            raise FeatureError(
                f"no step encoder for camera feature {camera!r} ({features[camera].describe()}) "
                f"in domain {domain!r}"
            )
        specs.append(spec)
    if not specs:
        raise FeatureError(f"the data has no camera feature ({', '.join(features.by_name)}): nothing to read")
    if read_actions and features.action.is_discrete:
        specs.append(EncoderSpec("discrete_action", ACTION, {"dim": 16}))
    return specs
