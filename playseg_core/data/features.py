"""The feature schema: what every step of a dataset holds, by name (in the spirit of LeRobot's `features`).

A feature is one array per step with a fixed dtype and per-step shape:

- ``observation.images.<camera>``: an RGB camera, (H, W, 3) uint8, one row per observation o_0..o_T.
  Any number of cameras, zero included.
- ``observation.state``: an optional low-dimensional state (a joint vector, a pose, a symbolic grid),
  one row per observation.
- ``action``: one float32 row per step a_0..a_{T-1}; discrete (``num_values`` choices, stored as the
  chosen index, shape (1,)) or continuous (``shape`` values, with optional ``low``/``high`` bounds).

`Features` is the schema of a dataset, a bag (in its rosbag2 ``custom_data``) or what a model reads; its
JSON form is what ``meta/info.json`` stores under ``features``. Models check a dataset's features against
the ones they were trained on, and a mismatch is an error naming the feature.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field, replace
from typing import Any, Literal, NotRequired, TypedDict

import numpy as np

from playseg_core.data.episode import Episode
from playseg_core.errors import PlaysegError

IMAGE_PREFIX = "observation.images."
STATE = "observation.state"
ACTION = "action"
DEFAULT_CAMERA = IMAGE_PREFIX + "camera"
"""The name of a single camera that its source does not name (a version 1 dataset, a PlayStep stream
without a declared schema)."""

Kind = Literal["image", "state", "action"]


class FeatureError(PlaysegError):
    """Data that contradicts a feature schema; the message names the feature."""


class FeatureJson(TypedDict):
    """One feature as ``meta/info.json`` stores it."""

    kind: Kind
    dtype: str
    shape: list[int]
    names: NotRequired[list[str] | None]
    action_type: NotRequired[Literal["discrete", "continuous"]]
    num_values: NotRequired[int]
    low: NotRequired[list[float] | None]
    high: NotRequired[list[float] | None]


class FeaturesJson(TypedDict):
    fps: float | None
    features: dict[str, FeatureJson]


@dataclass(frozen=True)
class Feature:
    """One named per-step array.

    names: what each value means (joint names, action axes), when known.
    num_values: for a discrete action, the number of choices (stored as one index per step); 0 otherwise.
    low, high: for a continuous action, its bounds when known.
    """

    name: str
    kind: Kind
    dtype: str
    shape: tuple[int, ...]
    names: tuple[str, ...] | None = None
    num_values: int = 0
    low: tuple[float, ...] | None = None
    high: tuple[float, ...] | None = None

    def __post_init__(self) -> None:
        where = f"feature {self.name!r}"
        expected_kind = _kind_of_name(self.name)
        if expected_kind is None:
            raise FeatureError(
                f"{where}: unknown name (expected {IMAGE_PREFIX}<camera>, {STATE!r} or {ACTION!r})"
            )
        if self.kind != expected_kind:
            raise FeatureError(f"{where}: kind {self.kind!r}, but its name says {expected_kind!r}")
        np.dtype(self.dtype)  # raises TypeError for a dtype numpy does not know
        if self.kind == "image" and (len(self.shape) != 3 or self.shape[-1] != 3 or self.dtype != "uint8"):
            raise FeatureError(f"{where}: an image must be (H, W, 3) uint8, got {self.shape} {self.dtype}")
        if self.names is not None and len(self.names) != int(np.prod(self.shape)):
            raise FeatureError(f"{where}: {len(self.names)} names for shape {self.shape}")
        if self.kind == "action" and self.dtype != "float32":
            raise FeatureError(f"{where}: actions are stored as float32 (a discrete one as its index)")
        if self.num_values < 0 or (self.num_values and (self.kind != "action" or self.shape != (1,))):
            raise FeatureError(f"{where}: only an action of shape (1,) can be discrete")
        for bound in (self.low, self.high):
            if bound is not None and len(bound) != int(np.prod(self.shape)):
                raise FeatureError(
                    f"{where}: bounds need {int(np.prod(self.shape))} values, got {len(bound)}"
                )

    @property
    def is_discrete(self) -> bool:
        return self.num_values > 0

    @property
    def size(self) -> int:
        """Values per step."""
        return int(np.prod(self.shape))

    def to_json(self) -> FeatureJson:
        out: FeatureJson = {"kind": self.kind, "dtype": self.dtype, "shape": list(self.shape)}
        if self.names is not None:
            out["names"] = list(self.names)
        if self.kind == "action":
            out["action_type"] = "discrete" if self.is_discrete else "continuous"
            if self.is_discrete:
                out["num_values"] = self.num_values
            else:
                out["low"] = None if self.low is None else list(self.low)
                out["high"] = None if self.high is None else list(self.high)
        return out

    @classmethod
    def from_json(cls, name: str, raw: Mapping[str, Any]) -> Feature:
        if not isinstance(raw, Mapping):
            raise FeatureError(f"feature {name!r}: expected a mapping, got {type(raw).__name__}")
        try:
            discrete = raw.get("action_type") == "discrete"
            return cls(
                name=name,
                kind=raw["kind"],
                dtype=str(raw["dtype"]),
                shape=tuple(int(n) for n in raw["shape"]),
                names=None if raw.get("names") is None else tuple(str(n) for n in raw["names"]),
                num_values=int(raw["num_values"]) if discrete else 0,
                low=_bound(raw.get("low")),
                high=_bound(raw.get("high")),
            )
        except (KeyError, TypeError, ValueError) as error:
            if isinstance(error, FeatureError):
                raise
            raise FeatureError(f"feature {name!r}: malformed ({type(error).__name__}: {error})") from None

    def check_rows(self, array: np.ndarray, rows: int, where: str) -> None:
        """``array`` must be ``rows`` rows of this feature (dtype and per-row shape)."""
        if array.shape != (rows, *self.shape) or array.dtype != np.dtype(self.dtype):
            raise FeatureError(
                f"{where}: feature {self.name!r} must be {(rows, *self.shape)} {self.dtype}, "
                f"got {array.shape} {array.dtype}"
            )

    def describe(self) -> str:
        if self.kind == "action":
            kind = f"discrete, {self.num_values} values" if self.is_discrete else f"continuous, {self.size}-d"
            return f"{self.name}: action ({kind})"
        return f"{self.name}: {self.kind} {list(self.shape)} {self.dtype}"


def _bound(values: Any) -> tuple[float, ...] | None:
    return None if values is None else tuple(float(v) for v in values)


def _kind_of_name(name: str) -> Kind | None:
    if name.startswith(IMAGE_PREFIX) and len(name) > len(IMAGE_PREFIX):
        return "image"
    return {STATE: "state", ACTION: "action"}.get(name)  # type: ignore[return-value]


@dataclass(frozen=True)
class Features:
    """The features of a dataset: cameras (any number), an optional state, the action; and the step rate."""

    by_name: dict[str, Feature] = field(default_factory=dict)
    fps: float | None = None

    def __post_init__(self) -> None:
        if ACTION not in self.by_name:
            raise FeatureError(f"features {sorted(self.by_name)}: the {ACTION!r} feature is required")
        for name, feature in self.by_name.items():
            if feature.name != name:
                raise FeatureError(f"feature {feature.name!r} filed under {name!r}")
        if self.fps is not None and not (math.isfinite(self.fps) and self.fps > 0):
            raise FeatureError(f"features: fps must be a positive number, got {self.fps}")

    @classmethod
    def of(cls, features: Iterable[Feature], fps: float | None = None) -> Features:
        return cls({f.name: f for f in features}, fps)

    @property
    def cameras(self) -> list[str]:
        """Names of the image features, sorted."""
        return sorted(name for name, f in self.by_name.items() if f.kind == "image")

    @property
    def state(self) -> Feature | None:
        return self.by_name.get(STATE)

    @property
    def action(self) -> Feature:
        return self.by_name[ACTION]

    def __getitem__(self, name: str) -> Feature:
        if name not in self.by_name:
            raise FeatureError(f"no feature {name!r} (the data has {', '.join(sorted(self.by_name))})")
        return self.by_name[name]

    def __contains__(self, name: object) -> bool:
        return name in self.by_name

    def to_json(self) -> FeaturesJson:
        return {"fps": self.fps, "features": {name: f.to_json() for name, f in sorted(self.by_name.items())}}

    @classmethod
    def from_json(cls, raw: Mapping[str, Any]) -> Features:
        if not isinstance(raw, Mapping) or not isinstance(raw.get("features"), Mapping):
            raise FeatureError("features: expected a mapping with a 'features' mapping")
        fps = raw.get("fps")
        if fps is not None and (isinstance(fps, bool) or not isinstance(fps, int | float)):
            raise FeatureError(f"features: fps must be a number, got {fps!r}")
        return cls(
            {str(name): Feature.from_json(str(name), spec) for name, spec in raw["features"].items()},
            None if fps is None else float(fps),
        )

    def with_action(self, action: Feature) -> Features:
        """The same features with another action feature."""
        return replace(self, by_name={**self.by_name, ACTION: action})

    def with_camera(self, camera: Feature) -> Features:
        """The same features with ``camera`` added or replaced."""
        return replace(self, by_name={**self.by_name, camera.name: camera})

    def check_episode(self, episode: Episode) -> None:
        """FeatureError naming the episode and feature when ``episode`` does not have these features."""
        where = f"episode {episode.episode_id!r}"
        rows = episode.num_steps + 1
        have = set(episode.images) | ({STATE} if episode.state is not None else set())
        want = set(self.cameras) | ({STATE} if self.state is not None else set())
        if have != want:
            extra, missing = sorted(have - want), sorted(want - have)
            raise FeatureError(f"{where}: has {extra or 'no extra'} features, lacks {missing or 'none'}")
        for name in self.cameras:
            self[name].check_rows(episode.images[name], rows, where)
        if self.state is not None:
            self.state.check_rows(episode.state, rows, where)
        action = self.action
        actions = episode.actions
        if actions.shape != (episode.num_steps, *action.shape):
            raise FeatureError(
                f"{where}: feature {ACTION!r} must be {(episode.num_steps, *action.shape)}, got {actions.shape}"
            )
        if action.is_discrete:
            check_discrete_actions(actions, action.num_values, f"{where} {ACTION}")

    def check_compatible(self, other: Features, names: Iterable[str], what: str) -> None:
        """FeatureError naming the first of ``names`` that ``other`` lacks or declares differently.

        ``self`` is what ``what`` (e.g. a checkpoint) expects; ``other`` what the data has. Bounds, names
        and dtypes may differ (they describe the data; readers cast). A model reading a discrete action
        also accepts an undeclared one-value action (a source that declares no kind): every value is
        checked as an index when read.
        """
        for name in names:
            mine = self[name]
            if name not in other:
                raise FeatureError(f"{what} reads feature {name!r}, which the data lacks ({mine.describe()})")
            theirs = other[name]
            if (
                mine.is_discrete
                and theirs.kind == "action"
                and not theirs.is_discrete
                and theirs.shape == (1,)
            ):
                continue
            if (mine.kind, mine.shape, mine.num_values) != (theirs.kind, theirs.shape, theirs.num_values):
                raise FeatureError(f"{what} reads {mine.describe()}, but the data has {theirs.describe()}")


def check_discrete_actions(actions: np.ndarray, num_values: int, where: str) -> np.ndarray:
    """(T, 1) discrete action indices -> (T,) int64; FeatureError naming `where` and the step otherwise."""
    actions = np.asarray(actions)
    if actions.ndim != 2 or actions.shape[1] != 1:
        raise FeatureError(f"{where}: discrete actions need shape (T, 1), got {actions.shape}")
    values = actions[:, 0]
    whole = np.isfinite(values) & (values == np.round(values))
    bad = ~whole | (values < 0) | (values >= num_values)
    if bad.any():
        step = int(np.flatnonzero(bad)[0])
        raise FeatureError(
            f"{where}[{step}] = {float(values[step])}: not a discrete action index in 0..{num_values - 1}"
        )
    return values.astype(np.int64)


def infer_features(episode: Episode) -> Features:
    """The schema of one episode's arrays, with a continuous action (nothing says it is discrete)."""
    features = [
        Feature(name, "image", str(a.dtype), tuple(a.shape[1:])) for name, a in episode.images.items()
    ]
    if episode.state is not None:
        features.append(Feature(STATE, "state", str(episode.state.dtype), tuple(episode.state.shape[1:])))
    features.append(Feature(ACTION, "action", "float32", tuple(episode.actions.shape[1:])))
    return Features.of(features)


def conform_episode(episode: Episode, features: Features) -> Episode:
    """``episode`` as ``features`` declare it: the state in its declared dtype, and a lone camera that its
    source could not name (`DEFAULT_CAMERA`) under the one declared camera. Not checked (`check_episode`)."""
    images = episode.images
    if list(images) == [DEFAULT_CAMERA] and len(features.cameras) == 1:
        images = {features.cameras[0]: images[DEFAULT_CAMERA]}
    state = episode.state
    if state is not None and features.state is not None:
        state = state.astype(features.state.dtype, copy=False)
    actions = episode.actions.astype(np.float32, copy=False)
    return replace(episode, actions=actions, images=images, state=state)
