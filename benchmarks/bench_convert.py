"""`playseg convert` throughput: MB of bag converted per second with 1 and 2 workers.

Bags of raw rgb8 camera frames (640x480 at 30 Hz, what makes robot bags large), 100 Hz JointState and a
10 Hz Twist command, written by rosbags (MCAP, uncompressed); converted at the camera's 30 fps with the
joints aligned 'nearest' and the commands 'previous'. The target is >= 1 GB per minute per worker
(~17 MB/s; users ask for under 5 minutes per GB). Then the same data exported as LeRobot v3.0: frames
encoded per second (h264 MP4 through PyAV).

    .venv/bin/python benchmarks/bench_convert.py [--bags 4] [--seconds 4] [--dir /tmp/bench_convert] [--ray]

``--ray`` also converts with ``--engine ray`` (a local Ray instance, 2 CPUs) and prints its time next to the
local engine's with 2 workers: the cost of starting Ray on one machine.
"""

from __future__ import annotations

import argparse
import shutil
import time
from pathlib import Path

import numpy as np
import yaml
from rosbags.rosbag2 import StoragePlugin, Writer

from playseg_core.data.dataset import PlayDataset
from playseg_ros.convert import convert, load_mapping
from playseg_ros.convert.lerobot import export_lerobot
from playseg_ros.convert.source import bag_size, convert_typestore

T0 = 1_700_000_000 * 10**9
WIDTH, HEIGHT = 640, 480
MAPPING = {
    "fps": 30,
    "primary": "observation.images.front",
    "tolerance_ms": 20,
    "features": {
        "observation.images.front": {"topic": "/camera/image_raw"},
        "observation.state": {"topic": "/joint_states", "field": "position"},
        "action": {
            "topic": "/cmd_vel",
            "fields": ["linear.x", "angular.z"],
            "align": "previous",
            "tolerance_ms": 120,
        },
    },
}


def write_bag(path: Path, seconds: float, seed: int) -> None:
    store = convert_typestore()
    types = store.types
    Time, Header, Vector3 = (
        types[n] for n in ("builtin_interfaces/msg/Time", "std_msgs/msg/Header", "geometry_msgs/msg/Vector3")
    )
    rng = np.random.default_rng(seed)
    # camera-like content (smooth gradients, a moving edge, sensor noise); the conversion itself does not
    # depend on it, the MP4 encoding of the LeRobot export does
    y, x = np.mgrid[0:HEIGHT, 0:WIDTH]
    base = np.stack([x * 255 // WIDTH, y * 255 // HEIGHT, (x + y) * 127 // (WIDTH + HEIGHT)], axis=-1).astype(
        np.int16
    )
    noise = rng.integers(-3, 4, size=(HEIGHT, WIDTH, 3), dtype=np.int16)
    messages = []
    for i in range(round(seconds * 30)):
        t = T0 + round(i * 1e9 / 30)
        image = np.roll(base, 4 * i, axis=1) + np.roll(noise, i, axis=0)
        image[100:200, (8 * i) % WIDTH : (8 * i) % WIDTH + 60] = (200, 40, 40)
        data = np.clip(image, 0, 255).astype(np.uint8).reshape(-1)
        messages.append(("/camera/image_raw", "sensor_msgs/msg/Image", t, types["sensor_msgs/msg/Image"](
            header=Header(stamp=Time(sec=t // 10**9, nanosec=t % 10**9), frame_id="cam"), height=HEIGHT,
            width=WIDTH, encoding="rgb8", is_bigendian=0, step=WIDTH * 3, data=data)))  # fmt: skip
    for k in range(round(seconds * 100)):
        t = T0 + k * 10_000_000
        messages.append(("/joint_states", "sensor_msgs/msg/JointState", t, types["sensor_msgs/msg/JointState"](
            header=Header(stamp=Time(sec=t // 10**9, nanosec=t % 10**9), frame_id=""),
            name=[f"j{j}" for j in range(7)], position=rng.normal(size=7), velocity=np.zeros(7), effort=np.zeros(7))))  # fmt: skip
    for m in range(round(seconds * 10)):
        t = T0 + m * 100_000_000 + 1_000_000
        messages.append(("/cmd_vel", "geometry_msgs/msg/Twist", t, types["geometry_msgs/msg/Twist"](
            linear=Vector3(x=float(m), y=0.0, z=0.0), angular=Vector3(x=0.0, y=0.0, z=-float(m)))))  # fmt: skip
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        connections = {}
        for topic, msgtype, t, msg in sorted(messages, key=lambda m: m[2]):
            if topic not in connections:
                connections[topic] = writer.add_connection(topic, msgtype, typestore=store)
            writer.write(connections[topic], t, store.serialize_cdr(msg, msgtype))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--bags", type=int, default=4)
    parser.add_argument("--seconds", type=float, default=4.0, help="recording length of each bag")
    parser.add_argument("--dir", default="/tmp/bench_convert")
    parser.add_argument("--ray", action="store_true", help="also time --engine ray (2 CPUs)")
    args = parser.parse_args()
    root = Path(args.dir)
    shutil.rmtree(root, ignore_errors=True)
    bags = root / "bags"
    started = time.perf_counter()
    for b in range(args.bags):
        write_bag(bags / f"bag_{b:02d}", args.seconds, b)
    total = sum(bag_size(p) for p in bags.iterdir())
    print(f"wrote {args.bags} bags, {total / 1e6:.0f} MB, in {time.perf_counter() - started:.1f} s")
    (root / "map.yaml").write_text(yaml.safe_dump(MAPPING))
    mapping = load_mapping(root / "map.yaml")
    runs = [(1, "local"), (2, "local")] + ([(2, "ray")] if args.ray else [])
    for workers, engine in runs:
        out = root / f"data_{workers}_{engine}"
        started = time.perf_counter()
        summary = convert([bags], out, mapping, workers=workers, progress=False, engine=engine)
        seconds = time.perf_counter() - started
        assert not summary.failed, [r.error for r in summary.failed]
        steps = summary.totals()["steps"]
        rate = total / 1e6 / seconds
        print(
            f"{engine} workers {workers}: {total / 1e6:.0f} MB in {seconds:.2f} s = {rate:.1f} MB/s "
            f"({rate * 60 / 1000:.2f} GB/min, {rate * 60 / 1000 / workers:.2f} GB/min per worker; "
            f"{steps + len(PlayDataset.open(out))} frames)"
        )
        if workers == 2:
            shutil.rmtree(out)
    # the LeRobot export of the same data: the MP4 encoding dominates
    started = time.perf_counter()
    exported = export_lerobot(PlayDataset.open(root / "data_1_local"), root / "lerobot")
    seconds = time.perf_counter() - started
    print(
        f"lerobot export: {exported.frames} frames ({WIDTH}x{HEIGHT}, h264) in {seconds:.2f} s = "
        f"{exported.frames / seconds:.0f} frames/s"
    )
    shutil.rmtree(root, ignore_errors=True)


if __name__ == "__main__":
    main()
