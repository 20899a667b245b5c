"""`playseg review`: time to the first video response of a long episode, in chunks and as one file.

    .venv/bin/python benchmarks/bench_review_video.py [--steps 20000] [--size 96] [--chunk 300]

One episode of ``--steps`` steps with one ``--size`` x ``--size`` camera (a square moving over a dark
background, so the encoder has motion to code) is written as a dataset in a temporary directory (twice
its frames' size on disk); a review server serves it on
localhost. Each run starts with an empty video cache and times one GET of the episode's video, from the
request to the last byte of the answer: as chunks of ``--chunk`` observations (the page's first request:
chunk 0) and as one file holding the whole episode (a chunk as long as the episode: how the page worked
before chunks). Then the next chunk, encoded ahead while the first was served, is timed too.
"""

from __future__ import annotations

import argparse
import tempfile
import threading
import time
import urllib.request
from pathlib import Path

import numpy as np

from playseg_core.data.dataset import DatasetWriter
from playseg_core.data.episode import Episode
from playseg_ros.review.app import start

CAMERA = "observation.images.top"


def write_long_episode(path: Path, steps: int, size: int) -> Path:
    # the frames on disk, not in memory: 100,000 frames of 96x96 are 2.8 GB
    frames = np.memmap(path.with_name("frames.raw"), np.uint8, "w+", shape=(steps + 1, size, size, 3))
    frames[:] = 30
    side = size // 4
    for k in range(steps + 1):
        x = k % (size - side)
        frames[k, side : 2 * side, x : x + side] = 220
    actions = np.zeros((steps, 2), np.float32)
    with DatasetWriter(path, ["reach"]) as writer:
        writer.add(Episode("long", actions, images={CAMERA: frames}), "play")
    return path


def timed_get(url: str) -> tuple[float, int]:
    started = time.perf_counter()
    with urllib.request.urlopen(url, timeout=3600) as response:
        size = len(response.read())
    return time.perf_counter() - started, size


def first_response(data: Path, work: Path, chunk: int) -> tuple[float, int, float | None]:
    """Seconds to the first video response and its bytes, then seconds for the next chunk (None: none)."""
    server, url = start(data, port=0, work=work, video_chunk=chunk)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    try:
        video = f"{url}api/episode/0/video/{CAMERA}"
        seconds, size = timed_get(video + "?chunk=0")
        steps = server.session.dataset.records[0].num_steps
        following = None
        if chunk < steps + 1:
            time.sleep(seconds)  # a user watches the first chunk for at least as long
            following, _ = timed_get(video + "?chunk=1")
        return seconds, size, following
    finally:
        server.shutdown()
        server.server_close()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--steps", type=int, default=20_000)
    parser.add_argument("--size", type=int, default=96)
    parser.add_argument("--chunk", type=int, default=300, help="observations per video file")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        data = write_long_episode(Path(tmp) / "long", args.steps, args.size)
        print(f"episode of {args.steps} steps, one {args.size}x{args.size} camera")
        for name, chunk in (("chunks", args.chunk), ("whole episode", args.steps + 1)):
            seconds, size, following = first_response(data, Path(tmp) / f"work-{chunk}", chunk)
            line = f"{name:>13} ({chunk} frames a file): first video response {seconds:.2f} s, {size / 1e6:.2f} MB"
            if following is not None:
                line += f"; the next chunk (encoded ahead) {following:.3f} s"
            print(line, flush=True)


if __name__ == "__main__":
    main()
