"""LabelledSegment sizes in both forms, and what resolving the reference form costs the trainer.

Sizes: rclpy-serialized LabelledSegment of a 100-step segment (101 PlaySteps, rgb8 frames, a 7-value
state and action) embedded, and as a reference (no steps). Resolving: a recording of `--steps` PlaySteps
(one 640x480 camera, zstd chunks of 1 MB as the recorder writes them) is indexed once
(`RecordedSteps`, first call), then 100-step segments are read back from it. Prints figures; not a test.

    .venv/bin/python benchmarks/bench_segment_forms.py [--steps 600]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
from rclpy.serialization import serialize_message

from playseg_core.data.episode import Segment
from playseg_ros.bag import BagWriter, topic_info
from playseg_ros.messages import (
    PLAY_STEP,
    RCLPY,
    ROSBAGS,
    labelled_segment_of_steps,
    labelled_segment_reference,
    play_step_message,
)
from playseg_ros.recorded_steps import RecordedSteps, reference_of
from playseg_ros.typestore import playseg_typestore

TOPIC = "/play/steps"
SEGMENT = Segment(0, 100, "put the red block left of the blue one", 0.9, -3.0)


def _steps(count: int, cameras: int, height: int, width: int, kind, seed: int = 0) -> Iterator[Any]:
    """``count`` PlaySteps of noise frames (zstd cannot shrink them), a fresh frame each step."""
    rng = np.random.default_rng(seed)
    state = np.zeros(7, np.float32)
    for t in range(count):
        frames = {
            f"observation.images.cam{i}": rng.integers(0, 256, (height, width, 3), dtype=np.uint8)
            for i in range(cameras)
        }
        action = None if t == count - 1 else state
        yield play_step_message("live:0", t, frames, state, action, 10**18 + t, kind=kind)


def sizes() -> None:
    print("| cameras | PlayStep | embedded (100 steps) | reference |")
    for cameras, (height, width) in ((1, (480, 640)), (2, (480, 640)), (1, (96, 128))):
        steps = list(_steps(SEGMENT.length + 1, cameras, height, width, RCLPY))
        embedded = labelled_segment_of_steps("live:0", SEGMENT, steps, "robot.pt", 10**18, kind=RCLPY)
        reference = labelled_segment_reference(
            "live:0", SEGMENT, "robot.pt", 10**18, ("/data/bags/arm_0001", TOPIC), (10**18, 10**18 + 100),
            kind=RCLPY,
        )  # fmt: skip
        print(
            f"| {cameras} x {width}x{height} | {len(serialize_message(steps[0])):,} B "
            f"| {len(serialize_message(embedded)):,} B | {len(serialize_message(reference)):,} B |"
        )


def resolving(count: int) -> None:
    store = playseg_typestore()
    with tempfile.TemporaryDirectory() as tmp:
        bag = Path(tmp) / "recording"
        with BagWriter(bag) as writer:
            writer.add_topic(topic_info(TOPIC, PLAY_STEP))
            for msg in _steps(count, 1, 480, 640, ROSBAGS):
                writer.write(TOPIC, bytes(store.serialize_cdr(msg, PLAY_STEP)), 10**18 + int(msg.step))
        recorded = RecordedSteps(bag, TOPIC)
        times = []
        for start in range(0, count - SEGMENT.length, SEGMENT.length):
            segment = Segment(start, start + SEGMENT.length, "x")
            msg = labelled_segment_reference(
                "live:0", segment, "m", 0, (str(bag), TOPIC), (10**18 + start, 10**18 + segment.end)
            )
            began = time.perf_counter()
            steps = recorded.steps(reference_of(msg))
            times.append(time.perf_counter() - began)
            assert [int(s.step) for s in steps] == list(range(start, segment.end + 1))
        size = sum(f.stat().st_size for f in bag.glob("*.mcap")) / 1e6
        print(
            f"recording of {count} steps ({size:.0f} MB): first segment (indexes the bag) {times[0]:.2f} s; "
            f"each further 100-step segment {np.median(times[1:]) * 1e3:.0f} ms (median of {len(times) - 1})"
        )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=600)
    args = parser.parse_args()
    sizes()
    resolving(args.steps)


if __name__ == "__main__":
    main()
