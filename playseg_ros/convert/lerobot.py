"""A playseg dataset as a LeRobot dataset, format v3.0 (``--format lerobot``).

Layout (one directory)::

    meta/info.json                              codebase_version "v3.0", fps, features, totals, paths
    meta/tasks.parquet                          one row per task string (the pandas index) -> task_index
    meta/episodes/chunk-000/file-000.parquet    per episode: tasks, length, where its rows and video lie,
                                                its statistics (stats/<feature>/<stat>)
    meta/stats.json                             per feature: min, max, mean, std, count, q01..q99
    data/chunk-XXX/file-XXX.parquet             one row per frame: the numeric features, timestamp,
                                                frame_index, episode_index, index, task_index,
                                                language_persistent
    videos/<camera>/chunk-XXX/file-XXX.mp4      each camera's frames (PyAV, h264 yuv420p); several
                                                episodes share a file, found by from/to timestamps

Frames: a playseg episode has T+1 observations and T actions; LeRobot pairs each frame's observation
with its action, so frame t is (o_t, a_t) for t < T and the last observation, which has no action, is
left out. Timestamps are frame_index / fps.

Language: the instruction segments become per-frame language as LeRobot represents subtasks. Every frame
of an episode carries the episode's ``language_persistent`` rows (role "assistant", style "subtask",
content = the instruction, timestamp = the segment's first frame / fps); a row is active from its
timestamp until the next row, and a row with null content ends a subtask where unlabelled play follows.
Each frame's ``task_index`` is its active instruction ("" outside any segment), so an episode's task list
holds its instructions.
"""

from __future__ import annotations

import json
import os
import shutil
from dataclasses import dataclass, field
from fractions import Fraction
from pathlib import Path
from typing import Any, NotRequired, TypedDict

import av
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from playseg_core.data.dataset import PlayDataset
from playseg_core.data.episode import Episode, Segment
from playseg_core.errors import PlaysegError

CODEBASE_VERSION = "v3.0"
CHUNKS_SIZE = 1000
DATA_FILES_SIZE_IN_MB = 100
VIDEO_FILES_SIZE_IN_MB = 200
DATA_PATH = "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"
VIDEO_PATH = "videos/{video_key}/chunk-{chunk_index:03d}/file-{file_index:03d}.mp4"
EPISODES_PATH = "meta/episodes/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"
TASKS_PATH = "meta/tasks.parquet"
INFO_PATH = "meta/info.json"
STATS_PATH = "meta/stats.json"
LANGUAGE_PERSISTENT = "language_persistent"
SUBTASK_STYLE = "subtask"
UNLABELLED_TASK = ""
VIDEO_CODEC = "h264"
PIX_FMT = "yuv420p"
QUANTILES = {"q01": 0.01, "q10": 0.10, "q50": 0.50, "q90": 0.90, "q99": 0.99}
DEFAULT_COLUMNS = {"timestamp": "float32", "frame_index": "int64", "episode_index": "int64", "index": "int64",
                   "task_index": "int64"}  # fmt: skip


class LeRobotFeatureJson(TypedDict):
    dtype: str
    shape: list[int]
    names: list[str] | None
    info: NotRequired[dict[str, Any]]


class LeRobotInfoJson(TypedDict):
    codebase_version: str
    robot_type: str | None
    total_episodes: int
    total_frames: int
    total_tasks: int
    chunks_size: int
    data_files_size_in_mb: int
    video_files_size_in_mb: int
    fps: float
    splits: dict[str, str]
    data_path: str
    video_path: str | None
    features: dict[str, LeRobotFeatureJson]


class FeatureStatsJson(TypedDict):
    min: list[Any]
    max: list[Any]
    mean: list[Any]
    std: list[Any]
    count: list[int]
    q01: list[Any]
    q10: list[Any]
    q50: list[Any]
    q90: list[Any]
    q99: list[Any]


def language_row_type() -> pa.StructType:
    """One ``language_persistent`` row, as LeRobot declares it."""
    json_type = pa.json_() if hasattr(pa, "json_") else pa.string()
    return pa.struct(
        [
            pa.field("role", pa.string(), nullable=False),
            pa.field("content", pa.string()),
            pa.field("style", pa.string()),
            pa.field("timestamp", pa.float32(), nullable=False),
            pa.field("camera", pa.string()),
            pa.field("tool_calls", pa.list_(json_type)),
        ]
    )


def language_rows(segments: list[Segment], num_frames: int, fps: float) -> list[dict[str, Any]]:
    """An episode's subtask rows: one per segment at its first frame, and a null row where a segment
    ends and no other begins (inside the episode)."""
    rows: list[dict[str, Any]] = []
    for k, segment in enumerate(segments):
        rows.append(_row(segment.instruction, segment.start / fps))
        next_start = segments[k + 1].start if k + 1 < len(segments) else None
        if segment.end < num_frames and next_start != segment.end:
            rows.append(_row(None, segment.end / fps))
    return rows


def language_column(rows: list[dict[str, Any]], num_frames: int) -> pa.ListArray:
    """The episode's rows on every one of its frames (built field by field: pyarrow cannot convert Python
    values to the JSON extension type of ``tool_calls``)."""
    row_type = language_row_type()
    repeated = rows * num_frames
    fields = []
    for field_type in row_type:
        if field_type.name == "tool_calls":
            fields.append(pa.nulls(len(repeated), field_type.type))
        else:
            fields.append(pa.array([row[field_type.name] for row in repeated], type=field_type.type))
    values = pa.StructArray.from_arrays(fields, fields=list(row_type))
    offsets = pa.array(np.arange(num_frames + 1, dtype=np.int32) * len(rows))
    return pa.ListArray.from_arrays(offsets, values, type=pa.list_(row_type))


def _row(content: str | None, timestamp: float) -> dict[str, Any]:
    return {"role": "assistant", "content": content, "style": SUBTASK_STYLE, "timestamp": float(np.float32(timestamp)),
            "camera": None, "tool_calls": None}  # fmt: skip


def frame_tasks(segments: list[Segment], num_frames: int) -> list[str]:
    """Each frame's active instruction (`UNLABELLED_TASK` outside the segments)."""
    tasks = [UNLABELLED_TASK] * num_frames
    for segment in segments:
        for t in range(segment.start, min(segment.end, num_frames)):
            tasks[t] = segment.instruction or UNLABELLED_TASK
    return tasks


# --------------------------------------------------------------------------------------------------
# Statistics


def feature_stats(
    values: np.ndarray, axis: tuple[int, ...] = (0,), keepdims: bool = False
) -> FeatureStatsJson:
    """LeRobot's statistics of ``values`` over ``axis`` (images: over frames and pixels, per channel)."""
    data = values.astype(np.float64)
    stats: dict[str, Any] = {
        "min": data.min(axis=axis, keepdims=keepdims),
        "max": data.max(axis=axis, keepdims=keepdims),
        "mean": data.mean(axis=axis, keepdims=keepdims),
        "std": data.std(axis=axis, keepdims=keepdims),
    }
    for name, q in QUANTILES.items():
        stats[name] = np.quantile(data, q, axis=axis, keepdims=keepdims)
    out = {name: np.asarray(value).tolist() for name, value in stats.items()}
    out["count"] = [int(values.shape[0])]
    return out  # type: ignore[return-value]


def image_stats(frames: np.ndarray) -> FeatureStatsJson:
    """Per-channel statistics of (N, H, W, 3) uint8 frames scaled to [0, 1], shaped (3, 1, 1) as LeRobot
    keeps them; pixels are subsampled to about 10,000 per frame."""
    step = max(1, int(np.sqrt(frames.shape[1] * frames.shape[2] / 10_000)))
    sample = frames[:, ::step, ::step].astype(np.float32) / 255.0  # (N, h, w, 3)
    channels_first = np.moveaxis(sample, -1, 1)  # (N, 3, h, w)
    stats = feature_stats(channels_first, axis=(0, 2, 3), keepdims=True)
    return {
        name: (np.asarray(value)[0].tolist() if name != "count" else value) for name, value in stats.items()
    }  # type: ignore[return-value]


# --------------------------------------------------------------------------------------------------
# Writing


@dataclass
class FileIndex:
    """Where the next file goes: chunk-XXX/file-XXX, at most `CHUNKS_SIZE` files per chunk."""

    chunk_index: int = 0
    file_index: int = 0

    def advance(self) -> None:
        self.file_index += 1
        if self.file_index >= CHUNKS_SIZE:
            self.chunk_index, self.file_index = self.chunk_index + 1, 0


@dataclass
class VideoFile:
    """One MP4 being written: frames of several episodes one after another."""

    path: Path
    fps: float
    width: int
    height: int
    frames: int = 0
    container: Any = None
    stream: Any = None

    def open(self) -> None:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.container = av.open(str(self.path), mode="w")
        rate = Fraction(self.fps).limit_denominator(1001)
        self.stream = self.container.add_stream(VIDEO_CODEC, rate=rate)
        self.stream.width, self.stream.height, self.stream.pix_fmt = self.width, self.height, PIX_FMT
        self.stream.time_base = Fraction(1, 1) / rate
        # a key frame every 2 frames: cheap random access for training; 'veryfast' encodes ~10x faster
        # than x264's default preset at a slightly larger file
        self.stream.options = {"g": "2", "crf": "20", "preset": "veryfast"}

    def write(self, frames: np.ndarray) -> None:
        if self.container is None:
            self.open()
        for image in frames:
            frame = av.VideoFrame.from_ndarray(np.ascontiguousarray(image), format="rgb24")
            frame.pts = self.frames
            self.frames += 1
            for packet in self.stream.encode(frame):
                self.container.mux(packet)

    def close(self) -> None:
        if self.container is not None:
            for packet in self.stream.encode():
                self.container.mux(packet)
            self.container.close()
            self.container = None

    @property
    def size_mb(self) -> float:
        return self.path.stat().st_size / 1e6 if self.path.exists() else 0.0


@dataclass
class LeRobotSummary:
    path: Path
    episodes: int
    frames: int
    tasks: int
    videos: int = 0
    notes: list[str] = field(default_factory=list)


def is_lerobot_dataset(path: Path) -> bool:
    try:
        info = json.loads((path / INFO_PATH).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return False
    return isinstance(info, dict) and info.get("codebase_version") == CODEBASE_VERSION


def export_lerobot(dataset: PlayDataset, out: Path, overwrite: bool = False) -> LeRobotSummary:
    """Write ``dataset`` (every split, in dataset order) as a LeRobot v3.0 dataset at ``out``, through a
    staging directory renamed into place; ``overwrite`` replaces only an earlier LeRobot v3.0 dataset."""
    out = Path(out)
    if out.exists() and not (overwrite and is_lerobot_dataset(out)):
        what = (
            "a LeRobot v3.0 dataset; replace it with --overwrite"
            if is_lerobot_dataset(out)
            else "not a LeRobot dataset"
        )
        raise FileExistsError(f"{out}: exists ({what}); refusing to write into it")
    staging = out.with_name(f".{out.name}.partial-{os.getpid()}")
    shutil.rmtree(staging, ignore_errors=True)
    try:
        summary = _write(dataset, staging)
        if out.exists():
            old = out.with_name(f".{out.name}.old-{os.getpid()}")
            out.rename(old)
            staging.rename(out)
            shutil.rmtree(old)
        else:
            staging.rename(out)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    summary.path = out
    return summary


def _write(dataset: PlayDataset, root: Path) -> LeRobotSummary:
    fps = dataset.features.fps
    if not fps:
        raise PlaysegError(f"{dataset.path}: the dataset declares no fps; LeRobot needs one")
    cameras = dataset.features.cameras
    numeric = [name for name in ("observation.state", "action") if name in dataset.features]
    for camera in cameras:
        height, width, _ = dataset.features[camera].shape
        if height % 2 or width % 2:
            raise PlaysegError(
                f"feature {camera!r}: {width}x{height}; {PIX_FMT} video needs even sizes (resize it)"
            )
    tasks: dict[str, int] = {}
    data_index, data_tables, data_bytes = FileIndex(), [], 0
    video_index = {camera: FileIndex() for camera in cameras}
    videos: dict[str, VideoFile] = {}
    episode_rows: list[dict[str, Any]] = []
    all_values: dict[str, list[np.ndarray]] = {name: [] for name in [*numeric, *DEFAULT_COLUMNS]}
    image_samples: dict[str, list[np.ndarray]] = {camera: [] for camera in cameras}
    frames_so_far = 0
    notes = []

    def flush_data() -> None:
        nonlocal data_tables, data_bytes
        if data_tables:
            path = root / DATA_PATH.format(
                chunk_index=data_index.chunk_index, file_index=data_index.file_index
            )
            path.parent.mkdir(parents=True, exist_ok=True)
            pq.write_table(pa.concat_tables(data_tables), path)
            data_index.advance()
            data_tables, data_bytes = [], 0

    for index in range(len(dataset)):
        episode = dataset.episode(index, truth=True)
        num_frames = episode.num_steps
        if num_frames == 0:
            notes.append(f"episode {episode.episode_id!r}: no action; left out")
            continue
        episode_index = len(episode_rows)
        frame_task = frame_tasks(episode.segments, num_frames)
        for task in frame_task:
            tasks.setdefault(task, len(tasks))
        columns = _episode_columns(
            episode, numeric, num_frames, fps, episode_index, frames_so_far, frame_task, tasks
        )
        rows = language_rows(episode.segments, num_frames, fps)
        columns[LANGUAGE_PERSISTENT] = language_column(rows, num_frames)
        table = pa.table(columns)
        record: dict[str, Any] = {
            "episode_index": episode_index,
            "tasks": list(dict.fromkeys(frame_task)),
            "length": num_frames,
            "data/chunk_index": data_index.chunk_index,
            "data/file_index": data_index.file_index,
            "dataset_from_index": frames_so_far,
            "dataset_to_index": frames_so_far + num_frames,
        }
        data_tables.append(table)
        data_bytes += table.nbytes
        if data_bytes > DATA_FILES_SIZE_IN_MB * 1e6:
            flush_data()
        for camera in cameras:
            frames = np.asarray(episode.images[camera][:num_frames])
            video = videos.get(camera)
            if video is None:
                height, width, _ = dataset.features[camera].shape
                place = video_index[camera]
                path = root / VIDEO_PATH.format(
                    video_key=camera, chunk_index=place.chunk_index, file_index=place.file_index
                )
                video = videos[camera] = VideoFile(path, fps, width, height)
            start = video.frames
            video.write(frames)
            place = video_index[camera]
            record[f"videos/{camera}/chunk_index"] = place.chunk_index
            record[f"videos/{camera}/file_index"] = place.file_index
            record[f"videos/{camera}/from_timestamp"] = start / fps
            record[f"videos/{camera}/to_timestamp"] = video.frames / fps
            stats = image_stats(frames)
            for stat, value in stats.items():
                record[f"stats/{camera}/{stat}"] = value
            image_samples[camera].append(frames[:: max(1, num_frames // 50)])
            if video.size_mb > VIDEO_FILES_SIZE_IN_MB:
                video.close()
                del videos[camera]
                place.advance()
        for name in [*numeric, *DEFAULT_COLUMNS]:
            values = _column_values(columns[name])
            all_values[name].append(values)
            for stat, value in feature_stats(values).items():
                record[f"stats/{name}/{stat}"] = value
        record["meta/episodes/chunk_index"] = 0
        record["meta/episodes/file_index"] = 0
        episode_rows.append(record)
        frames_so_far += num_frames
    if not episode_rows:
        raise PlaysegError(f"{dataset.path}: no episode with an action; nothing to export")
    flush_data()
    for video in videos.values():
        video.close()
    _write_table(root / EPISODES_PATH.format(chunk_index=0, file_index=0), episode_rows)
    _write_tasks(root / TASKS_PATH, tasks)
    stats: dict[str, FeatureStatsJson] = {
        name: feature_stats(np.concatenate(parts)) for name, parts in all_values.items()
    }
    for camera in cameras:
        stats[camera] = image_stats(np.concatenate(image_samples[camera]))
        stats[camera]["count"] = [frames_so_far]
    (root / STATS_PATH).write_text(json.dumps(stats, indent=2) + "\n", encoding="utf-8")
    info = _info(dataset, len(episode_rows), frames_so_far, len(tasks), fps, numeric, cameras)
    (root / INFO_PATH).write_text(json.dumps(info, indent=2) + "\n", encoding="utf-8")
    return LeRobotSummary(root, len(episode_rows), frames_so_far, len(tasks), len(cameras), notes)


def _episode_columns(
    episode: Episode,
    numeric: list[str],
    num_frames: int,
    fps: float,
    episode_index: int,
    first_index: int,
    frame_task: list[str],
    tasks: dict[str, int],
) -> dict[str, pa.Array]:
    columns: dict[str, pa.Array] = {}
    for name in numeric:
        values = np.asarray(episode.actions if name == "action" else episode.state)[:num_frames]
        flat = values.reshape(num_frames, -1)
        arrow_type = pa.from_numpy_dtype(flat.dtype)
        columns[name] = pa.FixedSizeListArray.from_arrays(
            pa.array(flat.reshape(-1), type=arrow_type), flat.shape[1]
        )
    frame_index = np.arange(num_frames, dtype=np.int64)
    columns["timestamp"] = pa.array((frame_index / fps).astype(np.float32))
    columns["frame_index"] = pa.array(frame_index)
    columns["episode_index"] = pa.array(np.full(num_frames, episode_index, dtype=np.int64))
    columns["index"] = pa.array(first_index + frame_index)
    columns["task_index"] = pa.array(np.array([tasks[t] for t in frame_task], dtype=np.int64))
    return columns


def _column_values(column: pa.Array) -> np.ndarray:
    if isinstance(column.type, pa.FixedSizeListType):
        return column.flatten().to_numpy().reshape(len(column), column.type.list_size)
    return column.to_numpy().reshape(len(column), 1)


def _write_table(path: Path, rows: list[dict[str, Any]]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    keys = list(dict.fromkeys(key for row in rows for key in row))
    pq.write_table(pa.table({key: [row.get(key) for row in rows] for key in keys}), path)


def _write_tasks(path: Path, tasks: dict[str, int]) -> None:
    """tasks.parquet as pandas writes a frame indexed by ``task``: LeRobot reads it with pandas."""
    table = pa.table(
        {"task_index": pa.array(list(tasks.values()), pa.int64()), "task": pa.array(list(tasks))}
    )
    pandas_meta = {
        "index_columns": ["task"],
        "column_indexes": [{"name": None, "field_name": None, "pandas_type": "unicode", "numpy_type": "object",
                            "metadata": {"encoding": "UTF-8"}}],
        "columns": [
            {"name": "task_index", "field_name": "task_index", "pandas_type": "int64", "numpy_type": "int64", "metadata": None},
            {"name": "task", "field_name": "task", "pandas_type": "unicode", "numpy_type": "object", "metadata": None},
        ],
        "creator": {"library": "pyarrow", "version": pa.__version__},
        "pandas_version": "2.2.3",
    }  # fmt: skip
    table = table.replace_schema_metadata({b"pandas": json.dumps(pandas_meta).encode()})
    pq.write_table(table, path)


def _info(
    dataset: PlayDataset,
    episodes: int,
    frames: int,
    tasks: int,
    fps: float,
    numeric: list[str],
    cameras: list[str],
) -> LeRobotInfoJson:
    features: dict[str, LeRobotFeatureJson] = {}
    for camera in cameras:
        height, width, channels = dataset.features[camera].shape
        features[camera] = {
            "dtype": "video",
            "shape": [height, width, channels],
            "names": ["height", "width", "channels"],
            "info": {"video.height": height, "video.width": width, "video.codec": VIDEO_CODEC,
                     "video.pix_fmt": PIX_FMT, "video.is_depth_map": False, "video.fps": fps,
                     "video.channels": channels, "has_audio": False},
        }  # fmt: skip
    for name in numeric:
        feature = dataset.features[name]
        features[name] = {"dtype": feature.dtype, "shape": [feature.size],
                          "names": list(feature.names) if feature.names else None}  # fmt: skip
    for name, dtype in DEFAULT_COLUMNS.items():
        features[name] = {"dtype": dtype, "shape": [1], "names": None}
    features[LANGUAGE_PERSISTENT] = {"dtype": "language", "shape": [1], "names": None}
    return {
        "codebase_version": CODEBASE_VERSION,
        "robot_type": None,
        "total_episodes": episodes,
        "total_frames": frames,
        "total_tasks": tasks,
        "chunks_size": CHUNKS_SIZE,
        "data_files_size_in_mb": DATA_FILES_SIZE_IN_MB,
        "video_files_size_in_mb": VIDEO_FILES_SIZE_IN_MB,
        "fps": fps,
        "splits": {"train": f"0:{episodes}"},
        "data_path": DATA_PATH,
        "video_path": VIDEO_PATH if cameras else None,
        "features": features,
    }
