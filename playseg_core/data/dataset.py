"""The training-dataset format: versioned, memory-mapped, split by episode (see docs/dataset-format.md).

Layout of a dataset directory::

    meta/info.json        format name and version, array shapes and dtypes, counts, instructions, meta
    meta/episodes.jsonl   one JSON object per episode: id, split, offsets into the arrays
    data/frames.bin       all episodes' frames, (sum of T+1, H, W, 3) uint8, C order
    data/states.bin       all episodes' states, (sum of T+1, *state_shape) (absent without states)
    data/actions.bin      all episodes' actions, (sum of T, action_dim) float32
    data/segments.npy     structured table: episode, start, end, instruction, confidence, log_prob

Each episode's boundary frames are stored once (T+1 frames per episode); segments are half-open step
ranges into their episode. Arrays are opened with ``np.memmap`` so a corpus larger than RAM loads lazily.
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
from playseg_core.data.splits import ANNOTATED_SPLITS, SPLITS

FORMAT_NAME = "playseg-dataset"
FORMAT_VERSION = 1

INFO_FILE = "meta/info.json"
EPISODES_FILE = "meta/episodes.jsonl"
SEGMENTS_FILE = "data/segments.npy"
ARRAY_FILES = {"frames": "data/frames.bin", "states": "data/states.bin", "actions": "data/actions.bin"}

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


class DatasetError(ValueError):
    """A dataset on disk is missing a file or contradicts its own metadata."""


@dataclass(frozen=True)
class EpisodeRecord:
    """One line of meta/episodes.jsonl: where an episode's data lies in the flat arrays."""

    index: int
    episode_id: str
    split: str
    num_steps: int
    frame_start: int
    step_start: int
    segment_start: int
    num_segments: int
    extra: dict[str, Any]

    def to_json(self) -> str:
        fields = asdict(self)
        extra = fields.pop("extra")
        return json.dumps({**fields, "extra": extra}, sort_keys=True)


# --------------------------------------------------------------------------------------------------
# Writing


class DatasetWriter:
    """Streams episodes into a new dataset directory.

    Arrays are appended to flat files in a temporary sibling directory; ``close()`` writes the segment
    table and meta/info.json and renames the directory into place, so ``path`` never holds a
    half-written dataset. Leaving the ``with`` block through an exception discards everything.
    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        instructions: Sequence[str],
        meta: dict[str, Any] | None = None,
        overwrite: bool = False,
    ) -> None:
        self.path = Path(path)
        if self.path.exists() and not overwrite:
            raise FileExistsError(
                f"{self.path}: dataset directory exists (pass overwrite=True to replace it)"
            )
        self.instructions = tuple(instructions)
        if len(set(self.instructions)) != len(self.instructions):
            raise ValueError("DatasetWriter: instructions contain duplicates")
        self._instruction_index = {text: i for i, text in enumerate(self.instructions)}
        self.meta = dict(meta or {})
        self.overwrite = overwrite
        self._tmp = self.path.with_name(f".{self.path.name}.partial-{os.getpid()}")
        if self._tmp.exists():
            shutil.rmtree(self._tmp)
        (self._tmp / "meta").mkdir(parents=True)
        (self._tmp / "data").mkdir()
        self._files: dict[str, Any] = {}
        self._episodes_file = open(self._tmp / EPISODES_FILE, "w", encoding="utf-8")  # noqa: SIM115
        self._shapes: dict[str, tuple[int, ...]] = {}
        self._dtypes: dict[str, np.dtype] = {}
        self._has_states: bool | None = None
        self._ids: set[str] = set()
        self._segments: list[tuple[int, int, int, int, float, float]] = []
        self._num_frames = 0
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
    def split_counts(self) -> dict[str, dict[str, int]]:
        """Episodes, steps and segments written so far, per split."""
        return {name: dict(counts) for name, counts in self._split_counts.items()}

    def add(self, episode: Episode, split: str, extra: dict[str, Any] | None = None) -> int:
        """Append ``episode`` to ``split``; returns its index in the dataset.

        ``episode.segments`` are stored as its ground truth (``play``/``test`` loaders hide them).
        ``extra`` (JSON-serialisable) is kept in the episode's meta/episodes.jsonl line.
        """
        if self._closed:
            raise RuntimeError(f"{self.path}: DatasetWriter is closed")
        name = f"episode {episode.episode_id!r}"
        if split not in SPLITS:
            raise ValueError(f"{name}: unknown split {split!r} (expected one of {SPLITS})")
        if episode.episode_id in self._ids:
            raise ValueError(f"{name}: episode_id already written to this dataset")
        has_states = episode.states is not None
        if self._has_states is None:
            self._has_states = has_states
        elif has_states != self._has_states:
            want = "states" if self._has_states else "no states"
            raise ValueError(f"{name}: field 'states' present={has_states}, but the dataset has {want}")
        arrays = {"frames": episode.frames, "actions": episode.actions.astype(np.float32, copy=False)}
        if has_states:
            arrays["states"] = episode.states
        for key, array in arrays.items():
            self._append(name, key, np.asarray(array))
        labels = []
        for seg in episode.segments:
            if seg.instruction == "":
                labels.append(UNLABELLED)
            elif seg.instruction in self._instruction_index:
                labels.append(self._instruction_index[seg.instruction])
            else:
                raise ValueError(
                    f"{name}: segment [{seg.start}, {seg.end}) field 'instruction' {seg.instruction!r} "
                    "is not in the dataset's instruction list"
                )
        index = len(self._ids)
        record = EpisodeRecord(
            index=index,
            episode_id=episode.episode_id,
            split=split,
            num_steps=episode.num_steps,
            frame_start=self._num_frames,
            step_start=self._num_steps,
            segment_start=len(self._segments),
            num_segments=len(episode.segments),
            extra=dict(extra or {}),
        )
        for seg, label in zip(episode.segments, labels, strict=True):
            self._segments.append((index, seg.start, seg.end, label, seg.confidence, seg.log_prob))
        self._episodes_file.write(record.to_json() + "\n")
        self._ids.add(episode.episode_id)
        self._num_frames += episode.num_steps + 1
        self._num_steps += episode.num_steps
        counts = self._split_counts[split]
        counts["episodes"] += 1
        counts["steps"] += episode.num_steps
        counts["segments"] += len(episode.segments)
        return index

    def _append(self, name: str, key: str, array: np.ndarray) -> None:
        if key not in self._shapes:
            self._shapes[key] = tuple(array.shape[1:])
            self._dtypes[key] = array.dtype
            self._files[key] = open(self._tmp / ARRAY_FILES[key], "wb")  # noqa: SIM115
        if tuple(array.shape[1:]) != self._shapes[key] or array.dtype != self._dtypes[key]:
            raise ValueError(
                f"{name}: field {key!r} is {array.shape[1:]} {array.dtype} per row, but the dataset holds "
                f"{self._shapes[key]} {self._dtypes[key]}"
            )
        self._files[key].write(np.ascontiguousarray(array).data)

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
        if not self._ids:
            raise ValueError(f"{self.path}: no episodes were added; refusing to write an empty dataset")
        for handle in [*self._files.values(), self._episodes_file]:
            handle.flush()
            os.fsync(handle.fileno())
            handle.close()
        np.save(self._tmp / SEGMENTS_FILE, np.array(self._segments, dtype=SEGMENT_DTYPE))
        rows = {"frames": self._num_frames, "states": self._num_frames, "actions": self._num_steps}
        info = {
            "format": FORMAT_NAME,
            "format_version": FORMAT_VERSION,
            "instructions": list(self.instructions),
            "arrays": {
                key: {
                    "file": ARRAY_FILES[key],
                    "dtype": self._dtypes[key].str,
                    "shape": [rows[key], *self._shapes[key]],
                }
                for key in self._shapes
            },
            "segments_file": SEGMENTS_FILE,
            "episodes_file": EPISODES_FILE,
            "counts": {
                "episodes": len(self._ids),
                "steps": self._num_steps,
                "frames": self._num_frames,
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
        self._arrays = self._open_arrays()
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

    @property
    def frames(self) -> np.ndarray:
        """All frames, (total frames, H, W, 3) uint8, memory-mapped."""
        return self._arrays["frames"]

    @property
    def states(self) -> np.ndarray | None:
        """All states, memory-mapped, or None when the dataset has none."""
        return self._arrays.get("states")

    @property
    def actions(self) -> np.ndarray:
        """All actions, (total steps, action_dim) float32, memory-mapped."""
        return self._arrays["actions"]

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

    def episode(self, index: int, truth: bool = False) -> Episode:
        """Episode ``index`` with memory-mapped arrays (no frame is read until used)."""
        if not 0 <= index < len(self.records):
            raise IndexError(f"{self.path}: episode index {index} out of range (0..{len(self.records) - 1})")
        record = self.records[index]
        frames = slice(record.frame_start, record.frame_start + record.num_steps + 1)
        steps = slice(record.step_start, record.step_start + record.num_steps)
        states = self.states
        return Episode(
            episode_id=record.episode_id,
            frames=self.frames[frames],
            actions=self.actions[steps],
            states=None if states is None else states[frames],
            segments=self.segments(index, truth=truth),
        )

    def episodes(self, split: str, truth: bool = False) -> Iterator[Episode]:
        """The episodes of ``split`` in dataset order."""
        for index in self.episode_indices(split):
            yield self.episode(index, truth=truth)

    def _open_arrays(self) -> dict[str, np.ndarray]:
        arrays = {}
        for key, spec in self.info["arrays"].items():
            file = self.path / spec["file"]
            field = f"{INFO_FILE} arrays.{key}"
            if not file.is_file():
                raise FileNotFoundError(f"{file}: missing (named by {field}.file)")
            dtype, shape = np.dtype(spec["dtype"]), tuple(int(n) for n in spec["shape"])
            expected = int(np.prod(shape)) * dtype.itemsize
            actual = file.stat().st_size
            if actual != expected:
                raise _fail(
                    file,
                    f"size {actual} bytes, but {field} (shape {list(shape)}, {dtype}) needs {expected} bytes",
                )
            if expected == 0:
                arrays[key] = np.zeros(shape, dtype)
            else:
                arrays[key] = np.memmap(file, dtype=dtype, mode="r", shape=shape)
        for key in ("frames", "actions"):
            if key not in arrays:
                raise _fail(self.path / INFO_FILE, f"field arrays.{key} is missing")
        counts = self.info["counts"]
        for key, rows in (
            ("frames", counts["frames"]),
            ("states", counts["frames"]),
            ("actions", counts["steps"]),
        ):
            if key in arrays and arrays[key].shape[0] != rows:
                raise _fail(
                    self.path / INFO_FILE,
                    f"arrays.{key}.shape[0] = {arrays[key].shape[0]} disagrees with counts ({rows} rows)",
                )
        return arrays

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
    if info.get("format_version") != FORMAT_VERSION:
        raise _fail(
            file,
            f"field 'format_version' is {info.get('format_version')!r}; this playseg reads version {FORMAT_VERSION}",
        )
    for field in ("instructions", "arrays", "counts"):
        if field not in info:
            raise _fail(file, f"field {field!r} is missing")
    for field in ("episodes", "steps", "frames", "segments"):
        if not isinstance(info["counts"].get(field), int):
            raise _fail(file, f"field 'counts.{field}' is missing or not an integer")
    return info


def _read_episodes(root: Path, info: dict[str, Any]) -> list[EpisodeRecord]:
    file = root / info.get("episodes_file", EPISODES_FILE)
    if not file.is_file():
        raise FileNotFoundError(f"{file}: missing (the episode table)")
    records: list[EpisodeRecord] = []
    frame_start = step_start = segment_start = 0
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
                    frame_start=int(fields["frame_start"]),
                    step_start=int(fields["step_start"]),
                    segment_start=int(fields["segment_start"]),
                    num_segments=int(fields["num_segments"]),
                    extra=dict(fields.get("extra", {})),
                )
            except (json.JSONDecodeError, KeyError, TypeError, ValueError) as error:
                raise _fail(file, f"{where}: bad episode record ({type(error).__name__}: {error})") from error
            expected = (len(records), frame_start, step_start, segment_start)
            actual = (record.index, record.frame_start, record.step_start, record.segment_start)
            if actual != expected or record.num_steps < 0:
                raise _fail(
                    file,
                    f"{where} (episode {record.episode_id!r}): fields index/frame_start/step_start/"
                    f"segment_start are {actual}, expected {expected}",
                )
            if record.split not in SPLITS:
                raise _fail(
                    file, f"{where} (episode {record.episode_id!r}): field 'split' {record.split!r} unknown"
                )
            records.append(record)
            frame_start += record.num_steps + 1
            step_start += record.num_steps
            segment_start += record.num_segments
    counts = info["counts"]
    totals = {"episodes": len(records), "frames": frame_start, "steps": step_start, "segments": segment_start}
    for field, total in totals.items():
        if counts[field] != total:
            raise _fail(file, f"adds up to {total} {field}, but {INFO_FILE} counts.{field} = {counts[field]}")
    return records
