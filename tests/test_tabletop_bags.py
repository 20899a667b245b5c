"""Tabletop play as standard-message robot bags: read back by `rosbags` (an independent reader) with the
right types, rates and contents, and converted by `playseg convert` into the very episodes that were
played, their ground truth included."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from rosbags.highlevel import AnyReader

from playseg_core.data.dataset import PlayDataset
from playseg_core.domains.tabletop.play import PlayConfig
from playseg_core.domains.tabletop.robot_log import EPISODE_GAP_NS, LOG_START_NS, record_robot_log
from playseg_ros.cli import main as cli_main
from playseg_ros.tabletop.bags import (
    ANNOTATION_TOPIC,
    CAMERA_TOPIC,
    COMMAND_TOPIC,
    COMPRESSED_TOPIC,
    JOINT_TOPIC,
    TRUTH_FILE,
    typestore,
    write_sample_bags,
)

SETTINGS = {"tasks_per_episode": (2, 2), "image_size": 48}
CONFIG = PlayConfig(**SETTINGS)
EXPECTED_TYPES = {
    CAMERA_TOPIC: "sensor_msgs/msg/Image",
    COMPRESSED_TOPIC: "sensor_msgs/msg/CompressedImage",
    JOINT_TOPIC: "sensor_msgs/msg/JointState",
    COMMAND_TOPIC: "geometry_msgs/msg/Twist",
    ANNOTATION_TOPIC: "playseg_msgs/msg/TimedAnnotation",
}


@pytest.fixture(scope="module")
def bags(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("tabletop") / "bags"
    written = write_sample_bags(out, episodes=2, annotated=1, images="both", seed=0, **SETTINGS)
    assert [bag.annotated for bag in written] == [True, False]
    return out


def read_topics(bag: Path) -> dict[str, list[tuple[int, object]]]:
    messages: dict[str, list[tuple[int, object]]] = {}
    with AnyReader([bag], default_typestore=typestore()) as reader:
        for connection in reader.connections:
            assert connection.msgtype == EXPECTED_TYPES[connection.topic], connection.topic
        for connection, timestamp, data in reader.messages():
            messages.setdefault(connection.topic, []).append(
                (timestamp, reader.deserialize(data, connection.msgtype))
            )
    return messages


def test_the_episodes_follow_one_another_in_time(bags: Path) -> None:
    spans = []
    for index in range(2):
        with AnyReader([bags / f"tabletop-{index}"], default_typestore=typestore()) as reader:
            spans.append((reader.start_time, reader.end_time))
    (_, first_end), (second_start, _) = spans
    last = first_end - 1  # rosbags' end_time is one past the last message
    assert spans[0][0] == LOG_START_NS and second_start - last == EPISODE_GAP_NS


@pytest.mark.parametrize("index", [0, 1])
def test_rosbags_reads_back_types_rates_and_contents(bags: Path, index: int) -> None:
    topics = read_topics(bags / f"tabletop-{index}")
    log = record_robot_log(CONFIG, index, start_ns=topics[CAMERA_TOPIC][0][0])
    assert (ANNOTATION_TOPIC in topics) == (index == 0)  # only the first bag is annotated
    steps = len(log.commands)

    def period_ms(topic: str) -> float:
        return float(np.median(np.diff([t for t, _ in topics[topic]]))) / 1e6

    assert period_ms(CAMERA_TOPIC) == period_ms(COMPRESSED_TOPIC) == period_ms(COMMAND_TOPIC) == 100.0
    assert period_ms(JOINT_TOPIC) == 20.0  # 50 Hz
    assert [len(topics[t]) for t in (CAMERA_TOPIC, JOINT_TOPIC, COMMAND_TOPIC)] == [
        steps + 1,
        5 * steps + 1,
        steps,
    ]

    stamp, image = topics[CAMERA_TOPIC][7]
    assert image.encoding == "rgb8" and (image.height, image.width) == (48, 48)
    assert image.header.stamp.sec * 10**9 + image.header.stamp.nanosec == stamp == log.frame_ns[7]
    np.testing.assert_array_equal(image.data.reshape(48, 48, 3), log.frames[7])
    _, compressed = topics[COMPRESSED_TOPIC][7]
    decoded = cv2.cvtColor(cv2.imdecode(compressed.data, cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
    assert compressed.format == "jpeg" and np.abs(decoded.astype(int) - log.frames[7]).mean() < 8
    _, joints = topics[JOINT_TOPIC][35]
    assert list(joints.name) == list(log.joint_names)
    np.testing.assert_allclose(joints.position, log.joint_positions[35])
    np.testing.assert_allclose(joints.velocity, log.joint_velocities[35])
    _, twist = topics[COMMAND_TOPIC][5]
    assert (twist.linear.x, twist.linear.y) == tuple(log.commands[5])

    truth = json.loads((bags / log.episode_id / TRUTH_FILE).read_text())["annotations"]
    start = log.frame_ns[0]
    assert [
        (round(a["start"] * 1e9) + start, round(a["end"] * 1e9) + start, a["instruction"]) for a in truth
    ] == [(int(s), int(e), text) for s, e, text in log.segment_times]
    if index == 0:
        labels = [
            (m.start.sec * 10**9 + m.start.nanosec, m.end.sec * 10**9 + m.end.nanosec, m.instruction)
            for _, m in topics[ANNOTATION_TOPIC]
        ]
        assert labels == [(int(s), int(e), text) for s, e, text in log.segment_times]


def test_playseg_convert_recovers_the_played_episodes(bags: Path, tmp_path: Path) -> None:
    for mapping, labelled in (("mapping.yaml", [True, False]), ("mapping_truth.yaml", [True, True])):
        out = tmp_path / mapping
        assert (
            cli_main(["convert", str(bags), "--out", str(out), "--mapping", str(bags / mapping), "--quiet"])
            == 0
        )
        data = PlayDataset.open(out)
        for index in range(2):
            log = record_robot_log(CONFIG, index)
            episode = data.episode(index, truth=True)
            assert episode.episode_id.startswith(log.episode_id)
            assert episode.num_steps == len(log.commands)
            np.testing.assert_array_equal(episode.images["observation.images.top"], log.frames)
            np.testing.assert_array_equal(episode.actions, log.commands.astype(np.float32))
            np.testing.assert_allclose(episode.state[:, :2], log.joint_positions[::5], atol=1e-6)
            assert episode.segments == (log.segments if labelled[index] else [])


def test_bad_requests_are_one_line_errors(bags: Path, tmp_path: Path) -> None:
    with pytest.raises(FileExistsError, match="exists; replace it only with overwrite"):
        write_sample_bags(bags, episodes=1, **SETTINGS)
    with pytest.raises(ValueError, match="images must be one of raw, jpeg, both"):
        write_sample_bags(tmp_path / "x", episodes=1, images="png", **SETTINGS)
    with pytest.raises(ValueError, match="state rate 30"):
        record_robot_log(CONFIG, 0, state_hz=30.0)
    assert not (tmp_path / "x").exists()
