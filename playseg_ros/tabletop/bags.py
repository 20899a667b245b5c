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
`playseg convert`.

Two sources: `write_sample_bags` plays new episodes (``samples.json`` lists them; `make bags`), and
`write_dataset_bags` (`playseg generate --domain tabletop --bag`) writes a generated dataset's episodes,
replayed from their seeds and checked against the dataset, one directory of bags per split as the play
bags of `playseg generate --bag` (playseg_ros/play_bags.py: annotated, play, test). This package is the
tabletop domain's ROS side: the rates, bounds and sizes come from playseg_core/domains/tabletop (its
spec and the data's features).
"""

from __future__ import annotations

import json
import multiprocessing
import shutil
import sys
from collections.abc import Iterator, Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys.store import Typestore

from playseg_core.data.dataset import PlayDataset
from playseg_core.data.features import Features
from playseg_core.data.generation import episode_seed
from playseg_core.domains.tabletop.play import PlayConfig
from playseg_core.domains.tabletop.robot_log import (
    DEFAULT_STATE_HZ,
    EPISODE_GAP_NS,
    LOG_START_NS,
    RobotLog,
    consecutive_starts_ns,
    dataset_play_config,
    record_robot_log,
    replay_dataset_episode,
)
from playseg_core.domains.tabletop.spec import DEFAULT_IMAGE_SIZE, DOMAIN
from playseg_core.errors import PlaysegError
from playseg_ros.play_bags import DATASET_BAGS
from playseg_ros.typestore import playseg_typestore

CAMERA_TOPIC = "/camera/image_raw"
COMPRESSED_TOPIC = "/camera/image_raw/compressed"
JOINT_TOPIC = "/joint_states"
COMMAND_TOPIC = "/cmd_vel"
ANNOTATION_TOPIC = "/annotations"
CAMERA_FRAME = "top_camera"
TRUTH_FILE = "ground_truth.json"
MANIFEST_FILE = "samples.json"
MAPPING_FILE = "mapping.yaml"
TRUTH_MAPPING_FILE = "mapping_truth.yaml"
IMAGE_CHOICES = ("raw", "jpeg", "both")
JPEG_QUALITY = 90

IMAGE = "sensor_msgs/msg/Image"
COMPRESSED_IMAGE = "sensor_msgs/msg/CompressedImage"
JOINT_STATE = "sensor_msgs/msg/JointState"
TWIST = "geometry_msgs/msg/Twist"
TIMED_ANNOTATION = "playseg_msgs/msg/TimedAnnotation"


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
            raise PlaysegError("tabletop bag: OpenCV could not encode a camera frame as jpeg")
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
    _check_images(images)
    if storage not in ("mcap", "sqlite3"):
        raise PlaysegError(f"tabletop bag: storage must be mcap or sqlite3, got {storage!r}")
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


def _numbers(values: Sequence[float] | None) -> str:
    if values is None:
        raise PlaysegError("tabletop bag mapping: the action declares no low/high bounds")
    return f"[{', '.join(f'{value:g}' for value in values)}]"


def mapping_yaml(features: Features, images: str, annotations: str) -> str:
    """A `playseg convert` mapping that reads these bags back into data of ``features`` (the played
    config's or the dataset's: step rate, camera, state, action bounds); ``annotations``: a topic or
    sidecar file entry."""
    if features.fps is None or features.state is None or len(features.cameras) != 1:
        raise PlaysegError("tabletop bag mapping: the features must declare fps, one camera and a state")
    camera = features.cameras[0]
    topic = COMPRESSED_TOPIC if images == "jpeg" else CAMERA_TOPIC
    action = features.action
    return f"""\
# playseg convert mapping for tabletop robot bags (playseg_ros/tabletop/bags.py)
fps: {features.fps:g}
primary: {camera}
tolerance_ms: 5
features:
  {camera}: {{topic: {topic}}}
  {features.state.name}: {{topic: {JOINT_TOPIC}, fields: [position, velocity]}}
  {action.name}:
    topic: {COMMAND_TOPIC}
    fields: [linear.x, linear.y]
    align: previous                       # the command in effect at the frame (sent with it)
    tolerance_ms: {1000 / features.fps:g}                     # the last frame has no command of its own: keep it
    low: {_numbers(action.low)}
    high: {_numbers(action.high)}
annotations: {annotations}
episodes: {{split: bag}}
domain: {DOMAIN}                         # train with the tabletop's encoders and symmetries
"""


def _write_mappings(out: Path, features: Features, images: str) -> None:
    (out / MAPPING_FILE).write_text(mapping_yaml(features, images, f"{{topic: {ANNOTATION_TOPIC}}}"))
    (out / TRUTH_MAPPING_FILE).write_text(mapping_yaml(features, images, f"{{file: {TRUTH_FILE}}}"))


def _check_images(images: str) -> None:
    if images not in IMAGE_CHOICES:
        raise PlaysegError(f"tabletop bag: images must be one of {', '.join(IMAGE_CHOICES)}, got {images!r}")


def write_sample_bags(
    out: str | Path,
    *,
    seed: int = 0,
    episodes: int = 3,
    annotated: int = 1,
    images: str = "raw",
    state_hz: float = DEFAULT_STATE_HZ,
    tasks_per_episode: tuple[int, int] = (4, 6),
    tasks: Sequence[int] | None = None,
    task_set: str = "all",
    image_size: int = DEFAULT_IMAGE_SIZE,
    storage: str = "mcap",
    overwrite: bool = False,
) -> list[WrittenBag]:
    """``episodes`` tabletop play episodes (seeds ``seed * 10**9 + i``, as `playseg generate`) as robot
    bags in ``out``, recorded one after the other (`EPISODE_GAP_NS` apart); the first ``annotated`` of
    them carry the annotations topic. ``tasks``, when given, is each bag's number of solved tasks (one bag
    per entry, in place of ``episodes`` and ``tasks_per_episode``); ``task_set`` the instructions play
    gives (`PlayConfig.task_set`)."""
    _check_images(images)
    if tasks is not None:
        if not tasks or any(count < 1 for count in tasks):
            raise PlaysegError(f"tabletop sample bags: tasks must be counts >= 1, got {list(tasks)}")
        episodes = len(tasks)
    if episodes < 1 or not 0 <= annotated <= episodes:
        raise PlaysegError(
            f"tabletop sample bags: need episodes >= 1 and 0 <= annotated <= episodes, got {episodes}, {annotated}"
        )
    out = Path(out)
    if out.exists():
        if not overwrite:
            raise FileExistsError(f"{out}: exists; replace it only with overwrite (--overwrite)")
        if not (out / MANIFEST_FILE).is_file():
            raise FileExistsError(f"{out}: exists and holds no {MANIFEST_FILE}; refusing to replace it")
        shutil.rmtree(out)
    config = PlayConfig(tasks_per_episode=tasks_per_episode, image_size=image_size, task_set=task_set)
    staging = out.with_name(f".{out.name}.partial")
    shutil.rmtree(staging, ignore_errors=True)
    staging.mkdir(parents=True)
    written = []
    try:
        start_ns = LOG_START_NS
        for index in range(episodes):
            played = config if tasks is None else replace(config, tasks_per_episode=(tasks[index],) * 2)
            log = record_robot_log(played, episode_seed(seed, index), state_hz=state_hz, start_ns=start_ns)
            start_ns = log.end_ns + EPISODE_GAP_NS
            bag = write_robot_bag(
                log, staging / log.episode_id, annotate=index < annotated, images=images, storage=storage
            )
            written.append(bag)
        _write_mappings(staging, config.features, images)
        manifest = {
            "domain": DOMAIN,
            "seed": seed,
            "task_set": task_set,
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


@dataclass(frozen=True)
class _BagTask:
    """One dataset episode to write as a bag (what a worker process needs)."""

    dataset: str
    index: int
    config: PlayConfig
    path: Path
    annotate: bool
    images: str
    state_hz: float
    storage: str
    start_ns: int


_OPEN: dict[str, PlayDataset] = {}


def _write_dataset_bag(task: _BagTask) -> WrittenBag:
    dataset = _OPEN.get(task.dataset)
    if dataset is None:  # one open per process: the arrays stay memory-mapped between episodes
        dataset = _OPEN[task.dataset] = PlayDataset.open(task.dataset)
    log = replay_dataset_episode(
        dataset, task.index, task.config, state_hz=task.state_hz, start_ns=task.start_ns
    )
    return write_robot_bag(log, task.path, annotate=task.annotate, images=task.images, storage=task.storage)


def _run(tasks: list[_BagTask], workers: int) -> Iterator[WrittenBag]:
    if workers == 1 or len(tasks) <= 1:
        yield from map(_write_dataset_bag, tasks)
        return
    # spawn: the parent may hold threads (tqdm, ROS, torch) that fork would copy half-locked. An
    # executor, not multiprocessing.Pool, whose terminate can wait forever for a killed worker's lock
    # (playseg_core/data/generation.py); stopped early, the bags not started are cancelled.
    context = multiprocessing.get_context("spawn")
    pool = ProcessPoolExecutor(min(workers, len(tasks)), mp_context=context)
    try:
        yield from pool.map(_write_dataset_bag, tasks)
    finally:
        pool.shutdown(wait=True, cancel_futures=True)


def write_dataset_bags(
    dataset_dir: str | Path,
    out_dir: str | Path,
    *,
    images: str = "raw",
    workers: int = 1,
    state_hz: float = DEFAULT_STATE_HZ,
    storage: str = "mcap",
) -> dict[str, list[WrittenBag]]:
    """A generated tabletop dataset's episodes as robot bags, one directory per dataset bag of
    `playseg generate --bag` (play_bags.DATASET_BAGS): ``out_dir/annotated/<episode id>/`` (train + val,
    with the annotations topic), ``out_dir/play/...`` and ``out_dir/test/...`` (ground truth only in the
    sidecar), plus ``out_dir/mapping.yaml`` and ``mapping_truth.yaml``.

    The episodes are recorded one after the other in the dataset's order (`consecutive_starts_ns`).
    Every episode is replayed from its seed and checked against the dataset, so converting a directory
    with the mapping gives back its episodes (with ``images="raw"`` or "both"; "jpeg" frames are lossy).
    Written into ``out_dir/.partial`` and moved into place at the end: nothing half-written stays.
    """
    _check_images(images)
    if workers < 1:
        raise PlaysegError(f"tabletop bags: workers must be >= 1, got {workers}")
    dataset = PlayDataset.open(dataset_dir)
    config = dataset_play_config(dataset)
    out = Path(out_dir)
    names = [*DATASET_BAGS, MAPPING_FILE, TRUTH_MAPPING_FILE]
    for name in names:  # refuse before writing anything
        if (out / name).exists():
            raise FileExistsError(f"{out / name}: already exists (remove it to write new bags)")
    created = not out.exists()
    staging = out / ".partial"
    shutil.rmtree(staging, ignore_errors=True)
    tasks: list[_BagTask] = []
    starts = consecutive_starts_ns([record.num_steps for record in dataset.records])
    for name, (splits, annotated) in DATASET_BAGS.items():
        (staging / name).mkdir(parents=True)
        for index in sorted(i for split in splits for i in dataset.episode_indices(split)):
            path = staging / name / dataset.records[index].episode_id
            task = _BagTask(
                str(dataset.path), index, config, path, annotated, images, state_hz, storage, starts[index]
            )
            tasks.append(task)
    try:
        written = list(_run(tasks, workers))
        _write_mappings(staging, dataset.features, images)
        for name in names:
            (staging / name).rename(out / name)
        staging.rmdir()
    except BaseException:
        shutil.rmtree(out if created else staging, ignore_errors=True)
        raise
    by_name: dict[str, list[WrittenBag]] = {name: [] for name in DATASET_BAGS}
    for bag in written:
        name = bag.path.parent.name
        by_name[name].append(replace(bag, path=out / name / bag.path.name))
    return by_name


def write_generated_bags(
    dataset_dir: str | Path, out_dir: str | Path, images: str = "raw", workers: int = 1
) -> list[str]:
    """`playseg generate --domain tabletop --bag`: `write_dataset_bags`, one summary line per directory."""
    lines = []
    for name, bags in write_dataset_bags(dataset_dir, out_dir, images=images, workers=workers).items():
        messages = sum(sum(bag.messages.values()) for bag in bags)
        size = sum(bag.bytes_on_disk for bag in bags)
        annotated = " with annotations" if any(bag.annotated for bag in bags) else ""
        lines.append(
            f"{Path(out_dir) / name}: {len(bags)} robot bags{annotated}, {messages} messages, {size / 1e6:.2f} MB"
        )
    mappings = ", ".join(str(Path(out_dir) / name) for name in (MAPPING_FILE, TRUTH_MAPPING_FILE))
    lines.append(f"convert them with {mappings}")
    return lines


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m playseg_ros.tabletop.bags --out DIR``: write sample bags (`make bags`)."""
    import argparse

    parser = argparse.ArgumentParser(description="tabletop play as standard-message robot bags")
    parser.add_argument("--out", required=True, help="directory to create (one bag per episode inside)")
    parser.add_argument("--episodes", type=int, default=3)
    parser.add_argument(
        "--tasks",
        type=int,
        nargs="+",
        help="each bag's number of solved tasks, one bag per value (in place of --episodes)",
    )
    parser.add_argument(
        "--task-set", default="all", help="the instructions play gives: all (197) or calvin (32 task types)"
    )
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
            tasks=args.tasks,
            task_set=args.task_set,
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
    "MAPPING_FILE",
    "TRUTH_FILE",
    "TRUTH_MAPPING_FILE",
    "WrittenBag",
    "mapping_yaml",
    "typestore",
    "write_dataset_bags",
    "write_generated_bags",
    "write_robot_bag",
    "write_sample_bags",
]
