"""Each camera of an episode as MP4 files (H.264 through PyAV) of `CHUNK_FRAMES` observations each,
encoded on demand, once, and cached.

Chunk c of an episode holds observations c * chunk .. (c + 1) * chunk - 1, one video frame each at the
dataset's rate, so its observation k is shown from k / fps to (k + 1) / fps of that file; each file starts
on a keyframe, with one every `GOP` frames and no B-frames, so seeking is exact and cheap. A long
episode's first request encodes one chunk, not the whole episode; asking for a chunk starts encoding the
next one in the background (`prefetch_chunk`), so playing on does not wait for it.
"""

from __future__ import annotations

import hashlib
import os
import threading
from pathlib import Path

import numpy as np

from playseg_core.data.dataset import INFO_FILE, PlayDataset
from playseg_core.errors import PlaysegError

GOP = 10
CHUNK_FRAMES = 300
"""Observations per video file (30 s at 10 Hz): what a first request encodes."""
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


def chunk_count(num_observations: int, chunk_frames: int) -> int:
    """The number of video files of an episode of ``num_observations``."""
    return max(1, -(-num_observations // chunk_frames))


def chunk_path(
    dataset: PlayDataset, index: int, camera: str, cache: Path, chunk: int, chunk_frames: int = CHUNK_FRAMES
) -> Path:
    """Where chunk ``chunk`` of ``camera`` in episode ``index`` is cached; PlaysegError when the episode has
    no such chunk."""
    record = dataset.records[index]
    chunks = chunk_count(record.num_steps + 1, chunk_frames)
    if not 0 <= chunk < chunks:
        raise PlaysegError(
            f"episode {index} has video chunks 0..{chunks - 1} of {chunk_frames} frames, not {chunk}"
        )
    # the dataset's own file too: a dataset written again in place (a bag converted again) is new video
    written = (dataset.path / INFO_FILE).stat()
    key = (
        f"{dataset.path.resolve()}|{written.st_mtime_ns}|{written.st_size}|{record.episode_id}|"
        f"{record.observation_start}|{record.num_steps}|{camera}|{chunk_frames}|{chunk}"
    )
    return cache / f"{hashlib.sha256(key.encode()).hexdigest()[:16]}.mp4"


def _lock(path: Path) -> threading.Lock:
    with _locks_guard:
        return _locks.setdefault(path, threading.Lock())


def episode_video(
    dataset: PlayDataset,
    index: int,
    camera: str,
    cache: Path,
    chunk: int = 0,
    chunk_frames: int = CHUNK_FRAMES,
) -> Path:
    """The MP4 of chunk ``chunk`` of ``camera`` in episode ``index``, from ``cache`` or encoded into it;
    PlaysegError when the episode has no such chunk."""
    path = chunk_path(dataset, index, camera, cache, chunk, chunk_frames)
    with _lock(path):
        if not path.is_file():
            cache.mkdir(parents=True, exist_ok=True)
            frames = dataset.episode(index).images[camera][chunk * chunk_frames : (chunk + 1) * chunk_frames]
            encode_mp4(np.asarray(frames), path, video_fps(dataset))
    return path


def prefetch_chunk(
    dataset: PlayDataset, index: int, camera: str, cache: Path, chunk: int, chunk_frames: int = CHUNK_FRAMES
) -> threading.Thread | None:
    """Encode chunk ``chunk`` in a background thread, unless the episode has no such chunk or it is cached
    or being encoded already; the thread, or None."""
    if not 0 <= chunk < chunk_count(dataset.records[index].num_steps + 1, chunk_frames):
        return None
    path = chunk_path(dataset, index, camera, cache, chunk, chunk_frames)
    if path.is_file() or _lock(path).locked():
        return None
    thread = threading.Thread(
        target=episode_video, args=(dataset, index, camera, cache, chunk, chunk_frames), daemon=True
    )
    thread.start()
    return thread
