"""Bag write/read throughput: play episodes (64x64 frames) and a raw 640x480 rgb8 Image stream.

MB/s counts serialized message bytes (the CDR payload), so the figures compare across formats. The raw
stream goes through BagWriter/BagReader and, for reference, straight through the mcap library with the
same chunk size and compression.

    .venv/bin/python benchmarks/bench_bag_io.py [--episodes 200] [--images 120]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
from mcap.reader import make_reader
from mcap.writer import CompressionType, Writer

from playseg_core.data.episode import Episode, Segment
from playseg_core.data.features import DEFAULT_CAMERA
from playseg_ros.bag import BagReader, BagWriter, topic_info
from playseg_ros.messages import header, image_message
from playseg_ros.play_bags import read_play_bag, write_play_bag
from playseg_ros.typestore import playseg_typestore

IMAGE = "sensor_msgs/msg/Image"
CHUNK_BYTES = 1 << 20


def blocky_episode(index: int, num_steps: int, rng: np.random.Generator) -> Episode:
    """BabyAI-like frames: an 8x8 grid of flat-coloured 8x8 tiles, a few tiles changing per step."""
    tiles = rng.integers(0, 256, (num_steps + 1, 8, 8, 3), dtype=np.uint8)
    tiles[1:] = tiles[0]
    changed = rng.random((num_steps, 8, 8)) < 0.05
    tiles[1:][changed] = rng.integers(0, 256, (int(changed.sum()), 3), dtype=np.uint8)
    frames = np.repeat(np.repeat(tiles, 8, axis=1), 8, axis=2)
    cut = num_steps // 2
    return Episode(
        episode_id=f"bench-{index:05d}",
        actions=rng.integers(0, 7, (num_steps, 1)).astype(np.float32),
        images={DEFAULT_CAMERA: frames},  # the camera a bag that declares no features is read back under
        state=rng.integers(0, 11, (num_steps + 1, 8, 8, 3)).astype(np.uint8),
        segments=[Segment(0, cut, "go to the red ball"), Segment(cut, num_steps, "go to a blue key")],
    )


def camera_frames(count: int, rng: np.random.Generator) -> list[bytes]:
    """Serialized 640x480 rgb8 Images: a moving gradient plus sensor noise (compressible, not trivially)."""
    store = playseg_typestore()
    y, x = np.mgrid[0:480, 0:640]
    out = []
    for i in range(count):
        base = np.stack([(x + 3 * i) % 256, (y + i) % 256, (x + y) // 5 % 256], axis=-1)
        frame = np.clip(base + rng.integers(-4, 5, base.shape), 0, 255).astype(np.uint8)
        out.append(bytes(store.serialize_cdr(image_message(frame, header(i, "camera")), IMAGE)))
    return out


def timed(action: Callable[[], object]) -> float:
    start = time.perf_counter()
    action()
    return time.perf_counter() - start


def report(label: str, payload_bytes: int, seconds: float, disk_bytes: int | None = None) -> None:
    disk = f", {disk_bytes / 1e6:7.1f} MB on disk" if disk_bytes is not None else ""
    print(
        f"{label:<46} {payload_bytes / 1e6 / seconds:8.1f} MB/s  ({payload_bytes / 1e6:.1f} MB in {seconds:.2f} s{disk})"
    )


def disk_size(path: Path) -> int:
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file())


def bench_play(workdir: Path, episodes: list[Episode]) -> None:
    bag = workdir / "play"
    seconds = timed(lambda: write_play_bag(bag, episodes, annotated=True))
    with BagReader(bag) as reader:
        payload = sum(len(m.data) for m in reader.messages())
    steps = sum(e.num_steps + 1 for e in episodes)
    report(f"play bag write ({len(episodes)} episodes, {steps} steps)", payload, seconds, disk_size(bag))
    seconds = timed(lambda: read_play_bag(bag))
    report("play bag read -> Episodes", payload, seconds)
    print(f"{'':<46} {steps / seconds:8.0f} steps/s read, 64x64 frames")


def bench_raw(workdir: Path, images: list[bytes], compression: str) -> None:
    payload = sum(len(d) for d in images)
    bag = workdir / f"raw-{compression}"

    def through_bag_writer() -> None:
        with BagWriter(bag, chunk_bytes=CHUNK_BYTES, compression=compression) as writer:
            writer.add_topic(topic_info("/camera/image", IMAGE))
            for i, data in enumerate(images):
                writer.write("/camera/image", data, i * 33_000_000)

    direct = workdir / f"direct-{compression}.mcap"
    kind = CompressionType.ZSTD if compression == "zstd" else CompressionType.NONE
    definition = topic_info("/camera/image", IMAGE)

    def through_mcap() -> None:
        with direct.open("wb") as stream:
            writer = Writer(stream, chunk_size=CHUNK_BYTES, compression=kind)
            writer.start(profile="ros2", library="bench")
            schema = writer.register_schema(IMAGE, "ros2msg", definition.definition.encode())
            channel = writer.register_channel("/camera/image", "cdr", schema, {})
            for i, data in enumerate(images):
                writer.add_message(channel, i * 33_000_000, data, i * 33_000_000)
            writer.finish()

    def read_bag() -> None:
        with BagReader(bag) as reader:
            assert sum(1 for _ in reader.messages()) == len(images)

    def read_direct() -> None:
        with direct.open("rb") as stream:
            assert sum(1 for _ in make_reader(stream).iter_messages()) == len(images)

    label = f"640x480 rgb8 x{len(images)}, {compression}"
    report(f"{label}: BagWriter write", payload, timed(through_bag_writer), disk_size(bag))
    report(f"{label}: mcap Writer write", payload, timed(through_mcap), direct.stat().st_size)
    report(f"{label}: BagReader read", payload, timed(read_bag))
    report(f"{label}: mcap reader read", payload, timed(read_direct))


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--episodes", type=int, default=200, help="play episodes of 40 steps")
    parser.add_argument("--images", type=int, default=120, help="640x480 frames in the raw stream")
    args = parser.parse_args()
    rng = np.random.default_rng(0)
    episodes = [blocky_episode(i, 40, rng) for i in range(args.episodes)]
    images = camera_frames(args.images, rng)
    with tempfile.TemporaryDirectory() as tmp:
        workdir = Path(tmp)
        bench_play(workdir, episodes)
        for compression in ("zstd", "none"):
            bench_raw(workdir, images, compression)


if __name__ == "__main__":
    main()
