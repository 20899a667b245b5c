"""`playseg convert`: robot bags written by rosbags (sqlite3 + zstd, MCAP split in two files, ROS 1)
through a mapping into a playseg dataset, checked value by value against what was written."""

from __future__ import annotations

import json
import shutil
import sqlite3
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
import yaml
from rosbags.rosbag1 import Writer as Ros1Writer
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.rosbag2.enums import CompressionFormat, CompressionMode
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from playseg_core.data.dataset import PlayDataset
from playseg_core.data.episode import Episode
from playseg_ros.cli import main
from playseg_ros.convert import MappingError, convert, load_mapping
from playseg_ros.convert.alignment import align
from playseg_ros.convert.source import convert_typestore

T0 = 1_700_000_000 * 10**9
CAMERA_HZ, JOINT_HZ, TWIST_HZ = 30, 100, 10
WIDTH, HEIGHT = 32, 24
JOINTS = ("shoulder", "elbow", "wrist")
TWIST_OFFSET_NS = 5_000_000  # commands arrive 5 ms after the frames they belong to
LABELS = [(0.3, 1.2, "pick up the cup"), (1.2, 2.5, "put the cup down")]

MAPPING = {
    "fps": 10,
    "primary": "observation.images.front",
    "tolerance_ms": 20,
    "features": {
        "observation.images.front": {"topic": "/camera/image_raw"},
        "observation.state": {"topic": "/joint_states", "field": "position"},
        "action": {"topic": "/cmd_vel", "fields": ["linear.x", "linear.y", "angular.z"]},
    },
    "annotations": {"topic": "/annotations"},
    "episodes": {"split": "bag"},
}


def frame(i: int) -> np.ndarray:
    """Camera frame i: every pixel says which frame it is (and where it is)."""
    image = np.zeros((HEIGHT, WIDTH, 3), dtype=np.uint8)
    image[..., 0] = i % 256
    image[..., 1] = np.arange(WIDTH, dtype=np.uint8)[None, :]
    image[..., 2] = np.arange(HEIGHT, dtype=np.uint8)[:, None] * 3
    return image


def joint_position(k: int) -> np.ndarray:
    return np.array([k, 2 * k, 0.5], dtype=np.float32)


def twist_values(m: int) -> tuple[float, float, float]:
    return float(m), 0.25, -float(m)


def ns(seconds: float) -> int:
    return T0 + round(seconds * 1e9)


@dataclass
class RobotBag:
    """What to write: seconds of camera, joints and commands, labels, and any damage to do."""

    seconds: float = 3.0
    camera: str = "raw"  # raw (rgb8 Image), bgr8, mono8, png, jpeg (CompressedImage)
    labels: list[tuple[float, float, str]] = field(default_factory=lambda: list(LABELS))
    joint_gap: tuple[float, float] | None = None  # no JointState in [a, b)
    camera_gap: tuple[float, float] | None = None  # no camera frame in [a, b)
    camera_topic: str = "/camera/image_raw"
    bad_image_at: int | None = None  # this frame's CompressedImage bytes are garbage
    silence: tuple[float, float] | None = None  # no message of any topic in [a, b) seconds
    markers: list[float] = field(default_factory=list)  # std_msgs/Empty on /episode_start
    joints: tuple[str, ...] = JOINTS
    stamped_commands: bool = False  # TwistStamped (a header: the same time live as recorded) instead of Twist

    def camera_times(self) -> list[int]:
        return [ns(i / CAMERA_HZ) for i in range(round(self.seconds * CAMERA_HZ))]

    def messages(self, store: Any) -> list[tuple[str, str, int, Any]]:
        """(topic, type, time, message) in time order."""
        types = store.types
        Time, Header = types["builtin_interfaces/msg/Time"], types["std_msgs/msg/Header"]

        ros1 = {"seq": 0} if "seq" in Header.__dataclass_fields__ else {}

        def header(t: int, frame_id: str = "base") -> Any:
            return Header(**ros1, stamp=Time(sec=t // 10**9, nanosec=t % 10**9), frame_id=frame_id)

        out: list[tuple[str, str, int, Any]] = []
        for i, t in enumerate(self.camera_times()):
            if self.camera_gap and ns(self.camera_gap[0]) <= t < ns(self.camera_gap[1]):
                continue
            image = frame(i)
            if self.camera in ("png", "jpeg"):
                ok, data = cv2.imencode(f".{self.camera}", cv2.cvtColor(image, cv2.COLOR_RGB2BGR))
                assert ok
                payload = (
                    np.frombuffer(b"not an image" * 4, np.uint8) if i == self.bad_image_at else data.ravel()
                )
                msg = types["sensor_msgs/msg/CompressedImage"](
                    header=header(t, "cam"), format=self.camera, data=payload
                )
                out.append((self.camera_topic, "sensor_msgs/msg/CompressedImage", t, msg))
                continue
            encoding = {"raw": "rgb8", "bgr8": "bgr8", "mono8": "mono8"}[self.camera]
            pixels = {"rgb8": image, "bgr8": image[..., ::-1], "mono8": image[..., 0]}[encoding]
            channels = 1 if encoding == "mono8" else 3
            msg = types["sensor_msgs/msg/Image"](
                header=header(t, "cam"), height=HEIGHT, width=WIDTH, encoding=encoding, is_bigendian=0,
                step=WIDTH * channels, data=np.ascontiguousarray(pixels).reshape(-1),
            )  # fmt: skip
            out.append((self.camera_topic, "sensor_msgs/msg/Image", t, msg))
        for k in range(round(self.seconds * JOINT_HZ)):
            seconds = k / JOINT_HZ
            if self.joint_gap and self.joint_gap[0] <= seconds < self.joint_gap[1]:
                continue
            t = ns(seconds)
            msg = types["sensor_msgs/msg/JointState"](
                header=header(t), name=list(self.joints), position=joint_position(k).astype(np.float64),
                velocity=np.zeros(3), effort=np.zeros(3),
            )  # fmt: skip
            out.append(("/joint_states", "sensor_msgs/msg/JointState", t, msg))
        Vector3 = types["geometry_msgs/msg/Vector3"]
        for m in range(round(self.seconds * TWIST_HZ)):
            t = ns(m / TWIST_HZ) + TWIST_OFFSET_NS
            x, y, z = twist_values(m)
            msg = types["geometry_msgs/msg/Twist"](
                linear=Vector3(x=x, y=y, z=0.0), angular=Vector3(x=0.0, y=0.0, z=z)
            )
            if self.stamped_commands:
                msg = types["geometry_msgs/msg/TwistStamped"](header=header(t), twist=msg)
            out.append(("/cmd_vel", f"geometry_msgs/msg/Twist{'Stamped' * self.stamped_commands}", t, msg))
        if "playseg_msgs/msg/TimedAnnotation" in types:
            for start, end, text in self.labels:
                t = ns(end)
                msg = types["playseg_msgs/msg/TimedAnnotation"](
                    header=header(t), start=Time(sec=ns(start) // 10**9, nanosec=ns(start) % 10**9),
                    end=Time(sec=ns(end) // 10**9, nanosec=ns(end) % 10**9), instruction=text, episode_id="",
                )  # fmt: skip
                out.append(("/annotations", "playseg_msgs/msg/TimedAnnotation", t, msg))
        for seconds in self.markers:
            out.append(("/episode_start", "std_msgs/msg/Empty", ns(seconds), types["std_msgs/msg/Empty"]()))
        if self.silence:
            out = [m for m in out if not ns(self.silence[0]) <= m[2] < ns(self.silence[1])]
        return sorted(out, key=lambda item: item[2])


def write_rosbag2(
    path: Path,
    spec: RobotBag,
    storage: str = "mcap",
    zstd: bool | str = False,
    start: float = 0.0,
    stop: float = 1e9,
) -> Path:
    """A rosbag2 bag written by rosbags holding ``spec``'s messages with times in [start, stop) seconds."""
    store = convert_typestore()
    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    writer = Writer(path, version=9, storage_plugin=plugin)
    if zstd:  # True: each message compressed; "file": each storage file
        writer.set_compression(
            CompressionMode.FILE if zstd == "file" else CompressionMode.MESSAGE, CompressionFormat.ZSTD
        )
    with writer:
        connections: dict[str, Any] = {}
        for topic, msgtype, t, msg in spec.messages(store):
            if not ns(start) <= t < ns(stop):
                continue
            if topic not in connections:
                connections[topic] = writer.add_connection(topic, msgtype, typestore=store)
            writer.write(connections[topic], t, store.serialize_cdr(msg, msgtype))
    return path


def write_split_mcap(path: Path, spec: RobotBag, at: float) -> Path:
    """One recording in two MCAP files (what rosbag2 writes with --max-bag-duration): rosbags writes both
    halves, and the second file joins the first bag's metadata."""
    first = write_rosbag2(path, spec, "mcap", stop=at)
    second = write_rosbag2(path.with_name(path.name + "-2"), spec, "mcap", start=at)
    meta_1 = yaml.safe_load((first / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    meta_2 = yaml.safe_load((second / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    name_2 = f"{path.name}_1.mcap"
    (second / meta_2["relative_file_paths"][0]).rename(first / name_2)
    shutil.rmtree(second)
    counts = {t["topic_metadata"]["name"]: t for t in meta_1["topics_with_message_count"]}
    for topic in meta_2["topics_with_message_count"]:
        name = topic["topic_metadata"]["name"]
        if name in counts:
            counts[name]["message_count"] += topic["message_count"]
        else:
            meta_1["topics_with_message_count"].append(topic)
    end = meta_2["starting_time"]["nanoseconds_since_epoch"] + meta_2["duration"]["nanoseconds"]
    meta_1["duration"]["nanoseconds"] = end - meta_1["starting_time"]["nanoseconds_since_epoch"]
    meta_1["message_count"] += meta_2["message_count"]
    meta_1["relative_file_paths"].append(name_2)
    file_2 = dict(meta_2["files"][0], path=name_2)
    meta_1["files"].append(file_2)
    (first / "metadata.yaml").write_text(yaml.safe_dump({"rosbag2_bagfile_information": meta_1}))
    return first


def write_ros1(path: Path, spec: RobotBag) -> Path:
    """A ROS 1 bag (no annotations: TimedAnnotation is a ROS 2 message)."""
    store = get_typestore(Stores.ROS1_NOETIC)
    with Ros1Writer(path) as writer:
        connections: dict[str, Any] = {}
        for topic, msgtype, t, msg in spec.messages(store):
            if topic not in connections:
                connections[topic] = writer.add_connection(topic, msgtype, typestore=store)
            writer.write(connections[topic], t, store.serialize_ros1(msg, msgtype))
    return path


def write_mapping(path: Path, mapping: dict[str, Any] | None = None, **changes: Any) -> Path:
    path.write_text(yaml.safe_dump({**(mapping or MAPPING), **changes}, sort_keys=False))
    return path


# --------------------------------------------------------------------------------------------------
# What the converted data must be


def expected_steps(spec: RobotBag) -> list[int]:
    """Camera frames taken as steps at 10 Hz: every third frame."""
    return list(range(0, round(spec.seconds * CAMERA_HZ), CAMERA_HZ // 10))


def check_episode(dataset: PlayDataset, index: int, spec: RobotBag, frames: list[int]) -> None:
    episode = dataset.episode(index, truth=True)
    images = episode.images["observation.images.front"]
    assert images.shape == (len(frames), HEIGHT, WIDTH, 3)
    for row, i in enumerate(frames):
        np.testing.assert_array_equal(images[row], frame(i), err_msg=f"frame of step {row}")
    # joints at 100 Hz: the sample at the frame's own time (frame i is at i/30 s = joint sample 10i/3)
    expected_state = np.stack([joint_position(round(i * JOINT_HZ / CAMERA_HZ)) for i in frames])
    np.testing.assert_array_equal(episode.state, expected_state)
    # commands at 10 Hz, 5 ms after the frame: the nearest one; the last observation has no action
    expected_actions = np.array(
        [twist_values(round(i * TWIST_HZ / CAMERA_HZ)) for i in frames[:-1]], np.float32
    )
    np.testing.assert_array_equal(episode.actions, expected_actions)


# --------------------------------------------------------------------------------------------------
# Tests


@pytest.mark.parametrize("layout", ["sqlite3-zstd", "mcap-split", "mcap-zstd-file"])
def test_mapping_converts_frames_states_actions_and_segments(tmp_path: Path, layout: str) -> None:
    spec = RobotBag()
    bag = tmp_path / "run_01"
    if layout == "sqlite3-zstd":
        write_rosbag2(bag, spec, "sqlite3", zstd=True)
    elif layout == "mcap-zstd-file":
        write_rosbag2(bag, spec, "mcap", zstd="file")
        assert len(list(bag.glob("*.mcap.zstd"))) == 1
    else:
        write_split_mcap(bag, spec, at=1.55)
        assert len(list(bag.glob("*.mcap"))) == 2
    summary = convert(
        [bag], tmp_path / "data", load_mapping(write_mapping(tmp_path / "map.yaml")), progress=False
    )
    assert summary.failed == []
    dataset = PlayDataset.open(tmp_path / "data")
    assert dataset.features.fps == 10
    assert dataset.features.state.names == JOINTS  # type: ignore[union-attr]
    assert dataset.features.action.names == ("linear.x", "linear.y", "angular.z")
    assert len(dataset) == 1 and dataset.records[0].split == "train"
    check_episode(dataset, 0, spec, expected_steps(spec))
    # labels [0.3, 1.2] and [1.2, 2.5] s on steps every 0.1 s: observations 3..12 and 12..25
    assert [(s.start, s.end, s.instruction) for s in dataset.segments(0)] == [
        (3, 12, "pick up the cup"),
        (12, 25, "put the cup down"),
    ]
    assert summary.totals() == {
        "episodes": 1,
        "steps": 29,
        "segments": 2,
        "model_segments": 0,
        "dropped_steps": 0,
    }


@pytest.mark.parametrize("camera", ["png", "bgr8", "mono8"])
def test_image_encodings_decode_to_the_written_rgb(tmp_path: Path, camera: str) -> None:
    spec = RobotBag(seconds=1.0, camera=camera, labels=[])
    bag = write_rosbag2(tmp_path / "bag", spec)
    summary = convert(
        [bag], tmp_path / "data", load_mapping(write_mapping(tmp_path / "m.yaml")), progress=False
    )
    assert summary.failed == []
    episode = PlayDataset.open(tmp_path / "data").episode(0)
    for row, i in enumerate(expected_steps(spec)):
        want = frame(i)
        if camera == "mono8":
            want = np.repeat(want[..., :1], 3, axis=2)
        np.testing.assert_array_equal(episode.images["observation.images.front"][row], want)


def test_ros1_bag_converts(tmp_path: Path) -> None:
    spec = RobotBag(seconds=1.0, labels=[])
    bag = write_ros1(tmp_path / "run.bag", spec)
    mapping = {k: v for k, v in MAPPING.items() if k != "annotations"}
    summary = convert(
        [bag], tmp_path / "data", load_mapping(write_mapping(tmp_path / "m.yaml", mapping)), progress=False
    )
    assert summary.failed == []
    dataset = PlayDataset.open(tmp_path / "data")
    assert dataset.records[0].split == "play"  # no annotations: unannotated play
    check_episode(dataset, 0, spec, expected_steps(spec))


def test_alignment_takes_samples_exactly_up_to_the_tolerance() -> None:
    tolerance = 20_000_000
    samples = np.array([0, 100_000_000, 200_000_000], dtype=np.int64)
    steps = np.array(
        [tolerance, tolerance + 1, 100_000_000 - tolerance, 100_000_000 - tolerance - 1, 150_000_000]
    )
    nearest = align(steps, samples, "nearest", tolerance)
    assert nearest.matched.tolist() == [True, False, True, False, False]
    assert nearest.lo[nearest.matched].tolist() == [0, 1]
    previous = align(steps, samples, "previous", tolerance)
    assert previous.matched.tolist() == [True, False, False, False, False]  # 80 ms after sample 0 is too old
    # a tie goes to the earlier sample
    tie = align(np.array([50]), np.array([0, 100]), "nearest", 50)
    assert tie.matched.tolist() == [True] and tie.lo.tolist() == [0]
    values = np.array([[0.0], [10.0], [20.0]], dtype=np.float32)
    linear = align(np.array([0, 20, 21, 100, 180, 181]), np.array([0, 40, 100, 200]), "linear", 60)
    # 20: between 0 and 40 (both within 60); 21 likewise; 100: exact; 180: 100 is 80 away: no match
    assert linear.matched.tolist() == [True, True, True, True, False, False]
    interpolated = linear.take(np.array([[0.0], [4.0], [10.0], [20.0]], dtype=np.float32))
    np.testing.assert_allclose(interpolated[:, 0], [0.0, 2.0, 2.1, 10.0], rtol=1e-6)
    assert align(np.array([0, 1]), np.zeros(0, np.int64), "nearest", 10).matched.tolist() == [False, False]
    assert values.shape == (3, 1)


def test_steps_without_a_joint_sample_are_dropped_and_reported(tmp_path: Path) -> None:
    spec = RobotBag(joint_gap=(1.05, 1.35), labels=[])
    bag = write_rosbag2(tmp_path / "gap", spec)
    summary = convert(
        [bag], tmp_path / "data", load_mapping(write_mapping(tmp_path / "m.yaml")), progress=False
    )
    (report,) = summary.reports
    # steps at 1.1, 1.2, 1.3 s have no joint sample within 20 ms (1.3 s: the nearest, 1.35 s, is 50 ms away)
    assert report.dropped_steps == 3
    assert any("observation.state (/joint_states): 3 step(s)" in note for note in report.notes)
    dataset = PlayDataset.open(tmp_path / "data")
    frames = [i for i in expected_steps(spec) if i not in (33, 36, 39)]
    check_episode(dataset, 0, spec, frames)


def test_derived_action_and_sidecar_annotations(tmp_path: Path) -> None:
    spec = RobotBag(labels=[])
    bag = write_rosbag2(tmp_path / "arm", spec)
    (bag / "labels.json").write_text(
        json.dumps({"annotations": [{"start": 0.5, "end": 1.0, "instruction": "wave"}]})
    )
    features = dict(MAPPING["features"], action={"derive": "delta", "of": "observation.state"})
    mapping = dict(MAPPING, features=features, annotations={"file": "labels.json"}, tolerance_ms=5)
    summary = convert(
        [bag], tmp_path / "data", load_mapping(write_mapping(tmp_path / "m.yaml", mapping)), progress=False
    )
    assert summary.failed == []
    dataset = PlayDataset.open(tmp_path / "data")
    episode = dataset.episode(0)
    np.testing.assert_array_equal(episode.actions, episode.state[1:] - episode.state[:-1])
    assert dataset.features.action.names == JOINTS
    # the sidecar's times are seconds from the bag's first message (t = 0 here): steps 5..10
    assert [(s.start, s.end, s.instruction) for s in dataset.segments(0)] == [(5, 10, "wave")]


@pytest.mark.slow
def test_bad_bags_fail_alone_and_a_rerun_skips_finished_bags(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    bags = tmp_path / "bags"
    spec = RobotBag(seconds=1.0)
    write_rosbag2(bags / "good_a", spec)
    write_rosbag2(bags / "good_b", spec, "sqlite3")
    truncated = write_rosbag2(bags / "truncated", spec)
    (mcap,) = truncated.glob("*.mcap")
    mcap.write_bytes(mcap.read_bytes()[: mcap.stat().st_size // 2])
    write_rosbag2(bags / "no_joints", RobotBag(seconds=1.0), stop=0.0)  # no messages of any topic
    bad_image = RobotBag(seconds=1.0, camera="jpeg", bad_image_at=6)
    write_rosbag2(bags / "bad_image", bad_image)
    mapping = write_mapping(tmp_path / "map.yaml")
    args = [
        "convert",
        str(bags),
        "--out",
        str(tmp_path / "data"),
        "--mapping",
        str(mapping),
        "--workers",
        "2",
        "--quiet",
    ]
    assert main(args) == 1
    err = capsys.readouterr().err
    failures = [line for line in err.splitlines() if "failed:" in line]
    assert len(failures) == 3, err
    assert any(
        "bag '" in line and "file 'truncated.mcap': the file is truncated" in line for line in failures
    )
    assert any("no_joints" in line and "topic missing" in line for line in failures)
    assert any(
        "bad_image" in line
        and "field 'data'" in line
        and "undecodable image" in line
        and "time 1700000000.200000" in line
        for line in failures
    )
    dataset = PlayDataset.open(tmp_path / "data")
    assert sorted(r.extra["bag"].rsplit("/", 1)[-1] for r in dataset.records) == ["good_a", "good_b"]
    # a rerun converts nothing it already holds: the two good bags are skipped, the bad ones fail again
    assert main(args) == 1
    out = capsys.readouterr().out
    assert "2 skipped" in out and "3 failed" in out and "0 converted" in out
    # once a bad bag is repaired (here: removed), the next run adds nothing and succeeds
    for name in ("truncated", "no_joints", "bad_image"):
        shutil.rmtree(bags / name)
    assert main(args) == 0
    assert len(PlayDataset.open(tmp_path / "data")) == 2


def test_a_new_bag_is_added_to_the_dataset_on_rerun(tmp_path: Path) -> None:
    spec = RobotBag(seconds=1.0)
    mapping = load_mapping(write_mapping(tmp_path / "m.yaml"))
    write_rosbag2(tmp_path / "bags" / "a", spec)
    convert([tmp_path / "bags"], tmp_path / "data", mapping, progress=False)
    write_rosbag2(tmp_path / "bags" / "b", spec)
    summary = convert([tmp_path / "bags"], tmp_path / "data", mapping, progress=False)
    assert [r.status for r in summary.reports] == ["skipped", "converted"]
    dataset = PlayDataset.open(tmp_path / "data")
    assert [r.episode_id for r in dataset.records] == ["a:0", "b:0"]
    check_episode(dataset, 1, spec, expected_steps(spec))
    other = load_mapping(write_mapping(tmp_path / "m2.yaml", tolerance_ms=30))
    with pytest.raises(ValueError, match="converted with another mapping"):
        convert([tmp_path / "bags"], tmp_path / "data", other, progress=False)


def test_inspect_proposes_a_mapping_that_converts(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    spec = RobotBag(seconds=2.0)
    bag = write_rosbag2(tmp_path / "robot", spec)
    assert main(["convert", "--inspect", str(bag)]) == 0
    text = capsys.readouterr().out
    assert "/joint_states" in text and "sensor_msgs/msg/JointState" in text and "100.00 Hz" in text
    (tmp_path / "proposed.yaml").write_text(text)
    proposed = yaml.safe_load(text)
    assert proposed["primary"] == "observation.images.camera" and proposed["fps"] == 30.0
    assert proposed["annotations"] == {"topic": "/annotations"}
    assert (
        main(
            [
                "convert",
                str(bag),
                "--out",
                str(tmp_path / "data"),
                "--mapping",
                str(tmp_path / "proposed.yaml"),
                "--quiet",
            ]
        )
        == 0
    )
    dataset = PlayDataset.open(tmp_path / "data")
    episode = dataset.episode(0, truth=True)
    # every frame a step at 30 fps, but the first: the proposal takes the command in effect ('previous'),
    # and the first command comes 5 ms after the first frame
    assert episode.num_steps + 1 == round(spec.seconds * CAMERA_HZ) - 1
    np.testing.assert_array_equal(episode.images["observation.images.camera"][7], frame(8))
    assert len(dataset.segments(0)) == 2


@pytest.mark.parametrize(
    ("text", "key", "detail"),
    [
        ("fps: 10\nprimary: observation.images.a\nfeatures:\n  observation.images.a: {topic: /a}\n"
         "  observation.state: {topic: /j, field: position}\n  observation.state: {topic: /k, field: position}\n",
         "features.observation.state", "given twice (lines 5 and 6)"),
        ("fps: 10\nprimary: observation.images.a\nfeatures:\n  observation.images.a: {topic: /a, feild: x}\n",
         "features.observation.images.a.feild", "unknown key"),
        ("fps: 10\nfeatures:\n  observation.images.a: {topic: /a}\n  action: {derive: next, of: observation.images.a}\n",
         "features.action.of", "cannot be derived from an image"),
        ("fps: 10\nfeatures:\n  observation.state: {topic: /j, field: position}\n  action: {derive: next, of: observation.state}\n",
         "primary", "missing"),
        ("fps: 0\nprimary: x\nfeatures: {}\n", "fps", "positive number"),
        ("fps: 10\nprimary: observation.state\nfeatures:\n  observation.state: {topic: /j, field: position, align: cubic}\n"
         "  action: {derive: next, of: observation.state}\n", "features.observation.state.align", "'cubic' is not one of"),
        ("fps: 10\nprimary: observation.state\ndomain: tabeltop\nfeatures:\n  observation.state: {topic: /j, field: position}\n"
         "  action: {derive: next, of: observation.state}\n", "domain", "unknown domain 'tabeltop'"),
    ],
)  # fmt: skip
def test_mapping_errors_name_the_file_and_key(tmp_path: Path, text: str, key: str, detail: str) -> None:
    path = tmp_path / "map.yaml"
    path.write_text(text)
    with pytest.raises(MappingError) as caught:
        load_mapping(path)
    message = str(caught.value)
    assert "\n" not in message and str(path) in message and f"key {key!r}" in message and detail in message


def test_cli_mapping_error_is_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bag = write_rosbag2(tmp_path / "bag", RobotBag(seconds=0.5))
    (tmp_path / "m.yaml").write_text("fps: 10\nfeatures: {}\n")
    assert (
        main(["convert", str(bag), "--out", str(tmp_path / "data"), "--mapping", str(tmp_path / "m.yaml")])
        == 1
    )
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [
        f"playseg convert: mapping {str(tmp_path / 'm.yaml')!r}, key 'features': no features named"
    ]
    assert not (tmp_path / "data").exists()


def test_episodes_split_at_markers_and_labels_are_cut_at_their_episode(tmp_path: Path) -> None:
    spec = RobotBag(markers=[1.45])
    bag = write_rosbag2(tmp_path / "marked", spec)
    mapping = dict(MAPPING, episodes={"split": "marker", "topic": "/episode_start"})
    summary = convert(
        [bag], tmp_path / "data", load_mapping(write_mapping(tmp_path / "m.yaml", mapping)), progress=False
    )
    (report,) = summary.reports
    dataset = PlayDataset.open(tmp_path / "data")
    assert [r.num_steps for r in dataset.records] == [14, 14]  # observations 0.0..1.4 s and 1.5..2.9 s
    check_episode(dataset, 0, spec, expected_steps(spec)[:15])
    check_episode(dataset, 1, spec, expected_steps(spec)[15:])
    # [0.3, 1.2]: steps 3..12 of episode 0; [1.2, 2.5] starts in episode 0, so it is cut at its last step
    assert [(s.start, s.end) for s in dataset.segments(0)] == [(3, 12), (12, 14)]
    assert dataset.segments(1) == [] and dataset.records[1].split == "play"
    assert any("'put the cup down'" in note and "cut at step 14" in note for note in report.notes)


def test_episodes_split_at_a_time_gap_drop_nothing(tmp_path: Path) -> None:
    spec = RobotBag(silence=(1.0, 2.0), labels=[])
    bag = write_rosbag2(tmp_path / "gappy", spec, "sqlite3")
    mapping = dict(MAPPING, episodes={"split": "gap", "gap_s": 0.5})
    summary = convert(
        [bag], tmp_path / "data", load_mapping(write_mapping(tmp_path / "m.yaml", mapping)), progress=False
    )
    assert summary.totals()["dropped_steps"] == 0
    dataset = PlayDataset.open(tmp_path / "data")
    frames = expected_steps(spec)
    check_episode(dataset, 0, spec, [i for i in frames if i < 30])
    check_episode(dataset, 1, spec, [i for i in frames if i >= 60])


def test_a_field_not_in_the_message_and_a_non_image_camera_fail_their_bag(tmp_path: Path) -> None:
    bag = write_rosbag2(tmp_path / "bag", RobotBag(seconds=0.5))
    features = dict(MAPPING["features"], action={"topic": "/cmd_vel", "fields": ["linear.x", "linear.w"]})
    mapping = load_mapping(write_mapping(tmp_path / "m.yaml", dict(MAPPING, features=features)))
    (report,) = convert([bag], tmp_path / "a", mapping, progress=False).reports
    assert report.status == "failed"
    assert (
        "topic '/cmd_vel', field 'linear.w', time 1700000000.005000: not in the message (there: x, y, z)"
        in str(report.error)
    )
    features = dict(MAPPING["features"], **{"observation.images.front": {"topic": "/joint_states"}})
    mapping = load_mapping(write_mapping(tmp_path / "m2.yaml", dict(MAPPING, features=features)))
    (report,) = convert([bag], tmp_path / "b", mapping, progress=False).reports
    assert "topic '/joint_states': type sensor_msgs/msg/JointState is not an image" in str(report.error)
    assert not (tmp_path / "a").exists() and not (tmp_path / "b").exists()


def test_play_bags_need_no_mapping_and_other_bags_do(tmp_path: Path) -> None:
    from playseg_core.data.episode import Episode, Segment
    from playseg_ros.play_bags import write_play_bag

    rng = np.random.default_rng(0)
    episode = Episode(
        "e0",
        rng.integers(0, 3, size=(6, 1)).astype(np.float32),
        {"observation.images.camera": rng.integers(0, 255, size=(7, 8, 8, 3), dtype=np.uint8)},
        segments=[Segment(0, 3, "left"), Segment(3, 6, "right")],
    )
    write_play_bag(tmp_path / "bags" / "play", [episode], annotated=True)
    write_rosbag2(tmp_path / "bags" / "robot", RobotBag(seconds=0.5))
    summary = convert([tmp_path / "bags"], tmp_path / "data", None, progress=False)
    assert [r.status for r in summary.reports] == ["converted", "failed"]
    assert "not a playseg play bag: give a mapping" in str(summary.reports[1].error)
    dataset = PlayDataset.open(tmp_path / "data")
    loaded = dataset.episode(0, truth=True)
    np.testing.assert_array_equal(
        loaded.images["observation.images.camera"], episode.images["observation.images.camera"]
    )
    np.testing.assert_array_equal(loaded.actions, episode.actions)
    assert loaded.segments == episode.segments and dataset.records[0].split == "train"


def test_joints_are_taken_by_name_and_a_bag_with_other_joints_fails_the_merge(tmp_path: Path) -> None:
    spec = RobotBag(seconds=1.0, labels=[])
    write_rosbag2(tmp_path / "bags" / "a", spec)
    write_rosbag2(tmp_path / "bags" / "b", RobotBag(seconds=1.0, labels=[], joints=("hip", "knee", "ankle")))
    state = {"topic": "/joint_states", "field": "position", "joints": ["wrist", "shoulder"]}
    features = dict(MAPPING["features"], **{"observation.state": state})
    mapping = load_mapping(write_mapping(tmp_path / "m.yaml", dict(MAPPING, features=features)))
    summary = convert([tmp_path / "bags"], tmp_path / "data", mapping, progress=False)
    assert [r.status for r in summary.reports] == ["converted", "failed"]
    assert "field 'position'" in str(summary.reports[1].error)
    assert "joint(s) ['wrist', 'shoulder'] not in this message" in str(summary.reports[1].error)
    dataset = PlayDataset.open(tmp_path / "data")
    assert dataset.features.state.names == ("wrist", "shoulder")  # type: ignore[union-attr]
    want = np.stack([joint_position(round(i * 10 / 3))[[2, 0]] for i in expected_steps(spec)])
    np.testing.assert_array_equal(dataset.episode(0).state, want)
    # without a selection both bags convert, but their state names differ: the second is not merged
    mapping = load_mapping(write_mapping(tmp_path / "all.yaml"))
    summary = convert([tmp_path / "bags"], tmp_path / "all", mapping, progress=False)
    assert [r.status for r in summary.reports] == ["converted", "failed"]
    assert "its features differ from the dataset's (observation.state" in str(summary.reports[1].error)
    assert "names differ" in str(summary.reports[1].error)
    assert len(PlayDataset.open(tmp_path / "all")) == 1


def test_a_type_without_definition_fails_its_bag(tmp_path: Path) -> None:
    """An older sqlite3 bag stores no message definitions; a type neither the bag nor ROS 2 defines is
    reported, not guessed."""
    store = get_typestore(Stores.ROS2_KILTED)
    store.register(get_types_from_msg("float64 width\n", "acme_msgs/msg/Gripper"))
    bag = tmp_path / "old"
    with Writer(bag, version=9, storage_plugin=StoragePlugin.SQLITE3) as writer:
        connection = writer.add_connection("/gripper", "acme_msgs/msg/Gripper", typestore=store)
        for i in range(5):
            msg = store.types["acme_msgs/msg/Gripper"](width=0.1 * i)
            writer.write(connection, T0 + i * 10**8, store.serialize_cdr(msg, "acme_msgs/msg/Gripper"))
    (database,) = bag.glob("*.db3")
    with sqlite3.connect(database) as connection_db:
        connection_db.execute("DELETE FROM message_definitions")
    features = {
        "observation.state": {"topic": "/gripper", "field": "width"},
        "action": {"derive": "next", "of": "observation.state"},
    }
    mapping = {"fps": 10, "primary": "observation.state", "features": features}
    (report,) = convert(
        [bag], tmp_path / "data", load_mapping(write_mapping(tmp_path / "m.yaml", mapping)), progress=False
    ).reports
    assert report.status == "failed"
    assert "topic '/gripper': unknown message type 'acme_msgs/msg/Gripper'" in str(report.error)


def test_an_out_that_holds_its_input_bags_is_refused_even_with_overwrite(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """`--out` a directory around the bags (a generated dataset with its bags inside): replacing it would
    delete them."""
    from playseg_core.data.episode import Episode, Segment
    from playseg_ros.play_bags import write_play_bag

    rng = np.random.default_rng(0)
    episode = Episode(
        "e0",
        rng.integers(0, 3, size=(6, 1)).astype(np.float32),
        {"observation.images.camera": rng.integers(0, 255, size=(7, 8, 8, 3), dtype=np.uint8)},
        segments=[Segment(0, 6, "left")],
    )
    bag = tmp_path / "data" / "bags" / "play"
    write_play_bag(bag, [episode], annotated=True)
    before = sorted(p.name for p in bag.iterdir())
    for out in (tmp_path / "data", bag):
        code = main(["convert", str(bag), "--out", str(out), "--overwrite", "--quiet"])
        err = capsys.readouterr().err.strip()
        assert code != 0 and "\n" not in err and f"overlaps the input {bag}" in err, err
    assert sorted(p.name for p in bag.iterdir()) == before


def test_a_truncated_play_bag_fails_saying_so_not_asking_for_a_mapping(tmp_path: Path) -> None:
    from playseg_ros.play_bags import write_play_bag

    rng = np.random.default_rng(1)
    episodes = [
        Episode(f"e{k}", rng.integers(0, 3, size=(40, 1)).astype(np.float32),
                {"observation.images.camera": rng.integers(0, 255, size=(41, 8, 8, 3), dtype=np.uint8)})
        for k in range(3)
    ]  # fmt: skip
    bag = tmp_path / "play"
    write_play_bag(bag, episodes, annotated=False)
    file = next(bag.glob("*.mcap"))
    file.write_bytes(file.read_bytes()[: file.stat().st_size // 2])
    summary = convert([bag], tmp_path / "data", None, progress=False)
    assert [r.status for r in summary.reports] == ["failed"]
    error = str(summary.reports[0].error)
    assert f"file '{file.name}'" in error and "truncated" in error and "mapping" not in error, error
