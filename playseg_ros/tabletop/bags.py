"""Tabletop play as a robot records it: rosbag2 bags of standard messages, written with `rosbags` (no
ROS graph needed).

One bag per play episode, ``<out>/<episode id>/``:

    /camera/image_raw             sensor_msgs/msg/Image, rgb8, at the control rate (10 Hz)
    /camera/image_raw/compressed  sensor_msgs/msg/CompressedImage, jpeg (``images="jpeg"`` or "both")
    /joint_states                 sensor_msgs/msg/JointState: the effector's two axes, position (m) and
                                  velocity (m/s), at the state rate (50 Hz by default)
    /cmd_vel                      geometry_msgs/msg/Twist: linear.x, linear.y = the commanded velocity
                                  (m/s), sent at each control step
    /annotations                  playseg_msgs/msg/TimedAnnotation: each instruction with its start and end
                                  time (annotated bags only)

and, in the bag directory next to the storage file, ``ground_truth.json``: every instruction segment as
times (the sidecar format of `playseg convert`), also for bags without annotations. ``<out>`` holds
``mapping.yaml`` (train: the annotations topic) and ``mapping_truth.yaml`` (the ground truth file) for
`playseg convert`, and ``samples.json`` listing the bags.

The log comes from the domain package through its public interface (`load_domain`), as
`playseg generate` gets its data.
"""

from __future__ import annotations

import json
import shutil
import sys
from collections.abc import Sequence
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any, Protocol

import cv2
import numpy as np
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys.store import Typestore

from playseg_core.domains import load_domain
from playseg_ros.typestore import playseg_typestore

CAMERA_TOPIC = "/camera/image_raw"
COMPRESSED_TOPIC = "/camera/image_raw/compressed"
JOINT_TOPIC = "/joint_states"
COMMAND_TOPIC = "/cmd_vel"
ANNOTATION_TOPIC = "/annotations"
CAMERA_FRAME = "top_camera"
TRUTH_FILE = "ground_truth.json"
MANIFEST_FILE = "samples.json"
IMAGE_CHOICES = ("raw", "jpeg", "both")
JPEG_QUALITY = 90

IMAGE = "sensor_msgs/msg/Image"
COMPRESSED_IMAGE = "sensor_msgs/msg/CompressedImage"
JOINT_STATE = "sensor_msgs/msg/JointState"
TWIST = "geometry_msgs/msg/Twist"
TIMED_ANNOTATION = "playseg_msgs/msg/TimedAnnotation"


class RobotLog(Protocol):
    """What the writer reads of a domain's robot log (playseg_core.domains.tabletop.robot_log)."""

    episode_id: str
    frame_ns: np.ndarray
    frames: np.ndarray
    joint_names: tuple[str, ...]
    joint_ns: np.ndarray
    joint_positions: np.ndarray
    joint_velocities: np.ndarray
    command_ns: np.ndarray
    commands: np.ndarray

    @property
    def segment_times(self) -> list[tuple[int, int, str]]: ...


@dataclass
class WrittenBag:
    """One bag written: where, what it holds (messages per topic), whether it carries annotations."""

    path: Path
    episode_id: str
    messages: dict[str, int]
    annotated: bool
    segments: int
    bytes_on_disk: int


def typestore() -> Typestore:
    """ROS 2 Kilted's standard types plus playseg_msgs (typestore.py; TimedAnnotation included)."""
    return playseg_typestore()


class _Messages:
    """Builds and serializes the messages of one bag."""

    def __init__(self, store: Typestore) -> None:
        self.store = store
        self.types = store.types

    def time(self, ns: int) -> Any:
        return self.types["builtin_interfaces/msg/Time"](sec=int(ns // 10**9), nanosec=int(ns % 10**9))

    def header(self, ns: int, frame: str = "") -> Any:
        return self.types["std_msgs/msg/Header"](stamp=self.time(ns), frame_id=frame)

    def serialize(self, msg: Any, type_name: str) -> bytes:
        return bytes(self.store.serialize_cdr(msg, type_name))

    def image(self, ns: int, frame: np.ndarray) -> bytes:
        height, width, _ = frame.shape
        msg = self.types[IMAGE](
            header=self.header(ns, CAMERA_FRAME),
            height=height,
            width=width,
            encoding="rgb8",
            is_bigendian=0,
            step=width * 3,
            data=np.ascontiguousarray(frame, dtype=np.uint8).reshape(-1),
        )
        return self.serialize(msg, IMAGE)

    def compressed(self, ns: int, frame: np.ndarray) -> bytes:
        ok, jpeg = cv2.imencode(
            ".jpg", cv2.cvtColor(frame, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY]
        )
        if not ok:
            raise ValueError("tabletop bag: OpenCV could not encode a camera frame as jpeg")
        msg = self.types[COMPRESSED_IMAGE](
            header=self.header(ns, CAMERA_FRAME), format="jpeg", data=jpeg.reshape(-1)
        )
        return self.serialize(msg, COMPRESSED_IMAGE)

    def joint_state(self, ns: int, names: Sequence[str], position: np.ndarray, velocity: np.ndarray) -> bytes:
        msg = self.types[JOINT_STATE](
            header=self.header(ns),
            name=list(names),
            position=np.asarray(position, np.float64),
            velocity=np.asarray(velocity, np.float64),
            effort=np.zeros(0, np.float64),
        )
        return self.serialize(msg, JOINT_STATE)

    def twist(self, command: np.ndarray) -> bytes:
        vector = self.types["geometry_msgs/msg/Vector3"]
        msg = self.types[TWIST](
            linear=vector(x=float(command[0]), y=float(command[1]), z=0.0),
            angular=vector(x=0.0, y=0.0, z=0.0),
        )
        return self.serialize(msg, TWIST)

    def annotation(self, start_ns: int, end_ns: int, instruction: str, episode_id: str) -> bytes:
        # Stamped when the annotator closes the label: at its end.
        msg = self.types[TIMED_ANNOTATION](
            header=self.header(end_ns),
            start=self.time(start_ns),
            end=self.time(end_ns),
            instruction=instruction,
            episode_id=episode_id,
        )
        return self.serialize(msg, TIMED_ANNOTATION)


def write_robot_bag(
    log: RobotLog,
    path: str | Path,
    *,
    annotate: bool,
    images: str = "raw",
    storage: str = "mcap",
) -> WrittenBag:
    """Write ``log`` as one rosbag2 bag at ``path`` (which must not exist) plus its ground-truth file."""
    if images not in IMAGE_CHOICES:
        raise ValueError(f"tabletop bag: images must be one of {', '.join(IMAGE_CHOICES)}, got {images!r}")
    if storage not in ("mcap", "sqlite3"):
        raise ValueError(f"tabletop bag: storage must be mcap or sqlite3, got {storage!r}")
    path = Path(path)
    if path.exists():
        raise FileExistsError(f"{path}: exists; a bag is written only into a new directory")
    store = typestore()
    build = _Messages(store)
    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    # Every message with its time, then written in time order (as a recorder would receive them).
    timeline: list[tuple[int, int, str, bytes]] = []
    for ns, frame in zip(log.frame_ns.tolist(), log.frames, strict=True):
        if images in ("raw", "both"):
            timeline.append((ns, 0, CAMERA_TOPIC, build.image(ns, frame)))
        if images in ("jpeg", "both"):
            timeline.append((ns, 1, COMPRESSED_TOPIC, build.compressed(ns, frame)))
    for ns, position, velocity in zip(
        log.joint_ns.tolist(), log.joint_positions, log.joint_velocities, strict=True
    ):
        timeline.append((ns, 2, JOINT_TOPIC, build.joint_state(ns, log.joint_names, position, velocity)))
    for ns, command in zip(log.command_ns.tolist(), log.commands, strict=True):
        timeline.append((ns, 3, COMMAND_TOPIC, build.twist(command)))
    segments = log.segment_times
    if annotate:
        for start_ns, end_ns, instruction in segments:
            timeline.append(
                (end_ns, 4, ANNOTATION_TOPIC, build.annotation(start_ns, end_ns, instruction, log.episode_id))
            )
    timeline.sort(key=lambda item: (item[0], item[1]))
    types = {
        CAMERA_TOPIC: IMAGE,
        COMPRESSED_TOPIC: COMPRESSED_IMAGE,
        JOINT_TOPIC: JOINT_STATE,
        COMMAND_TOPIC: TWIST,
        ANNOTATION_TOPIC: TIMED_ANNOTATION,
    }
    counts: dict[str, int] = {}
    for _, _, topic, _ in timeline:
        counts[topic] = counts.get(topic, 0) + 1
    with Writer(path, version=9, storage_plugin=plugin) as writer:
        connections = {topic: writer.add_connection(topic, types[topic], typestore=store) for topic in counts}
        for ns, _, topic, data in timeline:
            writer.write(connections[topic], ns, data)
    start = int(log.frame_ns[0])
    truth = {
        "times": "from_start",
        "annotations": [
            {"start": (s - start) / 1e9, "end": (e - start) / 1e9, "instruction": text}
            for s, e, text in segments
        ],
    }
    (path / TRUTH_FILE).write_text(json.dumps(truth, indent=1) + "\n", encoding="utf-8")
    size = sum(f.stat().st_size for f in path.rglob("*") if f.is_file())
    return WrittenBag(path, log.episode_id, counts, annotate, len(segments), size)


def mapping_yaml(images: str, annotations: str) -> str:
    """A `playseg convert` mapping for these bags; ``annotations``: a topic or sidecar file entry."""
    camera = COMPRESSED_TOPIC if images == "jpeg" else CAMERA_TOPIC
    return f"""\
# playseg convert mapping for tabletop robot bags (playseg_ros/tabletop/bags.py)
fps: 10
primary: observation.images.top
tolerance_ms: 5
features:
  observation.images.top: {{topic: {camera}}}
  observation.state: {{topic: {JOINT_TOPIC}, fields: [position, velocity]}}
  action:
    topic: {COMMAND_TOPIC}
    fields: [linear.x, linear.y]
    align: previous                       # the command in effect at the frame (sent with it)
    tolerance_ms: 100                     # the last frame has no command of its own: keep it
    low: [-0.2, -0.2]
    high: [0.2, 0.2]
annotations: {annotations}
episodes: {{split: bag}}
"""


def write_sample_bags(
    out: str | Path,
    *,
    seed: int = 0,
    episodes: int = 3,
    annotated: int = 1,
    images: str = "raw",
    state_hz: float = 50.0,
    tasks_per_episode: tuple[int, int] = (4, 6),
    image_size: int = 96,
    storage: str = "mcap",
    overwrite: bool = False,
    domain: str = "tabletop",
) -> list[WrittenBag]:
    """``episodes`` tabletop play episodes (seeds ``seed * 10**9 + i``, as `playseg generate`) as robot
    bags in ``out``; the first ``annotated`` of them carry the annotations topic."""
    if images not in IMAGE_CHOICES:
        raise ValueError(f"tabletop bag: images must be one of {', '.join(IMAGE_CHOICES)}, got {images!r}")
    if episodes < 1 or not 0 <= annotated <= episodes:
        raise ValueError(
            f"tabletop sample bags: need episodes >= 1 and 0 <= annotated <= episodes, got {episodes}, {annotated}"
        )
    out = Path(out)
    if out.exists():
        if not overwrite:
            raise FileExistsError(f"{out}: exists; replace it only with overwrite (--overwrite)")
        if not (out / MANIFEST_FILE).is_file():
            raise FileExistsError(f"{out}: exists and holds no {MANIFEST_FILE}; refusing to replace it")
        shutil.rmtree(out)
    play = load_domain(domain)
    config = play.play_config(tasks_per_episode=tasks_per_episode, image_size=image_size)
    staging = out.with_name(f".{out.name}.partial")
    shutil.rmtree(staging, ignore_errors=True)
    staging.mkdir(parents=True)
    written = []
    try:
        for index in range(episodes):
            log = play.record_robot_log(config, seed * 10**9 + index, state_hz=state_hz)
            bag = write_robot_bag(
                log, staging / log.episode_id, annotate=index < annotated, images=images, storage=storage
            )
            written.append(bag)
        (staging / "mapping.yaml").write_text(mapping_yaml(images, f"{{topic: {ANNOTATION_TOPIC}}}"))
        (staging / "mapping_truth.yaml").write_text(mapping_yaml(images, f"{{file: {TRUTH_FILE}}}"))
        manifest = {
            "domain": domain,
            "seed": seed,
            "images": images,
            "state_hz": state_hz,
            "bags": [{**asdict(bag), "path": bag.path.name} for bag in written],
        }
        (staging / MANIFEST_FILE).write_text(json.dumps(manifest, indent=1) + "\n", encoding="utf-8")
        staging.rename(out)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    return [replace(bag, path=out / bag.path.name) for bag in written]


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m playseg_ros.tabletop.bags --out DIR``: write sample bags (not yet part of `make bags`)."""
    import argparse

    parser = argparse.ArgumentParser(description="tabletop play as standard-message robot bags")
    parser.add_argument("--out", required=True, help="directory to create (one bag per episode inside)")
    parser.add_argument("--episodes", type=int, default=3)
    parser.add_argument("--annotated", type=int, default=1, help="how many of the bags carry /annotations")
    parser.add_argument("--images", choices=IMAGE_CHOICES, default="jpeg")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--overwrite", action="store_true")
    args = parser.parse_args(argv)
    try:
        bags = write_sample_bags(
            args.out,
            seed=args.seed,
            episodes=args.episodes,
            annotated=args.annotated,
            images=args.images,
            overwrite=args.overwrite,
        )
    except (ValueError, OSError) as error:
        print(f"tabletop bags: {error}", file=sys.stderr)
        return 1
    for bag in bags:
        counts = ", ".join(f"{topic} {n}" for topic, n in bag.messages.items())
        print(
            f"{bag.path}: {bag.segments} segments{' (annotated)' if bag.annotated else ''}; {counts}; "
            f"{bag.bytes_on_disk / 1e6:.2f} MB"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())


__all__ = [
    "ANNOTATION_TOPIC",
    "CAMERA_TOPIC",
    "COMMAND_TOPIC",
    "COMPRESSED_TOPIC",
    "JOINT_TOPIC",
    "TRUTH_FILE",
    "WrittenBag",
    "mapping_yaml",
    "typestore",
    "write_robot_bag",
    "write_sample_bags",
]
