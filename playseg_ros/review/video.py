"""Each camera of an episode as an MP4 (H.264 through PyAV), encoded once and cached.

One video frame per observation at the dataset's rate, so observation k is shown from k / fps to
(k + 1) / fps; a keyframe every `GOP` frames and no B-frames keep seeking exact and cheap.
"""

from __future__ import annotations

import hashlib
import os
import threading
from pathlib import Path

import numpy as np

from playseg_core.data.dataset import INFO_FILE, PlayDataset

GOP = 10
DEFAULT_FPS = 10.0
_locks: dict[Path, threading.Lock] = {}
_locks_guard = threading.Lock()


def video_fps(dataset: PlayDataset) -> float:
    """The rate the videos play at: the dataset's step rate (10 Hz when it declares none)."""
    return float(dataset.features.fps or DEFAULT_FPS)


def encode_mp4(frames: np.ndarray, path: Path, fps: float) -> None:
    """Write ``frames`` ((N, H, W, 3) uint8) as an H.264 MP4 at ``fps``, atomically."""
    import av

    height, width = frames.shape[1] + frames.shape[1] % 2, frames.shape[2] + frames.shape[2] % 2
    staging = path.with_name(f".{path.name}.partial-{os.getpid()}-{threading.get_ident()}")
    with av.open(str(staging), mode="w", format="mp4") as container:
        stream = container.add_stream("libx264", rate=round(fps * 1000) / 1000 if fps % 1 else int(fps))
        stream.width, stream.height, stream.pix_fmt = width, height, "yuv420p"
        stream.options = {"g": str(GOP), "bf": "0", "crf": "18", "preset": "veryfast"}
        for i, frame in enumerate(frames):
            if frame.shape[:2] != (height, width):  # H.264 in 4:2:0 needs even sides
                frame = np.pad(
                    frame, ((0, height - frame.shape[0]), (0, width - frame.shape[1]), (0, 0)), "edge"
                )
            video_frame = av.VideoFrame.from_ndarray(np.ascontiguousarray(frame), format="rgb24")
            video_frame.pts = i
            container.mux(stream.encode(video_frame))
        container.mux(stream.encode(None))
    os.replace(staging, path)


def episode_video(dataset: PlayDataset, index: int, camera: str, cache: Path) -> Path:
    """The MP4 of ``camera`` in episode ``index``, from ``cache`` or encoded into it."""
    record = dataset.records[index]
    # the dataset's own file too: a dataset written again in place (a bag converted again) is new video
    written = (dataset.path / INFO_FILE).stat()
    key = (
        f"{dataset.path.resolve()}|{written.st_mtime_ns}|{written.st_size}|{record.episode_id}|"
        f"{record.observation_start}|{record.num_steps}|{camera}"
    )
    name = f"{hashlib.sha256(key.encode()).hexdigest()[:16]}.mp4"
    path = cache / name
    with _locks_guard:
        lock = _locks.setdefault(path, threading.Lock())
    with lock:
        if not path.is_file():
            cache.mkdir(parents=True, exist_ok=True)
            encode_mp4(np.asarray(dataset.episode(index).images[camera]), path, video_fps(dataset))
    return path
