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

from playseg_core.data.features import ACTION, IMAGE_PREFIX, STATE
from playseg_core.domains import has_domain_package
from playseg_core.yaml_io import YamlFileError, load_yaml
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
    allow_outside_bag: bool  # a relative ``file`` may lead out of the bag's directory


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
    domain: NotRequired[str]


TOP_KEYS = (
    "fps", "primary", "tolerance_ms", "align", "clock", "features", "annotations", "episodes", "domain",
)  # fmt: skip
TOPIC_FEATURE_KEYS = ("topic", "field", "fields", "joints", "align", "tolerance_ms", "resize", "low", "high")
DERIVED_ACTION_KEYS = ("derive", "of", "low", "high")
ANNOTATION_KEYS = ("topic", "file", "allow_outside_bag")
EPISODE_KEYS = {
    "bag": ("split", "min_steps"),
    "marker": ("split", "topic", "min_steps"),
    "gap": ("split", "gap_s", "min_steps"),
}
DEFAULT_TOLERANCE_MS = 50.0
DEFAULT_MIN_STEPS = 1
MIN_FPS, MAX_FPS = 1e-3, 1000.0
MAX_SECONDS = 1e9
"""The longest tolerance or episode gap, in seconds: in nanoseconds still far inside int64."""
MAX_IMAGE_SIDE = 4096
"""The widest or tallest ``resize``: a frame of 4096 x 4096 RGB is 48 MB already."""


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
    annotation_file_outside_bag: bool
    split: SplitKind
    marker_topic: str | None
    gap_ns: int | None
    min_steps: int
    digest: str
    """sha256 of the mapping's content: a dataset converted with another mapping is not resumed."""
    domain: str | None = None
    """The world the bags record (a playseg_core.domains package), stamped on the dataset so that
    training uses its encoders and symmetries; None: a robot without a domain package (generic ones)."""

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


def read_yaml(path: Path, what: str = "mapping") -> Any:
    """A YAML (or JSON) file's content through the project's safe loader (limits on size, depth and
    aliases; a key given twice is an error); `MappingError` naming the file and the entry otherwise."""
    try:
        return load_yaml(path, what)
    except YamlFileError as error:
        raise MappingError(error.path, error.key, error.detail, what) from None


def load_mapping(path: str | Path) -> ConvertMapping:
    """The validated mapping in ``path``; MappingError naming the file and key otherwise."""
    path = Path(path)
    return parse_mapping(read_yaml(path), path)


def parse_mapping(raw: Any, path: Path) -> ConvertMapping:
    """Validate the YAML content ``raw`` of the mapping file ``path``."""
    top = _mapping(raw, path, None)
    _known_keys(top, TOP_KEYS, path, None)
    fps = _positive(top.get("fps"), path, "fps", MAX_FPS, least=MIN_FPS)
    tolerance_ms = _positive(
        top.get("tolerance_ms", DEFAULT_TOLERANCE_MS), path, "tolerance_ms", MAX_SECONDS * 1e3
    )
    align = _choice(top.get("align", "nearest"), ALIGN_METHODS, path, "align")
    clock = _choice(top.get("clock", "header"), CLOCKS, path, "clock")
    features_raw = _mapping(top.get("features"), path, "features")
    if not features_raw:
        raise MappingError(path, "features", "no features named")
    features: dict[str, TopicFeature] = {}
    action: TopicFeature | DerivedAction | None = None
    for name, spec in features_raw.items():
        key = _key("features", name)
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
        raise MappingError(
            path, f"features.{ACTION}.of", f"{_show(action.of)} is not a feature of this mapping"
        )
    if isinstance(action, DerivedAction) and features[action.of].is_image:
        raise MappingError(path, f"features.{ACTION}.of", "an action cannot be derived from an image")
    primary = top.get("primary")
    if primary is None:
        raise MappingError(path, "primary", "missing (the feature whose clock the steps follow)")
    if not isinstance(primary, str) or primary not in features:
        raise MappingError(
            path, "primary", f"{_show(primary)} is not one of the observation features {sorted(features)}"
        )
    annotations = _mapping(top.get("annotations", {}), path, "annotations")
    _known_keys(annotations, ANNOTATION_KEYS, path, "annotations")
    annotation_topic = _optional_str(annotations.get("topic"), path, "annotations.topic")
    annotation_file = _optional_str(annotations.get("file"), path, "annotations.file")
    outside_bag = annotations.get("allow_outside_bag", False)
    if not isinstance(outside_bag, bool):
        raise MappingError(
            path, "annotations.allow_outside_bag", f"must be true or false, got {_show(outside_bag)}"
        )
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
        gap_ns = round(_positive(episodes.get("gap_s"), path, "episodes.gap_s", MAX_SECONDS) * 1e9)
    min_steps = episodes.get("min_steps", DEFAULT_MIN_STEPS)
    if isinstance(min_steps, bool) or not isinstance(min_steps, int) or min_steps < 1:
        raise MappingError(path, "episodes.min_steps", f"must be a whole number >= 1, got {_show(min_steps)}")
    domain = _optional_str(top.get("domain"), path, "domain")
    if domain is not None and not has_domain_package(domain):
        raise MappingError(
            path, "domain", f"unknown domain {_show(domain)} (no playseg_core.domains package)"
        )
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
        annotation_file_outside_bag=outside_bag,
        split=split,
        marker_topic=marker_topic,
        gap_ns=gap_ns,
        min_steps=min_steps,
        digest=digest,
        domain=domain,
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
                path, f"{key}.fields", f"must be a non-empty list of field paths, got {_show(fields)}"
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
    tolerance = _positive(
        spec.get("tolerance_ms", tolerance_ms), path, f"{key}.tolerance_ms", MAX_SECONDS * 1e3
    )
    joints = spec.get("joints")
    if joints is not None and (
        not isinstance(joints, list) or not joints or not all(isinstance(j, str) for j in joints)
    ):
        raise MappingError(
            path, f"{key}.joints", f"must be a non-empty list of joint names, got {_show(joints)}"
        )
    resize = None
    if "resize" in spec:
        size = _mapping(spec["resize"], path, f"{key}.resize")
        _known_keys(size, ("width", "height"), path, f"{key}.resize")
        width, height = (size.get(k) for k in ("width", "height"))
        if not all(
            isinstance(v, int) and not isinstance(v, bool) and 0 < v <= MAX_IMAGE_SIDE
            for v in (width, height)
        ):
            raise MappingError(
                path,
                f"{key}.resize",
                f"needs whole width and height from 1 to {MAX_IMAGE_SIDE}, got {_show(dict(size))}",
            )
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
            where = _key(key, name)
            raise MappingError(path, where, f"unknown key (expected one of {', '.join(known)})")


def _positive(value: Any, path: Path, key: str, most: float, least: float = 0.0) -> float:
    """A number above 0 in [least, most]: a bound keeps every derived nanosecond count inside int64 (and a huge
    YAML integer, which float() cannot hold, is an error here rather than an OverflowError later)."""
    if value is None:
        raise MappingError(path, key, "missing")
    number = _finite(value)
    if number is None or not 0 < number <= most or number < least:
        range_text = f"from {least:g} to {most:g}" if least else f"up to {most:g}"
        raise MappingError(path, key, f"must be a positive number {range_text}, got {_show(value)}")
    return number


def _finite(value: Any) -> float | None:
    """``value`` as a finite float; None for anything else (a bool, a string, NaN, inf, an int past float)."""
    if isinstance(value, bool) or not isinstance(value, int | float):
        return None
    try:
        number = float(value)
    except OverflowError:
        return None
    return number if math.isfinite(number) else None


def _key(prefix: str | None, name: Any) -> str:
    """The dotted key of ``name`` under ``prefix``; a long name cut short (it may be a whole line of a file
    that is not a mapping at all)."""
    text = str(name) if len(str(name)) <= 60 else str(name)[:57] + "..."
    return f"{prefix}.{text}" if prefix else text


def _show(value: Any) -> str:
    """``value`` for an error message, cut short: a wrong value may be a whole list or mapping."""
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def _choice(value: Any, choices: tuple[str, ...], path: Path, key: str) -> Any:
    if value not in choices:
        raise MappingError(path, key, f"{_show(value)} is not one of {', '.join(choices)}")
    return value


def _optional_str(value: Any, path: Path, key: str) -> str | None:
    if value is None:
        return None
    if not isinstance(value, str) or not value:
        raise MappingError(path, key, f"must be a non-empty string, got {_show(value)}")
    return value


def _bounds(value: Any, path: Path, key: str) -> tuple[float, ...] | None:
    if value is None:
        return None
    numbers = [_finite(v) for v in value] if isinstance(value, list) else [None]
    if any(n is None for n in numbers):
        raise MappingError(path, key, f"must be a list of finite numbers, got {_show(value)}")
    return tuple(numbers)  # type: ignore[arg-type]
