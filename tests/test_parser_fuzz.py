"""Fuzzing the parsers of user files: the mapping, the annotation sidecar and the YAML loader under them.

Whatever the input (random structures and values, NaN, inf, huge and negative numbers, wrong types, deep
nesting, anchors and aliases, random YAML text), the result is a valid value or the project's one-line
error naming the file, never another exception, and never slow. Few examples in `make test`, 2000 each
in `make fuzz` (the profiles in conftest.py).
"""

from __future__ import annotations

import copy
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml
from hypothesis import given
from hypothesis import strategies as st
from test_convert import MAPPING

from playseg_core.yaml_io import YamlFileError, load_yaml
from playseg_ros.convert.annotations import TimedLabel, labels_from_file, segments_of_episodes
from playseg_ros.convert.errors import ConvertError, MappingError
from playseg_ros.convert.mapping import ConvertMapping, load_mapping

pytestmark = pytest.mark.fuzz

INT64 = 2**63 - 1

numbers = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True),
    st.integers(-(10**30), 10**30),
    st.sampled_from([0, -1, 1, 10**400, -(10**400), 1e300, -1e300, 5e-324, 4096, 4097]),
)
scalars = st.one_of(
    st.none(),
    st.booleans(),
    numbers,
    st.text(max_size=12),
    st.sampled_from(["nearest", "linear", "gap", "marker", "bag", "/topic", "position", "action"]),
)
values = st.recursive(
    scalars,
    lambda children: st.one_of(
        st.lists(children, max_size=4),
        st.dictionaries(st.one_of(st.text(max_size=8), st.sampled_from(["topic", "width", "split"])),
                        children, max_size=4),
    ),
    max_leaves=12,
)  # fmt: skip

MAPPING_PATHS: list[tuple[str, ...]] = [
    ("fps",), ("primary",), ("tolerance_ms",), ("align",), ("clock",), ("features",), ("annotations",),
    ("episodes",), ("unknown",),
    ("features", "observation.images.front"), ("features", "observation.images.front", "resize"),
    ("features", "observation.images.front", "resize", "width"),
    ("features", "observation.images.front", "tolerance_ms"),
    ("features", "observation.state", "field"), ("features", "observation.state", "joints"),
    ("features", "action", "fields"), ("features", "action", "low"), ("features", "action", "high"),
    ("features", "action", "derive"), ("features", "action", "of"), ("features", "observation.extra"),
    ("annotations", "file"), ("annotations", "allow_outside_bag"),
    ("episodes", "split"), ("episodes", "gap_s"), ("episodes", "min_steps"), ("episodes", "topic"),
]  # fmt: skip
VALID_MAPPING = dict(
    MAPPING,
    features=dict(
        MAPPING["features"],
        **{"observation.images.front": {"topic": "/camera/image_raw", "resize": {"width": 16, "height": 8}}},
    ),
)


@pytest.fixture(scope="module")
def work(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Path]:
    yield tmp_path_factory.mktemp("fuzz")


def _set(tree: dict[str, Any], path: tuple[str, ...], value: Any) -> None:
    """Put ``value`` at ``path`` (None: delete the key) where the parents are mappings."""
    for key in path[:-1]:
        tree = tree.get(key) if isinstance(tree, dict) else None  # type: ignore[assignment]
        if not isinstance(tree, dict):
            return
    if value is None:
        tree.pop(path[-1], None)
    else:
        tree[path[-1]] = value


def _check_mapping(path: Path) -> ConvertMapping | None:
    try:
        mapping = load_mapping(path)
    except MappingError as error:
        message = str(error)
        assert message.startswith(f"mapping {str(path)!r}") and "\n" not in message, message
        assert len(message) < 500, message
        return None
    assert 1 <= mapping.period_ns <= INT64 and 0 < mapping.tolerance_ns <= INT64
    assert mapping.gap_ns is None or 0 <= mapping.gap_ns <= INT64
    for feature in mapping.topic_features:
        assert 0 <= feature.tolerance_ns <= INT64
        assert feature.resize is None or all(1 <= side <= 4096 for side in feature.resize)
        for bound in (feature.low, feature.high):
            assert bound is None or all(np.isfinite(bound))
    return mapping


@pytest.mark.slow
@given(changes=st.lists(st.tuples(st.sampled_from(MAPPING_PATHS), st.one_of(st.none(), values)), max_size=4))
def test_any_mapping_gives_a_mapping_or_one_named_line(
    work: Path, changes: list[tuple[tuple[str, ...], Any]]
) -> None:
    raw = copy.deepcopy(VALID_MAPPING)
    for path, value in changes:
        _set(raw, path, value)
    file = work / "mapping.yaml"
    file.write_text(yaml.safe_dump(raw, sort_keys=False))
    mapping = _check_mapping(file)
    if not changes:
        assert mapping is not None


# YAML text made of the characters that carry its structure, anchors and aliases included
yaml_text = st.lists(
    st.one_of(
        st.sampled_from([": ", "- ", "[", "]", "{", "}", ", ", "\n", "  ", "&a ", "&b ", "*a", "*b", "<<: ",
                         "!!str ", "!!float ", "? ", "|\n", "'", '"', "#", ".inf", ".nan", "1e9", "-3",
                         "fps", "features", "annotations", "start", "end", "instruction", "\t", "\x00"]),
        st.text(max_size=3),
    ),
    max_size=40,
).map("".join)  # fmt: skip


@given(text=yaml_text)
def test_any_text_as_a_mapping_or_sidecar_is_a_value_or_one_named_line(work: Path, text: str) -> None:
    file = work / "text.yaml"
    file.write_text(text, encoding="utf-8", errors="surrogatepass")
    try:
        load_yaml(file)
    except YamlFileError as error:
        assert str(error).startswith(f"YAML file {str(file)!r}") and "\n" not in str(error)
    _check_mapping(file)
    _check_sidecar(file, 1_700_000_000 * 10**9)


@given(
    levels=st.integers(1, 12),
    fan_out=st.integers(1, 12),
    nested=st.integers(0, 80),
    duplicate=st.booleans(),
)
def test_anchors_and_aliases_never_hang_and_duplicates_are_found(
    work: Path, levels: int, fan_out: int, nested: int, duplicate: bool
) -> None:
    """Each anchor holds ``fan_out`` aliases of the one before (fan_out**levels values when expanded),
    inside ``nested`` brackets; a duplicate key inside the first anchor is found through every alias."""
    first = "{x: 1, x: 2}" if duplicate else "{x: 1}"
    lines = [f"a0: &a0 {first}"]
    for k in range(1, levels + 1):
        lines.append(f"a{k}: &a{k} {'[' * nested}[{', '.join([f'*a{k - 1}'] * fan_out)}]{']' * nested}")
    file = work / "aliases.yaml"
    file.write_text("\n".join(lines) + "\n")
    try:
        loaded = load_yaml(file)
    except YamlFileError as error:
        assert "\n" not in str(error)
        if "nested deeper than 64 levels" in str(error):  # what the text nests, or the aliases add
            assert nested + 3 > 64 or levels * (nested + 1) + 2 > 64, error
        elif duplicate:
            assert error.key == "a0.x" and "given twice" in str(error), error
        else:
            assert "its aliases expand to more than" in str(error) and fan_out**levels > 10**5, error
    else:
        assert not duplicate and loaded["a0"] == {"x": 1}


def _check_sidecar(file: Path, bag_start_ns: int) -> list[TimedLabel] | None:
    bag = Path("/bags/fuzzed")
    try:
        labels = labels_from_file(bag, file, bag_start_ns)
    except ConvertError as error:
        message = str(error)
        assert message.startswith(f"bag '{bag}': annotations file {str(file)!r}") and "\n" not in message
        assert len(message) < 500, message
        return None
    for label in labels:
        assert -INT64 <= label.start_ns <= label.end_ns <= INT64 and isinstance(label.instruction, str)
    return labels


entries = st.one_of(
    st.fixed_dictionaries(
        {"start": numbers, "end": numbers, "instruction": st.one_of(st.text(max_size=10), scalars)}
    ),
    st.fixed_dictionaries(
        {"start": st.floats(-10, 10), "end": st.floats(-10, 10), "instruction": st.text(max_size=5)}
    ),
    values,
)


@given(
    listed=st.lists(entries, max_size=6),
    times=st.one_of(st.sampled_from(["from_start", "absolute", None]), values),
    bare=st.booleans(),
    extra=st.one_of(st.none(), st.dictionaries(st.text(max_size=6), values, max_size=2)),
    bag_start_ns=st.integers(0, 4 * 10**18),
)
def test_any_sidecar_gives_labels_or_one_named_line(
    work: Path, listed: list[Any], times: Any, bare: bool, extra: dict | None, bag_start_ns: int
) -> None:
    raw: Any = listed
    if not bare:
        raw = {"annotations": listed, **({"times": times} if times is not None else {}), **(extra or {})}
    file = work / "labels.yaml"
    file.write_text(yaml.safe_dump(raw))
    labels = _check_sidecar(file, bag_start_ns)
    if labels:  # what the labels become must not fail either: two episodes of ten steps at 10 Hz
        steps = [bag_start_ns + np.arange(10, dtype=np.int64) * 10**8 + k * 2 * 10**9 for k in range(2)]
        segments, notes = segments_of_episodes(steps, labels)
        assert all(0 <= s.start < s.end < 10 for episode in segments for s in episode)
        assert all("\n" not in note for note in notes)
