"""The training-dataset format: versioned, memory-mapped, split by episode (see docs/dataset-format.md).

Layout of a dataset directory (format version 2)::

    meta/info.json           format name and version, the feature schema (data/features.py), array files,
                             counts, instructions, domain, free-form meta
    meta/episodes.jsonl      one JSON object per episode: id, split, offsets into the arrays
    data/<feature>.bin       one flat file per feature, e.g. data/observation.images.front.bin
                             (sum of T+1, H, W, 3) uint8, data/observation.state.bin (sum of T+1, ...),
                             data/action.bin (sum of T, ...) float32; C order
    data/segments.npy        structured table: episode, start, end, instruction, confidence, log_prob
    data/timestamp.bin       (sum of T+1,) float64: each observation's recording time in seconds from its
                             source's start (absent in older datasets: read as step / fps)

Each episode's boundary observations are stored once (T+1 per episode); segments are half-open step
ranges into their episode. Arrays are opened with ``np.memmap`` so a corpus larger than RAM loads lazily.
Version 1 (one unnamed camera in data/frames.bin, data/states.bin, data/actions.bin) is read as well:
see `_features_of_version_1`.
"""

from __future__ import annotations

import json
import os
import shutil
from collections.abc import Iterator, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from playseg_core.data.episode import Episode, Segment
from playseg_core.data.features import (
    ACTION,
    DEFAULT_CAMERA,
    STATE,
    Feature,
    FeatureError,
    Features,
    conform_episode,
    infer_features,
)
from playseg_core.data.splits import ANNOTATED_SPLITS, SPLITS
from playseg_core.errors import PlaysegError

FORMAT_NAME = "playseg-dataset"
FORMAT_VERSION = 2
READABLE_VERSIONS = (1, 2)

INFO_FILE = "meta/info.json"
EPISODES_FILE = "meta/episodes.jsonl"
SEGMENTS_FILE = "data/segments.npy"
TIMESTAMP = "timestamp"
"""The `arrays` entry of the per-observation recording times (not a feature: no model reads it)."""
VERSION_1_FILES = {"frames": DEFAULT_CAMERA, "states": STATE, "actions": ACTION}
"""Version 1 array names -> the feature each one is."""


def is_dataset(path: str | os.PathLike[str]) -> bool:
    """Whether ``path`` holds a playseg dataset (any format version): its meta/info.json says so."""
    try:
        info = json.loads((Path(path) / INFO_FILE).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return False
    return isinstance(info, dict) and info.get("format") == FORMAT_NAME


def check_out_apart(
    out: str | os.PathLike[str], source: str | os.PathLike[str], option: str = "--out"
) -> None:
    """Refuse an output directory that is, holds or lies inside an input: writing (or replacing) the output
    would destroy the input."""
    out, source = Path(out).resolve(), Path(source).resolve()
    if out == source or source in out.parents or out in source.parents:
        raise PlaysegError(f"{option} {out}: overlaps the input {source}; choose another directory")


def _remove_stale_staging(path: Path) -> list[Path]:
    """Remove ``.NAME.partial-PID`` siblings of ``path`` whose writing process no longer exists."""
    removed = []
    for staging in path.parent.glob(f".{path.name}.partial-*"):
        pid = staging.name.rsplit("-", 1)[-1]
        if not pid.isdigit() or int(pid) == os.getpid():
            continue
        try:
            os.kill(int(pid), 0)
            continue  # still running: another writer's
        except ProcessLookupError:
            pass
        except PermissionError:
            continue  # a live process of another user
        shutil.rmtree(staging, ignore_errors=True)
        removed.append(staging)
    return removed


def array_file(feature: str) -> str:
    """Where a feature's flat array lies inside a dataset directory."""
    return f"data/{feature}.bin"


UNLABELLED = -1
"""Instruction index of a segment without a label."""

SEGMENT_DTYPE = np.dtype(
    [
        ("episode", "<i8"),
        ("start", "<i8"),
        ("end", "<i8"),
        ("instruction", "<i4"),
        ("confidence", "<f4"),
        ("log_prob", "<f4"),
    ]
)


class DatasetError(PlaysegError):
    """A dataset on disk is missing a file or contradicts its own metadata."""


@dataclass(frozen=True)
class EpisodeRecord:
    """One line of meta/episodes.jsonl: where an episode's data lies in the flat arrays."""

    index: int
    episode_id: str
    split: str
    num_steps: int
    observation_start: int  # first row of its observations (version 1 called it frame_start)
    step_start: int
    segment_start: int
    num_segments: int
    extra: dict[str, Any]
    source: dict[str, Any] | None = None  # where it was recorded (`Episode.source`)

    def to_json(self) -> str:
        fields = asdict(self)
        extra = fields.pop("extra")
        if fields["source"] is None:
            del fields["source"]
        return json.dumps({**fields, "extra": extra}, sort_keys=True)


# --------------------------------------------------------------------------------------------------
# Writing


class DatasetWriter:
    """Streams episodes into a new dataset directory.

    Arrays are appended to flat files in a temporary sibling directory; ``close()`` writes the segment
    table and meta/info.json and renames the directory into place, so ``path`` never holds a
    half-written dataset. Leaving the ``with`` block through an exception discards everything.

    ``features`` is the schema every episode must follow (FeatureError naming the episode and feature
    otherwise); when None it is taken from the first episode, with a continuous action. ``domain`` names
    the world the data comes from when it is a known one (its step encoders and policy may be used).

    ``overwrite`` replaces only a previous playseg dataset, never another directory. Staging directories
    left by a killed writer of the same dataset (their process is gone) are removed on start
    (`removed_stale` lists them).
    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        instructions: Sequence[str],
        meta: dict[str, Any] | None = None,
        overwrite: bool = False,
        features: Features | None = None,
        domain: str | None = None,
    ) -> None:
        self.path = Path(path)
        if self.path.exists():
            if not overwrite:
                raise FileExistsError(f"{self.path}: exists; replace it only with overwrite (--overwrite)")
            if not is_dataset(self.path):
                raise FileExistsError(
                    f"{self.path}: exists and is not a playseg dataset; refusing to replace it"
                )
        self.instructions = tuple(instructions)
        if len(set(self.instructions)) != len(self.instructions):
            raise PlaysegError("DatasetWriter: instructions contain duplicates")
        self._instruction_index = {text: i for i, text in enumerate(self.instructions)}
        self.meta = dict(meta or {})
        self.features = features
        self.domain = domain
        self.overwrite = overwrite
        self.removed_stale = _remove_stale_staging(self.path)
        self._tmp = self.path.with_name(f".{self.path.name}.partial-{os.getpid()}")
        if self._tmp.exists():
            shutil.rmtree(self._tmp)
        (self._tmp / "meta").mkdir(parents=True)
        (self._tmp / "data").mkdir()
        self._files: dict[str, Any] = {}
        self._episodes_file = open(self._tmp / EPISODES_FILE, "w", encoding="utf-8")  # noqa: SIM115
        self._ids: set[str] = set()
        self._segments: list[tuple[int, int, int, int, float, float]] = []
        self._num_observations = 0
        self._num_steps = 0
        self._split_counts = {name: {"episodes": 0, "steps": 0, "segments": 0} for name in SPLITS}
        self._closed = False

    def __enter__(self) -> DatasetWriter:
        return self

    def __exit__(self, exc_type: object, exc: object, tb: object) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()

    @property
    def num_episodes(self) -> int:
        return len(self._ids)

    @property
    def staging_dir(self) -> Path:
        """Where the dataset is written until ``close`` renames it into place: files a caller adds here
        (e.g. a bag of the same run) appear with the dataset, or not at all."""
        return self._tmp

    @property
    def split_counts(self) -> dict[str, dict[str, int]]:
        """Episodes, steps and segments written so far, per split."""
        return {name: dict(counts) for name, counts in self._split_counts.items()}

    def add(self, episode: Episode, split: str, extra: dict[str, Any] | None = None) -> int:
        """Append ``episode`` to ``split``; returns its index in the dataset.

        ``episode.segments`` are stored as its ground truth (``play``/``test`` loaders hide them).
        ``extra`` (JSON-serialisable) is kept in the episode's meta/episodes.jsonl line, with
        ``episode.source``. ``episode.timestamps`` are stored; without them, step / fps (step / 1 without fps).
        """
        if self._closed:
            raise RuntimeError(f"{self.path}: DatasetWriter is closed")
        name = f"episode {episode.episode_id!r}"
        if split not in SPLITS:
            raise PlaysegError(f"{name}: unknown split {split!r} (expected one of {SPLITS})")
        if episode.episode_id in self._ids:
            raise PlaysegError(f"{name}: episode_id already written to this dataset")
        if self.features is None:
            self.features = infer_features(episode)
        episode = conform_episode(episode, self.features)
        self.features.check_episode(episode)
        actions = episode.actions
        labels = []
        for seg in episode.segments:
            if seg.instruction == "":
                labels.append(UNLABELLED)
            elif seg.instruction in self._instruction_index:
                labels.append(self._instruction_index[seg.instruction])
            else:
                raise PlaysegError(
                    f"{name}: segment [{seg.start}, {seg.end}) field 'instruction' {seg.instruction!r} "
                    "is not in the dataset's instruction list"
                )
        arrays = {**episode.images, ACTION: actions}
        if episode.state is not None:
            arrays[STATE] = episode.state
        for feature, array in arrays.items():
            if feature not in self._files:
                self._files[feature] = open(self._tmp / array_file(feature), "wb")  # noqa: SIM115
            self._files[feature].write(np.ascontiguousarray(array).data)
        times = episode.timestamps
        if times is None:
            times = np.arange(episode.num_steps + 1) / (self.features.fps or 1.0)
        if TIMESTAMP not in self._files:
            self._files[TIMESTAMP] = open(self._tmp / array_file(TIMESTAMP), "wb")  # noqa: SIM115
        self._files[TIMESTAMP].write(np.ascontiguousarray(times, dtype="<f8").data)
        index = len(self._ids)
        record = EpisodeRecord(
            index=index,
            episode_id=episode.episode_id,
            split=split,
            num_steps=episode.num_steps,
            observation_start=self._num_observations,
            step_start=self._num_steps,
            segment_start=len(self._segments),
            num_segments=len(episode.segments),
            extra=dict(extra or {}),
            source=episode.source,
        )
        for seg, label in zip(episode.segments, labels, strict=True):
            self._segments.append((index, seg.start, seg.end, label, seg.confidence, seg.log_prob))
        self._episodes_file.write(record.to_json() + "\n")
        self._ids.add(episode.episode_id)
        self._num_observations += episode.num_steps + 1
        self._num_steps += episode.num_steps
        counts = self._split_counts[split]
        counts["episodes"] += 1
        counts["steps"] += episode.num_steps
        counts["segments"] += len(episode.segments)
        return index

    def close(self) -> Path:
        """Write the metadata, then move the finished dataset to ``path``. Returns ``path``."""
        if self._closed:
            return self.path
        try:
            self._finish()
        except BaseException:
            self.abort()
            raise
        return self.path

    def _finish(self) -> None:
        if not self._ids or self.features is None:
            raise PlaysegError(f"{self.path}: no episodes were added; refusing to write an empty dataset")
        for handle in [*self._files.values(), self._episodes_file]:
            handle.flush()
            os.fsync(handle.fileno())
            handle.close()
        np.save(self._tmp / SEGMENTS_FILE, np.array(self._segments, dtype=SEGMENT_DTYPE))
        arrays = {}
        for name, feature in self.features.by_name.items():
            rows = self._num_steps if feature.kind == "action" else self._num_observations
            arrays[name] = {"file": array_file(name), "dtype": feature.dtype, "shape": [rows, *feature.shape]}
        arrays[TIMESTAMP] = {
            "file": array_file(TIMESTAMP),
            "dtype": "float64",
            "shape": [self._num_observations],
        }
        info = {
            "format": FORMAT_NAME,
            "format_version": FORMAT_VERSION,
            "domain": self.domain,
            "fps": self.features.fps,
            "features": self.features.to_json()["features"],
            "instructions": list(self.instructions),
            "arrays": arrays,
            "segments_file": SEGMENTS_FILE,
            "episodes_file": EPISODES_FILE,
            "counts": {
                "episodes": len(self._ids),
                "steps": self._num_steps,
                "observations": self._num_observations,
                "segments": len(self._segments),
                "splits": self._split_counts,
            },
            "meta": self.meta,
        }
        with open(self._tmp / INFO_FILE, "w", encoding="utf-8") as handle:
            json.dump(info, handle, indent=2)
            handle.write("\n")
        self._closed = True
        if self.path.exists():
            if not self.overwrite:
                raise FileExistsError(f"{self.path}: appeared while writing; the new dataset is discarded")
            old = self.path.with_name(f".{self.path.name}.old-{os.getpid()}")
            self.path.rename(old)
            self._tmp.rename(self.path)
            shutil.rmtree(old)
        else:
            self._tmp.rename(self.path)

    def abort(self) -> None:
        """Discard everything written so far."""
        self._closed = True
        for handle in [*self._files.values(), self._episodes_file]:
            handle.close()
        shutil.rmtree(self._tmp, ignore_errors=True)


# --------------------------------------------------------------------------------------------------
# Reading


def _fail(path: Path, message: str) -> DatasetError:
    return DatasetError(f"{path}: {message}")


class PlayDataset:
    """A dataset on disk. Arrays are memory-mapped; episodes are returned as core ``Episode`` objects."""

    def __init__(self, path: Path, info: dict[str, Any], records: list[EpisodeRecord]) -> None:
        self.path = path
        self.info = info
        self.records = records
        self.instructions: tuple[str, ...] = tuple(info["instructions"])
        self.format_version: int = info["format_version"]
        self.domain: str | None = info.get("domain")
        self.features, files = _features_and_files(path, info)
        self._arrays = self._open_arrays(files)
        self._timestamps = self._open_timestamps()
        self.segment_table: np.ndarray = self._load_segments()
        self._by_split = {name: [r.index for r in records if r.split == name] for name in SPLITS}

    @classmethod
    def open(cls, path: str | os.PathLike[str]) -> PlayDataset:
        """Open and validate the dataset at ``path`` (reads only metadata; arrays stay on disk)."""
        root = Path(path)
        if not root.is_dir():
            raise FileNotFoundError(f"{root}: no dataset directory here")
        info = _read_info(root)
        records = _read_episodes(root, info)
        return cls(root, info, records)

    # Pickling copies a memmap's data; a worker process reopens the files instead.
    def __getstate__(self) -> dict[str, Any]:
        return {"path": str(self.path)}

    def __setstate__(self, state: dict[str, Any]) -> None:
        other = PlayDataset.open(state["path"])
        self.__dict__.update(other.__dict__)

    def __len__(self) -> int:
        return len(self.records)

    @property
    def splits(self) -> tuple[str, ...]:
        """Names of the splits that hold at least one episode, in the order of SPLITS."""
        return tuple(name for name in SPLITS if self._by_split[name])

    def array(self, feature: str) -> np.ndarray:
        """All episodes' rows of ``feature``, memory-mapped (observations: sum of T+1 rows; action: sum of T)."""
        self.features[feature]  # FeatureError naming the feature when the dataset has no such feature
        return self._arrays[feature]

    def episode_indices(self, split: str) -> list[int]:
        """Indices of the episodes in ``split`` (empty when the split holds none)."""
        if split not in SPLITS:
            raise KeyError(f"{self.path}: unknown split {split!r} (expected one of {SPLITS})")
        return list(self._by_split[split])

    def segments(self, index: int, truth: bool = False) -> list[Segment]:
        """The segments of episode ``index`` that its split reveals (all of them with ``truth``)."""
        record = self.records[index]
        if not truth and record.split not in ANNOTATED_SPLITS:
            return []
        rows = self.segment_table[record.segment_start : record.segment_start + record.num_segments]
        return [
            Segment(
                int(row["start"]),
                int(row["end"]),
                "" if row["instruction"] == UNLABELLED else self.instructions[row["instruction"]],
                float(row["confidence"]),
                float(row["log_prob"]),
            )
            for row in rows
        ]

    def timestamps(self, index: int) -> np.ndarray:
        """Episode ``index``'s observation times in seconds from its source's start, (T+1,) float64 (a
        dataset written without them: step / fps)."""
        record = self.records[index]
        if self._timestamps is None:
            return np.arange(record.num_steps + 1) / (self.features.fps or 1.0)
        return self._timestamps[record.observation_start : record.observation_start + record.num_steps + 1]

    def episode(self, index: int, truth: bool = False) -> Episode:
        """Episode ``index`` with memory-mapped arrays (nothing is read until used)."""
        if not 0 <= index < len(self.records):
            raise IndexError(f"{self.path}: episode index {index} out of range (0..{len(self.records) - 1})")
        record = self.records[index]
        observations = slice(record.observation_start, record.observation_start + record.num_steps + 1)
        steps = slice(record.step_start, record.step_start + record.num_steps)
        state = self._arrays.get(STATE)
        return Episode(
            episode_id=record.episode_id,
            actions=self._arrays[ACTION][steps],
            images={name: self._arrays[name][observations] for name in self.features.cameras},
            state=None if state is None else state[observations],
            segments=self.segments(index, truth=truth),
            timestamps=self.timestamps(index),
            source=record.source,
        )

    def episodes(self, split: str, truth: bool = False) -> Iterator[Episode]:
        """The episodes of ``split`` in dataset order."""
        for index in self.episode_indices(split):
            yield self.episode(index, truth=truth)

    def _open_arrays(self, files: dict[str, str]) -> dict[str, np.ndarray]:
        counts = self.info["counts"]
        arrays = {}
        for name, relative in files.items():
            feature = self.features[name]
            file = self.path / relative
            rows = counts["steps"] if feature.kind == "action" else counts["observations"]
            field = f"{INFO_FILE} features.{name}"
            if not file.is_file():
                raise FileNotFoundError(f"{file}: missing (the array of {field})")
            dtype, shape = np.dtype(feature.dtype), (rows, *feature.shape)
            expected = int(np.prod(shape)) * dtype.itemsize
            actual = file.stat().st_size
            if actual != expected:
                raise _fail(
                    file,
                    f"size {actual} bytes, but {field} ({rows} rows of {list(feature.shape)} {dtype}) "
                    f"needs {expected} bytes",
                )
            if expected == 0:
                arrays[name] = np.zeros(shape, dtype)
            else:
                arrays[name] = np.memmap(file, dtype=dtype, mode="r", shape=shape)
        return arrays

    def _open_timestamps(self) -> np.ndarray | None:
        spec = self.info["arrays"].get(TIMESTAMP) if self.format_version >= 2 else None
        if spec is None:
            return None
        file, rows = self.path / str(spec.get("file")), self.info["counts"]["observations"]
        if not file.is_file():
            raise FileNotFoundError(f"{file}: missing (the array of {INFO_FILE} arrays.{TIMESTAMP})")
        if file.stat().st_size != rows * 8:
            raise _fail(file, f"size {file.stat().st_size} bytes, but {rows} observations need {rows * 8}")
        times = np.memmap(file, dtype="<f8", mode="r", shape=(rows,)) if rows else np.zeros(0)
        for record in self.records:
            own = times[record.observation_start : record.observation_start + record.num_steps + 1]
            if not np.all(np.isfinite(own)) or np.any(np.diff(own) < 0):
                name = f"episode {record.episode_id!r} (index {record.index})"
                raise _fail(file, f"{name}: timestamps are not finite and non-decreasing")
        return times

    def _load_segments(self) -> np.ndarray:
        file = self.path / self.info.get("segments_file", SEGMENTS_FILE)
        if not file.is_file():
            raise FileNotFoundError(f"{file}: missing (the segment table)")
        try:
            table = np.load(file, allow_pickle=False)
        except ValueError as error:
            raise _fail(file, f"unreadable segment table: {error}") from error
        if table.dtype != SEGMENT_DTYPE or table.ndim != 1:
            raise _fail(
                file, f"segment table has dtype {table.dtype} shape {table.shape}, expected {SEGMENT_DTYPE}"
            )
        if len(table) != self.info["counts"]["segments"]:
            raise _fail(
                file,
                f"{len(table)} segments, but {INFO_FILE} counts.segments = {self.info['counts']['segments']}",
            )
        for record in self.records:
            rows = table[record.segment_start : record.segment_start + record.num_segments]
            name = f"episode {record.episode_id!r} (index {record.index})"
            if len(rows) != record.num_segments or np.any(rows["episode"] != record.index):
                raise _fail(file, f"{name}: rows {record.segment_start}.. do not belong to this episode")
            if (
                np.any(rows["start"] < 0)
                or np.any(rows["end"] <= rows["start"])
                or np.any(rows["end"] > record.num_steps)
            ):
                raise _fail(file, f"{name}: a segment lies outside [0, {record.num_steps}] or is empty")
            if np.any(rows["instruction"] >= len(self.instructions)) or np.any(
                rows["instruction"] < UNLABELLED
            ):
                raise _fail(file, f"{name}: field 'instruction' outside the instruction list")
        return table


def _features_and_files(root: Path, info: dict[str, Any]) -> tuple[Features, dict[str, str]]:
    """The dataset's feature schema and the file of each feature, for either format version."""
    if info["format_version"] == 1:
        return _features_of_version_1(root, info)
    try:
        features = Features.from_json({"fps": info.get("fps"), "features": info["features"]})
    except FeatureError as error:
        raise _fail(root / INFO_FILE, str(error)) from None
    arrays = info.get("arrays", {})
    files = {}
    for name in features.by_name:
        spec = arrays.get(name)
        if not isinstance(spec, dict) or "file" not in spec:
            raise _fail(root / INFO_FILE, f"field arrays.{name}.file is missing")
        files[name] = str(spec["file"])
    return features, files


def _features_of_version_1(root: Path, info: dict[str, Any]) -> tuple[Features, dict[str, str]]:
    """Version 1 held one unnamed camera (`DEFAULT_CAMERA`), an optional state and the actions.

    It declared no action kind: actions of shape (1,) that are all whole numbers >= 0 read as discrete
    with max + 1 values (the only discrete action spaces version 1 held); anything else as continuous.
    """
    arrays, features, files = info["arrays"], [], {}
    for key, name in VERSION_1_FILES.items():
        if key not in arrays:
            if key != "states":
                raise _fail(root / INFO_FILE, f"field arrays.{key} is missing")
            continue
        spec = arrays[key]
        try:
            shape, dtype = tuple(int(n) for n in spec["shape"][1:]), str(np.dtype(spec["dtype"]))
            kind = {"frames": "image", "states": "state", "actions": "action"}[key]
            files[name] = str(spec["file"])
            features.append(Feature(name, kind, dtype, shape))  # type: ignore[arg-type]
        except (KeyError, TypeError, ValueError) as error:
            raise _fail(root / INFO_FILE, f"field arrays.{key} is malformed ({error})") from None
    try:
        schema = Features.of(features)
    except FeatureError as error:
        raise _fail(root / INFO_FILE, str(error)) from None
    action = schema.action
    if action.shape == (1,):
        file = root / files[ACTION]
        rows = int(info["counts"]["steps"])
        values = np.memmap(file, np.float32, "r", shape=(rows,)) if rows and file.is_file() else np.zeros(0)
        whole = values.size > 0 and bool(np.all((values >= 0) & (values == np.round(values))))
        if whole:
            schema = schema.with_action(
                Feature(ACTION, "action", "float32", (1,), num_values=int(values.max()) + 1)
            )
    return schema, files


def _read_info(root: Path) -> dict[str, Any]:
    file = root / INFO_FILE
    if not file.is_file():
        raise FileNotFoundError(f"{file}: missing (not a playseg dataset, or an unfinished one)")
    try:
        info = json.loads(file.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as error:
        raise _fail(file, f"not valid JSON: {error}") from error
    if not isinstance(info, dict):
        raise _fail(file, "top level must be a JSON object")
    if info.get("format") != FORMAT_NAME:
        raise _fail(file, f"field 'format' is {info.get('format')!r}, expected {FORMAT_NAME!r}")
    version = info.get("format_version")
    if version not in READABLE_VERSIONS:
        raise _fail(
            file,
            f"field 'format_version' is {version!r}; this playseg reads versions {list(READABLE_VERSIONS)}",
        )
    for field in ("instructions", "arrays", "counts") + (("features",) if version >= 2 else ()):
        if field not in info:
            raise _fail(file, f"field {field!r} is missing")
    if not isinstance(info["counts"], dict):
        raise _fail(file, "field 'counts' must be an object")
    if version == 1 and "frames" in info["counts"]:  # version 1 called observations frames
        info["counts"]["observations"] = info["counts"]["frames"]
    for field in ("episodes", "steps", "observations", "segments"):
        if not isinstance(info["counts"].get(field), int):
            raise _fail(file, f"field 'counts.{field}' is missing or not an integer")
    return info


def _read_episodes(root: Path, info: dict[str, Any]) -> list[EpisodeRecord]:
    file = root / info.get("episodes_file", EPISODES_FILE)
    if not file.is_file():
        raise FileNotFoundError(f"{file}: missing (the episode table)")
    records: list[EpisodeRecord] = []
    observation_start = step_start = segment_start = 0
    with open(file, encoding="utf-8") as handle:
        for line_number, line in enumerate(handle, start=1):
            where = f"line {line_number}"
            try:
                fields = json.loads(line)
                record = EpisodeRecord(
                    index=int(fields["index"]),
                    episode_id=str(fields["episode_id"]),
                    split=str(fields["split"]),
                    num_steps=int(fields["num_steps"]),
                    observation_start=int(fields.get("observation_start", fields.get("frame_start"))),
                    step_start=int(fields["step_start"]),
                    segment_start=int(fields["segment_start"]),
                    num_segments=int(fields["num_segments"]),
                    extra=dict(fields.get("extra", {})),
                    source=fields.get("source"),
                )
            except (json.JSONDecodeError, KeyError, TypeError, ValueError) as error:
                raise _fail(file, f"{where}: bad episode record ({type(error).__name__}: {error})") from error
            expected = (len(records), observation_start, step_start, segment_start)
            actual = (record.index, record.observation_start, record.step_start, record.segment_start)
            if actual != expected or record.num_steps < 0:
                raise _fail(
                    file,
                    f"{where} (episode {record.episode_id!r}): fields index/observation_start/step_start/"
                    f"segment_start are {actual}, expected {expected}",
                )
            if record.split not in SPLITS:
                raise _fail(
                    file, f"{where} (episode {record.episode_id!r}): field 'split' {record.split!r} unknown"
                )
            records.append(record)
            observation_start += record.num_steps + 1
            step_start += record.num_steps
            segment_start += record.num_segments
    counts = info["counts"]
    totals = {
        "episodes": len(records),
        "observations": observation_start,
        "steps": step_start,
        "segments": segment_start,
    }
    for field, total in totals.items():
        if counts[field] != total:
            raise _fail(file, f"adds up to {total} {field}, but {INFO_FILE} counts.{field} = {counts[field]}")
    return records
