"""The mapping file: which dataset features come from which topics and fields, on which clock.

The YAML form (docs/convert.md is the reference)::

    fps: 10                                   # step rate of the dataset
    primary: observation.images.front         # steps are taken on this feature's clock
    tolerance_ms: 50                          # how far another feature's sample may lie from a step
    features:
      observation.images.front: {topic: /camera/color/image_raw}
      observation.state: {topic: /joint_states, field: position}
      action: {topic: /cmd_vel, fields: [linear.x, linear.y, angular.z]}
    annotations: {topic: /annotations}        # and/or {file: annotations.yaml}
    episodes: {split: bag}                    # or {split: marker, topic: ...} or {split: gap, gap_s: ...}

`load_mapping` validates everything it can without a bag and raises `MappingError` naming the file and
the key; what only a bag can tell (a topic's type, a field's presence) is checked per bag.
"""

from __future__ import annotations

import hashlib
import json
import math
from collections.abc import Mapping as MappingType
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal, NotRequired, TypedDict

import yaml

from playseg_core.data.features import ACTION, IMAGE_PREFIX, STATE
from playseg_ros.convert.errors import MappingError

AlignMethod = Literal["nearest", "previous", "linear"]
ALIGN_METHODS: tuple[AlignMethod, ...] = ("nearest", "previous", "linear")
Clock = Literal["header", "receive"]
CLOCKS: tuple[Clock, ...] = ("header", "receive")
SplitKind = Literal["bag", "marker", "gap"]
SPLITS: tuple[SplitKind, ...] = ("bag", "marker", "gap")
Derive = Literal["next", "delta"]
DERIVES: tuple[Derive, ...] = ("next", "delta")


# --------------------------------------------------------------------------------------------------
# The file as YAML holds it


class ResizeYaml(TypedDict):
    width: int
    height: int


class FeatureYaml(TypedDict, total=False):
    """One entry of ``features``: a topic and what to take from it, or (the action) a derivation."""

    topic: str
    field: str
    fields: list[str]
    joints: list[str]
    align: AlignMethod
    tolerance_ms: float
    resize: ResizeYaml
    low: list[float]
    high: list[float]
    # an action derived from another feature instead of read from a topic
    derive: Derive
    of: str


class AnnotationsYaml(TypedDict, total=False):
    topic: str
    file: str


class EpisodesYaml(TypedDict, total=False):
    split: SplitKind
    topic: str
    gap_s: float
    min_steps: int


class MappingYaml(TypedDict):
    fps: float
    primary: str
    tolerance_ms: NotRequired[float]
    align: NotRequired[AlignMethod]
    clock: NotRequired[Clock]
    features: dict[str, FeatureYaml]
    annotations: NotRequired[AnnotationsYaml]
    episodes: NotRequired[EpisodesYaml]


TOP_KEYS = ("fps", "primary", "tolerance_ms", "align", "clock", "features", "annotations", "episodes")
TOPIC_FEATURE_KEYS = ("topic", "field", "fields", "joints", "align", "tolerance_ms", "resize", "low", "high")
DERIVED_ACTION_KEYS = ("derive", "of", "low", "high")
ANNOTATION_KEYS = ("topic", "file")
EPISODE_KEYS = {
    "bag": ("split", "min_steps"),
    "marker": ("split", "topic", "min_steps"),
    "gap": ("split", "gap_s", "min_steps"),
}
DEFAULT_TOLERANCE_MS = 50.0
DEFAULT_MIN_STEPS = 1


# --------------------------------------------------------------------------------------------------
# The validated mapping


@dataclass(frozen=True)
class TopicFeature:
    """A feature read from one topic: ``fields`` are dotted paths into the message (empty: the whole
    message, e.g. an image), aligned onto the step clock by ``align`` within ``tolerance_ns``."""

    name: str
    topic: str
    fields: tuple[str, ...]
    align: AlignMethod
    tolerance_ns: int
    joints: tuple[str, ...] | None = None
    resize: tuple[int, int] | None = None  # (width, height)
    low: tuple[float, ...] | None = None
    high: tuple[float, ...] | None = None

    @property
    def is_image(self) -> bool:
        return self.name.startswith(IMAGE_PREFIX)


@dataclass(frozen=True)
class DerivedAction:
    """The action derived from the next observation of feature ``of``: its value (``next``) or its change
    (``delta``); the last observation of an episode has no action, as always."""

    of: str
    derive: Derive
    low: tuple[float, ...] | None = None
    high: tuple[float, ...] | None = None


@dataclass(frozen=True)
class ConvertMapping:
    path: Path
    fps: float
    primary: str
    tolerance_ns: int
    clock: Clock
    features: dict[str, TopicFeature]
    action: TopicFeature | DerivedAction
    annotation_topic: str | None
    annotation_file: str | None
    split: SplitKind
    marker_topic: str | None
    gap_ns: int | None
    min_steps: int
    digest: str
    """sha256 of the mapping's content: a dataset converted with another mapping is not resumed."""

    @property
    def period_ns(self) -> int:
        return round(1e9 / self.fps)

    @property
    def topic_features(self) -> list[TopicFeature]:
        """Every feature read from a topic, the action included when it is."""
        return [*self.features.values(), *([self.action] if isinstance(self.action, TopicFeature) else [])]

    @property
    def topics(self) -> list[str]:
        """Every topic the mapping reads."""
        topics = [f.topic for f in self.topic_features]
        topics += [t for t in (self.annotation_topic, self.marker_topic) if t]
        return sorted(set(topics))


# --------------------------------------------------------------------------------------------------
# Loading


def _duplicate_key(node: yaml.Node | None, prefix: str = "") -> tuple[str, int, int] | None:
    """The first key given twice in one YAML mapping (plain YAML silently keeps the last one): its dotted
    path and both lines."""
    if isinstance(node, yaml.MappingNode):
        seen: dict[str, int] = {}
        for key_node, value_node in node.value:
            key = f"{prefix}{key_node.value}"
            line = key_node.start_mark.line + 1
            if key in seen:
                return key, seen[key], line
            seen[key] = line
            found = _duplicate_key(value_node, f"{key}.")
            if found:
                return found
    elif isinstance(node, yaml.SequenceNode):
        for i, item in enumerate(node.value):
            found = _duplicate_key(item, f"{prefix}{i}.")
            if found:
                return found
    return None


def read_yaml(path: Path, what: str = "mapping") -> Any:
    """A YAML (or JSON) file's content; `MappingError` naming a key given twice, or the YAML error."""
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as error:
        raise MappingError(path, None, f"cannot read: {error.strerror or error}", what) from None
    try:
        duplicate = _duplicate_key(yaml.compose(text, Loader=yaml.SafeLoader))
        if duplicate:
            key, first, second = duplicate
            raise MappingError(path, key, f"given twice (lines {first} and {second})", what)
        return yaml.safe_load(text)
    except yaml.YAMLError as error:
        raise MappingError(path, None, f"not valid YAML: {error}", what) from None


def load_mapping(path: str | Path) -> ConvertMapping:
    """The validated mapping in ``path``; MappingError naming the file and key otherwise."""
    path = Path(path)
    return parse_mapping(read_yaml(path), path)


def parse_mapping(raw: Any, path: Path) -> ConvertMapping:
    """Validate the YAML content ``raw`` of the mapping file ``path``."""
    top = _mapping(raw, path, None)
    _known_keys(top, TOP_KEYS, path, None)
    fps = _positive(top.get("fps"), path, "fps")
    tolerance_ms = _positive(top.get("tolerance_ms", DEFAULT_TOLERANCE_MS), path, "tolerance_ms")
    align = _choice(top.get("align", "nearest"), ALIGN_METHODS, path, "align")
    clock = _choice(top.get("clock", "header"), CLOCKS, path, "clock")
    features_raw = _mapping(top.get("features"), path, "features")
    if not features_raw:
        raise MappingError(path, "features", "no features named")
    features: dict[str, TopicFeature] = {}
    action: TopicFeature | DerivedAction | None = None
    for name, spec in features_raw.items():
        key = f"features.{name}"
        if not isinstance(name, str) or not _valid_feature_name(name):
            raise MappingError(
                path, key, f"unknown feature name (expected {IMAGE_PREFIX}<camera>, {STATE} or {ACTION})"
            )
        spec = _mapping(spec, path, key)
        if name == ACTION and ("derive" in spec or "of" in spec):
            action = _derived_action(spec, path, key)
            continue
        feature = _topic_feature(name, spec, path, key, align, tolerance_ms)
        if name == ACTION:
            action = feature
        else:
            features[name] = feature
    if action is None:
        raise MappingError(
            path, f"features.{ACTION}", "missing (a topic, or {derive: next, of: observation.state})"
        )
    if isinstance(action, DerivedAction) and action.of not in features:
        raise MappingError(path, f"features.{ACTION}.of", f"{action.of!r} is not a feature of this mapping")
    if isinstance(action, DerivedAction) and features[action.of].is_image:
        raise MappingError(path, f"features.{ACTION}.of", "an action cannot be derived from an image")
    primary = top.get("primary")
    if primary is None:
        raise MappingError(path, "primary", "missing (the feature whose clock the steps follow)")
    if primary not in features:
        raise MappingError(
            path, "primary", f"{primary!r} is not one of the observation features {sorted(features)}"
        )
    annotations = _mapping(top.get("annotations", {}), path, "annotations")
    _known_keys(annotations, ANNOTATION_KEYS, path, "annotations")
    annotation_topic = _optional_str(annotations.get("topic"), path, "annotations.topic")
    annotation_file = _optional_str(annotations.get("file"), path, "annotations.file")
    episodes = _mapping(top.get("episodes", {"split": "bag"}), path, "episodes")
    split = _choice(episodes.get("split", "bag"), SPLITS, path, "episodes.split")
    _known_keys(episodes, EPISODE_KEYS[split], path, "episodes")
    marker_topic = None
    gap_ns = None
    if split == "marker":
        marker_topic = _optional_str(episodes.get("topic"), path, "episodes.topic")
        if marker_topic is None:
            raise MappingError(path, "episodes.topic", "missing (the topic whose messages start an episode)")
    if split == "gap":
        gap_ns = round(_positive(episodes.get("gap_s"), path, "episodes.gap_s") * 1e9)
    min_steps = episodes.get("min_steps", DEFAULT_MIN_STEPS)
    if isinstance(min_steps, bool) or not isinstance(min_steps, int) or min_steps < 1:
        raise MappingError(path, "episodes.min_steps", f"must be a whole number >= 1, got {min_steps!r}")
    digest = hashlib.sha256(json.dumps(raw, sort_keys=True, default=str).encode()).hexdigest()
    return ConvertMapping(
        path=path,
        fps=fps,
        primary=primary,
        tolerance_ns=round(tolerance_ms * 1e6),
        clock=clock,
        features=features,
        action=action,
        annotation_topic=annotation_topic,
        annotation_file=annotation_file,
        split=split,
        marker_topic=marker_topic,
        gap_ns=gap_ns,
        min_steps=min_steps,
        digest=digest,
    )


def _valid_feature_name(name: str) -> bool:
    return (name.startswith(IMAGE_PREFIX) and len(name) > len(IMAGE_PREFIX)) or name in (STATE, ACTION)


def _topic_feature(
    name: str, spec: MappingType[str, Any], path: Path, key: str, align: AlignMethod, tolerance_ms: float
) -> TopicFeature:
    _known_keys(spec, TOPIC_FEATURE_KEYS, path, key)
    topic = _optional_str(spec.get("topic"), path, f"{key}.topic")
    if topic is None:
        raise MappingError(path, f"{key}.topic", "missing (the topic this feature is read from)")
    if "field" in spec and "fields" in spec:
        raise MappingError(path, key, "give 'field' or 'fields', not both")
    if "fields" in spec:
        fields = spec["fields"]
        if not isinstance(fields, list) or not fields or not all(isinstance(f, str) and f for f in fields):
            raise MappingError(
                path, f"{key}.fields", f"must be a non-empty list of field paths, got {fields!r}"
            )
    elif "field" in spec:
        field = _optional_str(spec["field"], path, f"{key}.field")
        fields = [field] if field else []
    else:
        fields = []
    if len(set(fields)) != len(fields):
        raise MappingError(path, f"{key}.fields", "a field is named twice")
    is_image = name.startswith(IMAGE_PREFIX)
    if is_image and fields:
        raise MappingError(path, key, "an image feature takes the whole message; no 'field'")
    if not is_image and not fields:
        raise MappingError(
            path, f"{key}.field", "missing (which numeric field(s) of the message, e.g. position)"
        )
    if not is_image and "resize" in spec:
        raise MappingError(path, f"{key}.resize", "only an image feature can be resized")
    feature_align = _choice(spec.get("align", align), ALIGN_METHODS, path, f"{key}.align")
    if is_image and feature_align == "linear":
        raise MappingError(path, f"{key}.align", "linear interpolation is for numeric features, not images")
    tolerance = _positive(spec.get("tolerance_ms", tolerance_ms), path, f"{key}.tolerance_ms")
    joints = spec.get("joints")
    if joints is not None and (
        not isinstance(joints, list) or not joints or not all(isinstance(j, str) for j in joints)
    ):
        raise MappingError(path, f"{key}.joints", f"must be a non-empty list of joint names, got {joints!r}")
    resize = None
    if "resize" in spec:
        size = _mapping(spec["resize"], path, f"{key}.resize")
        _known_keys(size, ("width", "height"), path, f"{key}.resize")
        width, height = (size.get(k) for k in ("width", "height"))
        if not all(isinstance(v, int) and not isinstance(v, bool) and v > 0 for v in (width, height)):
            raise MappingError(path, f"{key}.resize", f"needs whole width and height > 0, got {dict(size)}")
        resize = (int(width), int(height))  # type: ignore[arg-type]
    if name != ACTION and ("low" in spec or "high" in spec):
        raise MappingError(path, key, "only the action takes bounds (low, high)")
    return TopicFeature(
        name=name,
        topic=topic,
        fields=tuple(fields),
        align=feature_align,
        tolerance_ns=round(tolerance * 1e6),
        joints=None if joints is None else tuple(joints),
        resize=resize,
        low=_bounds(spec.get("low"), path, f"{key}.low"),
        high=_bounds(spec.get("high"), path, f"{key}.high"),
    )


def _derived_action(spec: MappingType[str, Any], path: Path, key: str) -> DerivedAction:
    _known_keys(spec, DERIVED_ACTION_KEYS, path, key)
    of = _optional_str(spec.get("of"), path, f"{key}.of")
    if of is None:
        raise MappingError(path, f"{key}.of", "missing (the feature whose next value is the action)")
    derive = _choice(spec.get("derive", "next"), DERIVES, path, f"{key}.derive")
    return DerivedAction(
        of,
        derive,
        _bounds(spec.get("low"), path, f"{key}.low"),
        _bounds(spec.get("high"), path, f"{key}.high"),
    )


def _mapping(value: Any, path: Path, key: str | None) -> MappingType[str, Any]:
    if value is None and key is not None:
        raise MappingError(path, key, "missing")
    if not isinstance(value, MappingType):
        raise MappingError(path, key, f"must be a mapping, got {type(value).__name__}")
    return value


def _known_keys(value: MappingType[str, Any], known: tuple[str, ...], path: Path, key: str | None) -> None:
    for name in value:
        if name not in known:
            where = f"{key}.{name}" if key else str(name)
            raise MappingError(path, where, f"unknown key (expected one of {', '.join(known)})")


def _positive(value: Any, path: Path, key: str) -> float:
    if value is None:
        raise MappingError(path, key, "missing")
    if (
        isinstance(value, bool)
        or not isinstance(value, int | float)
        or not math.isfinite(value)
        or value <= 0
    ):
        raise MappingError(path, key, f"must be a positive number, got {value!r}")
    return float(value)


def _choice(value: Any, choices: tuple[str, ...], path: Path, key: str) -> Any:
    if value not in choices:
        raise MappingError(path, key, f"{value!r} is not one of {', '.join(choices)}")
    return value


def _optional_str(value: Any, path: Path, key: str) -> str | None:
    if value is None:
        return None
    if not isinstance(value, str) or not value:
        raise MappingError(path, key, f"must be a non-empty string, got {value!r}")
    return value


def _bounds(value: Any, path: Path, key: str) -> tuple[float, ...] | None:
    if value is None:
        return None
    if not isinstance(value, list) or not all(
        isinstance(v, int | float) and not isinstance(v, bool) for v in value
    ):
        raise MappingError(path, key, f"must be a list of numbers, got {value!r}")
    return tuple(float(v) for v in value)
