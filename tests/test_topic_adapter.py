"""The mapping live: bag_player plays a rosbags-written bag of standard messages (30 Hz rgb8 Image, 100 Hz
JointState with a gap, 10 Hz TwistStamped) into topic_adapter + segmenter, real processes on real DDS. The adapter's
PlaySteps are the episode `playseg convert` makes of the same bag, and the segmenter's segments are the
ones `playseg convert --segment` stores. A bag whose commands are header-less Twists, replayed at recorded
speed with its /clock into an adapter on sim time, gives the same steps as `playseg convert`."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from lifecycle_msgs.msg import State
from node_procs import Processes, RosPeer, stop, wait_for_log
from playseg_msgs.msg import LabelledSegment, PlayStep
from rclpy.qos import QoSProfile
from rosgraph_msgs.msg import Clock
from test_convert import MAPPING, RobotBag, write_mapping, write_rosbag2
from test_convert_live import messages_of
from test_convert_segment import untrained_model
from test_robot_nodes import LifecycleProbe

from playseg_core.data.dataset import PlayDataset
from playseg_core.ps.model import load_model
from playseg_core.ps.segmentation import segment_episode
from playseg_ros import qos
from playseg_ros.cli import main
from playseg_ros.ros_types import message_class

CAMERA = "observation.images.front"
TOPICS = ["/camera/image_raw", "/joint_states", "/cmd_vel"]


def test_live_steps_and_segments_equal_playseg_convert_segment(
    procs: Processes, peer: RosPeer, tmp_path: Path
) -> None:
    bag = write_rosbag2(
        tmp_path / "robot", RobotBag(seconds=4.0, labels=[], stamped_commands=True, joint_gap=(1.05, 1.35))
    )
    action = {"topic": "/cmd_vel", "fields": ["twist.linear.x", "twist.linear.y", "twist.angular.z"]}
    mapping = write_mapping(
        tmp_path / "map.yaml", dict(MAPPING, features={**MAPPING["features"], "action": action})
    )
    quiet = ["--mapping", str(mapping), "--quiet"]
    assert main(["convert", str(bag), "--out", str(tmp_path / "plain"), *quiet]) == 0
    plain = PlayDataset.open(tmp_path / "plain")
    episode = plain.episode(0)
    probe, _ = load_model(untrained_model(tmp_path / "probe.pt", plain.features, episode))
    threshold = float(np.median([s.confidence for s in segment_episode(probe, episode, probe.cfg.min_len)]))
    model_path = untrained_model(tmp_path / "ps.pt", plain.features, episode, threshold)
    assert (
        main(["convert", str(bag), "--out", str(tmp_path / "data"), *quiet, "--segment", str(model_path)])
        == 0
    )
    converted = PlayDataset.open(tmp_path / "data")
    assert converted.info["meta"]["convert"]  # 3 steps (1.1 - 1.3 s) have no joint sample within 20 ms
    assert episode.num_steps + 1 == 40 - 3
    expected = converted.segments(0, truth=True)
    assert expected and converted.records[0].episode_id == "robot:0"

    steps: list[PlayStep] = []
    segments: list[LabelledSegment] = []
    peer.node.create_subscription(PlayStep, "/play/steps", steps.append, qos.PLAY_STEPS)
    peer.node.create_subscription(LabelledSegment, "/segments", segments.append, qos.SEGMENTS)
    segmenter, segmenter_log = procs.node(
        "segmenter", "segmenter", model=str(model_path), keep="label"
    )  # the checkpoint's label threshold, as convert --segment keeps by default
    adapter, adapter_log = procs.node(
        "topic_adapter",
        "adapter",
        mapping=str(mapping),
        episode_id="robot",
        idle_timeout_s=8.0,
        wait_for_subscribers=2,
    )
    # PlaySteps are volatile: play once the segmenter and this test listen to the adapter.
    listening = lambda: peer.node.count_subscribers("/play/steps") >= 2  # noqa: E731
    assert peer.spin_until(listening, 60), segmenter_log.read_text()[-2000:]
    wait_for_log(adapter_log, r"topic_adapter\]: mapping", 30, adapter)
    player, player_log = procs.node(
        "bag_player",
        "player",
        bag=str(bag),
        rate=0.0,
        topics=TOPICS,
        wait_for_subscribers=1,
        wait_topics=TOPICS,
    )
    ended = lambda: any(s.episode_end for s in steps)  # noqa: E731
    assert peer.spin_until(ended, 60), adapter_log.read_text()[-3000:] + player_log.read_text()[-2000:]
    assert peer.spin_until(lambda: len(segments) >= len(expected), 30), (
        [(s.start_step, s.end_step, s.instruction) for s in segments],
        expected,
        [(m.episode_id, m.step) for m in steps],
        adapter_log.read_text()[-3000:],
    )
    peer.spin_until(lambda: False, 1.0)  # nothing more comes

    # Same steps: the converted episode, step by step (frames, joint state, commands, times).
    assert [s.step for s in steps] == list(range(episode.num_steps + 1))
    assert {s.episode_id for s in steps} == {"robot:0"}
    for t, msg in enumerate(steps):
        assert list(msg.camera_names) == [CAMERA]
        frame = np.frombuffer(bytes(msg.observation.data), np.uint8).reshape(episode.images[CAMERA].shape[1:])
        np.testing.assert_array_equal(frame, episode.images[CAMERA][t])
        np.testing.assert_array_equal(np.asarray(msg.state, np.float32), episode.state[t])
        if t < episode.num_steps:
            np.testing.assert_array_equal(np.asarray(msg.action, np.float32), episode.actions[t])
    # Same segments: what convert --segment stored (the model's, filtered by its label threshold).
    assert [(s.episode_id, s.start_step, s.end_step, s.instruction) for s in segments] == [
        ("robot:0", s.start, s.end, s.instruction) for s in expected
    ]
    np.testing.assert_allclose(
        [s.label_confidence for s in segments], [s.confidence for s in expected], atol=1e-4
    )
    # The steps without a joint sample were dropped and reported live too, once the stream ended.
    assert (
        "observation.state (/joint_states): 3 step(s) without a sample within 20 ms"
        in adapter_log.read_text()
    )
    assert stop(adapter) == 0 and stop(segmenter) == 0
    for log in (adapter_log, segmenter_log):
        assert "Traceback" not in log.read_text()


def test_every_transition_in_every_state(procs: Processes, peer: RosPeer, tmp_path: Path) -> None:
    mapping = write_mapping(tmp_path / "map.yaml")
    for shutdown_from in (State.PRIMARY_STATE_UNCONFIGURED, State.PRIMARY_STATE_ACTIVE):
        node, log = procs.node(
            "topic_adapter", f"adapter-{shutdown_from}", autostart=False, mapping=str(mapping)
        )
        LifecycleProbe(peer, "topic_adapter", {}).walk(shutdown_from)
        assert node.poll() is None, log.read_text()[-3000:]
        assert stop(node) == 0, log.read_text()[-3000:]
        text = log.read_text()
        assert "Traceback" not in text and "failed" not in text, text[-3000:]


@pytest.mark.parametrize(
    ("params", "message"),
    [
        ({}, "mapping must be set"),
        ({"mapping": "/nonexistent/map.yaml"}, "mapping '/nonexistent/map.yaml': cannot read"),
        ({"topic_types": ["/nope=std_msgs/msg/Empty"]}, "topic_types names topics the mapping does not read"),
    ],
)
def test_bad_parameters_fail_configure_in_one_line(
    procs: Processes, tmp_path: Path, params: dict, message: str
) -> None:
    if "topic_types" in params:
        params = {**params, "mapping": str(write_mapping(tmp_path / "map.yaml"))}
    node, log = procs.node("topic_adapter", "adapter", **params)
    # 2: a parameter's value is wrong (docs/nodes.md); 1: configure failed on what it names (a missing file)
    assert node.wait(timeout=60) == (1 if "cannot read" in message else 2)
    text = log.read_text()
    assert message in text and "Traceback" not in text, text


def test_headerless_twist_replayed_with_clock_gives_the_steps_of_playseg_convert(
    procs: Processes, peer: RosPeer, tmp_path: Path
) -> None:
    """bag_player clock:=true at recorded speed, topic_adapter use_sim_time: a geometry_msgs/Twist (no
    header) takes the /clock of its publication, its recorded time, as convert takes its log time."""
    bag = write_rosbag2(tmp_path / "robot", RobotBag(seconds=4.0, labels=[], stamped_commands=False))
    mapping = write_mapping(tmp_path / "map.yaml")
    assert (
        main(["convert", str(bag), "--out", str(tmp_path / "data"), "--mapping", str(mapping), "--quiet"])
        == 0
    )
    converted = PlayDataset.open(tmp_path / "data")
    episode = converted.episode(0)
    assert converted.records[0].episode_id == "robot:0" and episode.num_steps + 1 == 40

    steps: list[PlayStep] = []
    peer.node.create_subscription(PlayStep, "/play/steps", steps.append, qos.PLAY_STEPS)
    adapter, adapter_log = procs.node(
        "topic_adapter", "adapter", mapping=str(mapping), episode_id="robot", use_sim_time=True,
        idle_timeout_s=3.0, wait_for_subscribers=1,
    )  # fmt: skip
    # volatile: play once the adapter publishes to this test (its timer discovers the player on sim time 0)
    assert peer.spin_until(lambda: peer.node.count_publishers("/play/steps") >= 1, 60)
    wait_for_log(adapter_log, r"topic_adapter\]: mapping", 30, adapter)
    peer.spin_until(lambda: False, 1.0)
    player, player_log = procs.node(
        "bag_player", "player", bag=str(bag), rate=1.0, clock=True, topics=TOPICS, wait_for_subscribers=1,
        wait_topics=TOPICS,
    )  # fmt: skip
    ended = lambda: any(s.episode_end for s in steps)  # noqa: E731
    assert peer.spin_until(ended, 60), adapter_log.read_text()[-3000:] + player_log.read_text()[-2000:]
    peer.spin_until(lambda: False, 1.0)  # nothing more comes
    assert player.wait(timeout=30) == 0

    assert [(s.episode_id, s.step) for s in steps] == [("robot:0", t) for t in range(episode.num_steps + 1)]
    for t, msg in enumerate(steps):
        frame = np.frombuffer(bytes(msg.observation.data), np.uint8).reshape(episode.images[CAMERA].shape[1:])
        np.testing.assert_array_equal(frame, episode.images[CAMERA][t])
        np.testing.assert_array_equal(np.asarray(msg.state, np.float32), episode.state[t])
        if t < episode.num_steps:
            np.testing.assert_array_equal(np.asarray(msg.action, np.float32), episode.actions[t])
    text = adapter_log.read_text()
    assert "dropped" not in text and "Traceback" not in text, text[-3000:]
    assert stop(adapter) == 0


def test_bag_player_clock_publishes_each_messages_recorded_time_before_it(
    procs: Processes, peer: RosPeer, tmp_path: Path
) -> None:
    bag = write_rosbag2(tmp_path / "robot", RobotBag(seconds=0.5, labels=[]))
    recorded = sorted(t for _, _, _, t in messages_of(bag))
    clocks: list[int] = []
    commands: list[object] = []
    peer.node.create_subscription(
        Clock,
        "/clock",
        lambda m: clocks.append(m.clock.sec * 10**9 + m.clock.nanosec),
        QoSProfile(depth=1000),
    )
    twist = message_class("geometry_msgs/msg/Twist")
    peer.node.create_subscription(twist, "/cmd_vel", commands.append, QoSProfile(depth=1000))
    player, log = procs.node(
        "bag_player", "player", bag=str(bag), rate=1.0, clock=True, wait_for_subscribers=1,
        wait_topics=["/cmd_vel"],
    )  # fmt: skip
    done = lambda: player.poll() is not None and len(clocks) >= len(recorded)  # noqa: E731
    assert peer.spin_until(done, 60), log.read_text()
    assert player.returncode == 0
    assert clocks == recorded  # the recorded time of each message, in order (published before it)
    assert len(commands) == 5


def test_one_camera_stamp_a_year_ahead_costs_one_frame_not_the_stream(
    procs: Processes, peer: RosPeer, tmp_path: Path
) -> None:
    """The issue's case on DDS: frame 31 of 120 carries a header stamp a year ahead. Before, the adapter
    published nothing while the input went on (its step clock and horizon jumped a year) and logged
    "315360000 steps missing". Now the frame is dropped with one warning and the steps are those of
    `playseg convert`, published while the stream is still open (idle_timeout_s 60 has not passed)."""
    from test_stamp_outliers import YEAR_NS, OutlierBag

    from playseg_ros.convert.build import convert_bag
    from playseg_ros.convert.mapping import load_mapping

    spec = OutlierBag(seconds=4.0, labels=[], stamped_commands=True, outliers={31: YEAR_NS / 1e9})
    bag = write_rosbag2(tmp_path / "robot", spec)
    action = {"topic": "/cmd_vel", "fields": ["twist.linear.x", "twist.linear.y", "twist.angular.z"]}
    mapping = write_mapping(
        tmp_path / "map.yaml", dict(MAPPING, features={**MAPPING["features"], "action": action})
    )
    (episode,) = convert_bag(bag, load_mapping(mapping)).episodes
    assert episode.num_steps + 1 >= 37

    steps: list[PlayStep] = []
    peer.node.create_subscription(PlayStep, "/play/steps", steps.append, qos.PLAY_STEPS)
    adapter, adapter_log = procs.node(
        "topic_adapter", "adapter", mapping=str(mapping), episode_id="robot", idle_timeout_s=60.0,
        wait_for_subscribers=1,
    )  # fmt: skip
    assert peer.spin_until(lambda: peer.node.count_subscribers("/play/steps") >= 1, 60)
    wait_for_log(adapter_log, r"topic_adapter\]: mapping", 30, adapter)
    player, player_log = procs.node(
        "bag_player", "player", bag=str(bag), rate=0.0, topics=TOPICS, wait_for_subscribers=1,
        wait_topics=TOPICS,
    )  # fmt: skip
    # all but the last step or two (they wait for later samples or the stream's end) while it is open
    published = lambda: len(steps) >= episode.num_steps - 1  # noqa: E731
    assert peer.spin_until(published, 60), adapter_log.read_text()[-3000:] + player_log.read_text()[-2000:]
    assert not any(s.episode_end for s in steps)
    for t, msg in enumerate(steps):
        frame = np.frombuffer(bytes(msg.observation.data), np.uint8).reshape(episode.images[CAMERA].shape[1:])
        np.testing.assert_array_equal(frame, episode.images[CAMERA][t])
    text = adapter_log.read_text()
    assert text.count("dropped as a stamp outlier") == 1 and "topic /camera/image_raw: sample stamped" in text
    assert "missing" not in text, text[-3000:]
    assert stop(adapter) == 0
    assert "Traceback" not in adapter_log.read_text()
