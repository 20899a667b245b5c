"""Recorder node throughput: a 640x480 rgb8 sensor_msgs/Image stream over DDS into a rosbag2 MCAP bag.

A publisher process publishes N serialized frames as fast as it can (RELIABLE + KEEP_ALL: a slow recorder
applies back-pressure instead of losing frames) to a recorder node process. Recorded MB/s = serialized
bytes / span of the recorder's receive stamps; the bag must hold all N frames. Beside it: the same bytes
written straight to MCAP with BagWriter (no DDS). Prints figures; not a test.

    .venv/bin/python benchmarks/bench_recorder.py [--frames 400] [--compression zstd none]
"""

from __future__ import annotations

import argparse
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from bench_bag_io import IMAGE, camera_frames

from playseg_ros.bag import BagReader, BagWriter, topic_info

TOPIC = "/camera/image"
DISTINCT_FRAMES = 24  # cycled; each published frame carries its index in header.stamp.sec


def publish(count: int) -> None:
    """The publisher process: wait for the recorder, publish `count` frames, wait for every ack."""
    import rclpy
    from rclpy.duration import Duration
    from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import Image

    frames = camera_frames(DISTINCT_FRAMES, np.random.default_rng(0))
    rclpy.init()
    node = rclpy.create_node("bench_camera")
    qos = QoSProfile(history=HistoryPolicy.KEEP_ALL, reliability=ReliabilityPolicy.RELIABLE)
    pub = node.create_publisher(Image, TOPIC, qos)
    while pub.get_subscription_count() == 0:
        time.sleep(0.01)
    time.sleep(0.5)  # let the subscription's side of the match settle
    for i in range(count):
        frame = bytearray(frames[i % len(frames)])
        frame[4:8] = i.to_bytes(4, "little")  # header.stamp.sec = frame index
        pub.publish(bytes(frame))
    acked = pub.wait_for_all_acked(Duration(seconds=120))
    print(f"published {count} frames, all acknowledged: {acked}", flush=True)
    node.destroy_node()
    rclpy.shutdown()


def record(count: int, compression: str, work: Path) -> dict[str, float]:
    """Run recorder + publisher processes; figures from the recorded bag."""
    out = work / f"rec-{compression}"
    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    env.setdefault("ROS_DOMAIN_ID", str(100 + os.getpid() % 100))
    recorder_cmd = [sys.executable, "-m", "playseg_ros.nodes.recorder", "--ros-args", "-p", f"output:={out}"]
    recorder_cmd += ["-p", f"topics:=[{TOPIC}]", "-p", f"compression:={compression}"]
    recorder_cmd += ["-p", "flush_period_s:=0.1", "--log-level", "recorder:=debug"]  # "flushed: N messages"
    log_path = work / f"recorder-{compression}.log"
    with open(log_path, "wb") as log:
        recorder = subprocess.Popen(recorder_cmd, env=env, stdout=log, stderr=subprocess.STDOUT)
        try:
            subprocess.run(
                [sys.executable, __file__, "--publish", str(count)], env=env, timeout=300, check=True
            )
            deadline = time.monotonic() + 60  # until the recorder has written every frame (or gives up)
            while f"flushed: {count} messages" not in log_path.read_text() and time.monotonic() < deadline:
                time.sleep(0.05)
        finally:
            recorder.send_signal(signal.SIGINT)
            recorder.wait(timeout=120)
    with BagReader(out) as reader:
        messages = [(m.log_time_ns, int.from_bytes(m.data[4:8], "little")) for m in reader.messages([TOPIC])]
        payload = reader.metadata["relative_file_paths"]
    stamps = [stamp for stamp, _ in messages]
    if [index for _, index in messages] != list(range(count)):
        print(f"compression {compression}: frames missing or out of order", file=sys.stderr)
    size = len(camera_frames(1, np.random.default_rng(0))[0])
    span = (stamps[-1] - stamps[0]) / 1e9 * len(stamps) / max(1, len(stamps) - 1)
    on_disk = sum((out / p).stat().st_size for p in payload)
    return {
        "frames": len(stamps),
        "mb_s": len(stamps) * size / span / 1e6,
        "ratio": len(stamps) * size / on_disk,
    }


def write_direct(count: int, compression: str, work: Path) -> float:
    """MB/s of BagWriter alone on the same bytes."""
    frames = camera_frames(DISTINCT_FRAMES, np.random.default_rng(0))
    started = time.perf_counter()
    with BagWriter(work / f"direct-{compression}", compression=compression) as bag:
        bag.add_topic(topic_info(TOPIC, IMAGE))
        for i in range(count):
            bag.write(TOPIC, frames[i % len(frames)], time.time_ns())
    return count * len(frames[0]) / (time.perf_counter() - started) / 1e6


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=400, help="frames per run")
    parser.add_argument("--compression", nargs="+", default=["zstd", "none"], choices=("zstd", "none"))
    parser.add_argument("--publish", type=int, help=argparse.SUPPRESS)  # the publisher process
    args = parser.parse_args()
    if args.publish:
        publish(args.publish)
        return
    print(f"{args.frames} frames of 640x480 rgb8 ({640 * 480 * 3 / 1e6:.2f} MB each), chunks of 1 MB")
    print(
        f"{'compression':<12} {'recorder node MB/s':>19} {'recorded':>9} {'ratio':>6} {'BagWriter MB/s':>15}"
    )
    with tempfile.TemporaryDirectory() as tmp:
        for compression in args.compression:
            rec = record(args.frames, compression, Path(tmp))
            direct = write_direct(args.frames, compression, Path(tmp))
            recorded = f"{rec['frames']}/{args.frames}"
            print(
                f"{compression:<12} {rec['mb_s']:>19.1f} {recorded:>9} {rec['ratio']:>6.2f} {direct:>15.1f}"
            )


if __name__ == "__main__":
    main()
