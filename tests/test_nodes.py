"""The nodes as real processes on real DDS: crashes, clean shutdowns, malformed input, playback, `playseg up`."""

from __future__ import annotations

import math
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import yaml
from lifecycle_msgs.msg import Transition
from lifecycle_msgs.srv import ChangeState
from mcap.reader import make_reader
from node_procs import Processes, RosPeer, descendants, node_env, stop, wait_for_log
from playseg_msgs.msg import LabelledSegment, PlayStep, TrainerStatus
from playseg_msgs.srv import EvaluatePolicy, Retrain, SaveBuffer
from rclpy.duration import Duration
from rclpy.serialization import serialize_message
from rosbags.highlevel import AnyReader
from sensor_msgs.msg import Image
from std_msgs.msg import String

from playseg_core.augment.buffer import AugmentationBuffer
from playseg_core.data.episode import Episode
from playseg_core.domains.babyai.play import PlayConfig, generate_episode
from playseg_core.domains.babyai.spec import CAMERA
from playseg_ros import qos
from playseg_ros.bag import BagReader, BagWriter, topic_info
from playseg_ros.bag.lock import LOCK_FILE
from playseg_ros.messages import RCLPY, episode_step_message, labelled_segment_of_steps
from playseg_ros.play_bags import read_play_bag, write_play_bag
from playseg_ros.typestore import playseg_typestore

FLUSHED = re.compile(r"flushed: (\d+) messages on disk")


def _episodes(count: int) -> list[Episode]:
    return [generate_episode(PlayConfig(), seed) for seed in range(count)]


# -- recorder ------------------------------------------------------------------------------------------


def test_recorder_sigkill_then_recover_restores_every_flushed_message(
    procs: Processes, tmp_path: Path
) -> None:
    out = tmp_path / "crash"
    recorder, rec_log = procs.node(
        "recorder", "recorder", "--log-level", "recorder:=debug", output=out, topics=["/play/steps"],
        flush_period_s=0.05,
    )  # fmt: skip
    wait_for_log(rec_log, r"recording", 30, recorder)
    procs.node("play_source", "play_source", rate_hz=1000.0, wait_for_subscribers=1, ground_truth_topic="''")
    wait_for_log(rec_log, r"flushed: ([2-9]\d\d|\d{4,}) messages", 60, recorder)  # >= 200 on disk
    recorder.send_signal(signal.SIGKILL)
    recorder.wait(timeout=10)
    flushed = int(FLUSHED.findall(rec_log.read_text())[-1])
    assert (tmp_path / "crash.partial").is_dir() and not out.exists()

    result = subprocess.run(
        [sys.executable, "-m", "playseg_ros.cli", "bag", "recover", str(out)],
        env=node_env(), capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    assert (out / "metadata.yaml").is_file() and not (tmp_path / "crash.partial").exists()

    store = playseg_typestore()
    with AnyReader([out], default_typestore=store) as reader:
        steps = [reader.deserialize(data, conn.msgtype) for conn, _, data in reader.messages()]
    assert len(steps) >= flushed > 0
    # What was recovered is the start of the play, step by step (nothing skipped inside the prefix).
    expected = [(e.episode_id, t) for e in _episodes(len(steps) // 30 + 2) for t in range(e.num_steps + 1)]
    assert [(s.episode_id, s.step) for s in steps] == expected[: len(steps)]


def test_recorder_sigint_finishes_bag_with_every_published_step(procs: Processes, tmp_path: Path) -> None:
    out = tmp_path / "play"
    episodes = _episodes(3)
    expected_steps = sum(e.num_steps + 1 for e in episodes)
    expected_total = expected_steps + sum(len(e.segments) for e in episodes)
    recorder, rec_log = procs.node(
        "recorder", "recorder", "--log-level", "recorder:=debug", output=out,
        topics=["play/steps", "/play/annotations"], flush_period_s=0.1,  # relative: resolved as the graph's
    )  # fmt: skip
    source, src_log = procs.node(
        "play_source", "play_source", rate_hz=500.0, num_episodes=3, annotate_share=1.0,
        wait_for_subscribers=1, ground_truth_topic="''",
    )  # fmt: skip
    wait_for_log(src_log, r"published 3 episodes", 60, source)
    wait_for_log(rec_log, rf"flushed: {expected_total} messages", 15, recorder)
    assert stop(recorder) == 0
    assert (out / "metadata.yaml").is_file() and not (tmp_path / "play.partial").exists()

    recorded = read_play_bag(out)  # a recording declares no features: its PlaySteps name the camera
    assert [e.episode_id for e in recorded] == [e.episode_id for e in episodes]
    for got, want in zip(recorded, episodes, strict=True):
        assert got.num_steps == want.num_steps
        np.testing.assert_array_equal(got.images[CAMERA], want.images[CAMERA])
        np.testing.assert_array_equal(got.state, want.state.astype(np.float32))
        np.testing.assert_array_equal(got.actions, want.actions)
        assert [(s.start, s.end, s.instruction) for s in got.segments] == [
            (s.start, s.end, s.instruction) for s in want.segments
        ]


def test_recorder_sigint_right_after_the_acks_keeps_every_acknowledged_message(
    procs: Processes, peer: RosPeer, tmp_path: Path
) -> None:
    """Messages DDS acknowledged but the recorder had not taken yet are written at stop, not dropped."""
    out, count = tmp_path / "camera", 120
    frame = bytearray(serialize_message(_camera_image()))
    pub = peer.node.create_publisher(Image, "/camera", qos.PLAY_STEPS)
    recorder, rec_log = procs.node("recorder", "recorder", output=out, topics=["/camera"], compression="zstd")
    assert peer.spin_until(lambda: pub.get_subscription_count() > 0, 60), rec_log.read_text()
    time.sleep(0.3)
    for i in range(count):
        frame[4:8] = i.to_bytes(4, "little")  # header.stamp.sec = index
        pub.publish(bytes(frame))
    assert pub.wait_for_all_acked(Duration(seconds=60))
    assert stop(recorder) == 0
    with BagReader(out) as reader:
        indices = [int.from_bytes(m.data[4:8], "little") for m in reader.messages()]
    assert indices == list(range(count))


def _camera_image() -> Image:
    image = Image(height=480, width=640, encoding="rgb8", step=640 * 3)
    image.data = np.random.default_rng(0).integers(0, 256, 480 * 640 * 3, dtype=np.uint8).tobytes()
    return image


# -- trainer -------------------------------------------------------------------------------------------


class TrainerClient:
    """Publishes LabelledSegments to the trainer and tracks its acknowledged count."""

    def __init__(self, peer: RosPeer) -> None:
        self.peer = peer
        self.statuses: list[TrainerStatus] = []
        self.pub = peer.node.create_publisher(LabelledSegment, "/segments", qos.SEGMENTS)
        peer.node.create_subscription(TrainerStatus, "/trainer/status", self.statuses.append, qos.STATUS)

    @property
    def acknowledged(self) -> int:
        return max((s.buffer_segments for s in self.statuses), default=-1)

    def wait_connected(self, timeout: float = 60.0) -> None:
        assert self.peer.spin_until(lambda: self.pub.get_subscription_count() > 0, timeout), "no trainer"

    def wait_acknowledged(self, count: int, timeout: float = 30.0) -> None:
        ok = self.peer.spin_until(lambda: self.acknowledged >= count, timeout)
        assert ok, f"trainer acknowledged {self.acknowledged}, expected {count}"


def _segment_msgs(episode: Episode) -> list[LabelledSegment]:
    return [
        labelled_segment_of_steps(
            episode.episode_id,
            seg,
            [episode_step_message(episode, t, kind=RCLPY) for t in range(seg.start, seg.end + 1)],
            "test",
            0,
            kind=RCLPY,
        )
        for seg in episode.segments
    ]


def _trainer(procs: Processes, tmp_path: Path, log_name: str, **params: object):
    params = {
        "buffer_dir": tmp_path / "buffer", "checkpoint_dir": tmp_path / "checkpoints", "retrain_every": 0,
        "status_period_s": 0.2, **params,
    }  # fmt: skip
    return procs.node("trainer", log_name, **params)


def test_trainer_sigkill_and_restart_keeps_every_acknowledged_segment(
    procs: Processes, peer: RosPeer, tmp_path: Path
) -> None:
    episode = generate_episode(PlayConfig(), 0)
    msgs = _segment_msgs(episode)
    client = TrainerClient(peer)
    trainer, _ = _trainer(procs, tmp_path, "trainer1")
    client.wait_connected()
    for msg in msgs:
        client.pub.publish(msg)
    client.wait_acknowledged(3)  # kill it while it may still be storing the rest
    trainer.send_signal(signal.SIGKILL)
    trainer.wait(timeout=10)
    peer.spin_until(lambda: False, 0.3)  # statuses already in flight
    acknowledged = client.acknowledged
    assert acknowledged >= 3

    client.statuses.clear()
    restarted, log = _trainer(procs, tmp_path, "trainer2")
    wait_for_log(log, r"buffer .*: (\d+) segments", 60, restarted)
    assert client.peer.spin_until(lambda: bool(client.statuses), 30)
    restored = client.statuses[-1].buffer_segments
    assert acknowledged <= restored <= len(msgs)
    assert stop(restarted) == 0
    with AugmentationBuffer(tmp_path / "buffer") as buffer:
        assert len(buffer) == restored
        for stored, seg in zip(buffer, episode.segments, strict=False):
            assert (stored.episode_id, stored.segment.start, stored.segment.end) == (
                episode.episode_id,
                seg.start,
                seg.end,
            )
            assert stored.segment.instruction == seg.instruction and stored.source == "test"
            np.testing.assert_array_equal(stored.actions, episode.actions[seg.start : seg.end])
            # without base data declaring the camera, the trainer stores the image under the name its
            # PlaySteps give it
            frames = episode.images[CAMERA][seg.start : seg.end + 1]
            np.testing.assert_array_equal(stored.images[CAMERA], frames)
            np.testing.assert_array_equal(stored.state, episode.state[seg.start : seg.end + 1])


def test_trainer_logs_malformed_segments_and_keeps_running(
    procs: Processes, peer: RosPeer, tmp_path: Path
) -> None:
    episode = generate_episode(PlayConfig(), 1)
    good = _segment_msgs(episode)[0]
    wrong_encoding, wrong_size, nan_action = _segment_msgs(episode)[1:4]
    wrong_encoding.steps[0].observation.encoding = "bgr8"
    small = np.zeros((32, 32, 3), np.uint8)
    image = wrong_size.steps[1].observation
    image.height, image.width, image.step, image.data = 32, 32, 96, small.tobytes()
    nan_action.steps[0].action = [math.nan]

    client = TrainerClient(peer)
    trainer, log = _trainer(procs, tmp_path, "trainer")
    client.wait_connected()
    for msg in (wrong_encoding, wrong_size, nan_action, good):
        client.pub.publish(msg)
    client.wait_acknowledged(1)
    text = wait_for_log(log, r"(?s)dropped.*dropped.*dropped.*", 10).group(0)
    assert "encoding is 'bgr8'" in text
    assert "observation is 32x32, expected 64x64" in text
    assert "NaN" in text
    peer.spin_until(lambda: False, 0.5)
    assert client.acknowledged == 1 and trainer.poll() is None
    assert stop(trainer) == 0


def test_trainer_keeps_a_reference_segment_pending_until_its_recording_holds_the_steps(
    procs: Processes, peer: RosPeer, tmp_path: Path
) -> None:
    """A reference-form segment naming a bag that is not there yet: one warning naming the bag, nothing
    stored, the node keeps running; once the bag holds the steps the segment is stored with them."""
    from playseg_ros.messages import PLAY_STEP, episode_messages, labelled_segment_reference

    episode = generate_episode(PlayConfig(), 4)
    segment = episode.segments[1]
    stamps = [1_000_000_000 * (50 + t) for t in range(episode.num_steps + 1)]
    bag = tmp_path / "recording"
    msg = labelled_segment_reference(
        episode.episode_id, segment, "ps", 0, (str(bag), "/play/steps"),
        (stamps[segment.start], stamps[segment.end]), kind=RCLPY,
    )  # fmt: skip
    client = TrainerClient(peer)
    trainer, log = _trainer(procs, tmp_path, "trainer", resolve_period_s=0.2)
    client.wait_connected()
    client.pub.publish(msg)
    line = wait_for_log(log, r"WARN.*kept pending.*", 30, trainer).group(0)
    assert f"episode {episode.episode_id!r} steps {segment.start}..{segment.end} on /play/steps" in line
    assert f"no bag at {bag}" in line
    peer.spin_until(lambda: False, 1.0)
    assert client.acknowledged == 0 and trainer.poll() is None
    with BagWriter(bag) as writer:
        writer.add_topic(topic_info("/play/steps", PLAY_STEP))
        for step, stamp in zip(episode_messages(episode, stamps), stamps, strict=True):
            writer.write("/play/steps", bytes(playseg_typestore().serialize_cdr(step, PLAY_STEP)), stamp)
    client.wait_acknowledged(1)
    assert stop(trainer) == 0
    assert "read from the recording, stored" in log.read_text()
    with AugmentationBuffer(tmp_path / "buffer") as buffer:
        (stored,) = list(buffer)
    assert (stored.episode_id, stored.segment.start, stored.segment.end) == (
        episode.episode_id, segment.start, segment.end,
    )  # fmt: skip
    np.testing.assert_array_equal(stored.actions, episode.actions[segment.start : segment.end])
    np.testing.assert_array_equal(
        stored.images[CAMERA], episode.images[CAMERA][segment.start : segment.end + 1]
    )


def test_trainer_retrain_service_writes_policy_version_1(
    procs: Processes, peer: RosPeer, tmp_path: Path
) -> None:
    client = TrainerClient(peer)
    trainer, _ = _trainer(procs, tmp_path, "trainer", train_steps=20, eval_episodes=8, batch_size=32)
    client.wait_connected()
    for msg in _segment_msgs(generate_episode(PlayConfig(), 2)):
        client.pub.publish(msg)
    client.wait_acknowledged(10)
    retrain = peer.node.create_client(Retrain, "/trainer/retrain")
    assert retrain.wait_for_service(timeout_sec=30)
    future = retrain.call_async(Retrain.Request(wait=True))
    assert peer.spin_until(future.done, 120), "no answer from ~/retrain"
    response = future.result()
    assert response.accepted, response.message
    assert response.policy_version == 1
    assert 0.0 <= response.eval_success_rate <= 1.0
    checkpoints = sorted((tmp_path / "checkpoints").glob("policy-v*.pt"))
    assert [c.name for c in checkpoints] == ["policy-v0001.pt"]
    assert client.peer.spin_until(lambda: client.statuses[-1].policy_version == 1, 10)
    assert stop(trainer) == 0


def test_trainer_services_exist_only_while_configured_and_configure_can_be_retried(
    procs: Processes, peer: RosPeer, tmp_path: Path
) -> None:
    """Services come with configure and go with cleanup; a failed configure leaves nothing behind."""
    services = {"/trainer/retrain", "/trainer/save_buffer", "/trainer/evaluate"}
    (tmp_path / "buffer").write_text("a file where the buffer directory should be")  # configure fails
    trainer, log = _trainer(procs, tmp_path, "trainer", autostart=False)
    change_state = peer.node.create_client(ChangeState, "/trainer/change_state")
    assert change_state.wait_for_service(timeout_sec=30), log.read_text()
    peer.spin_until(lambda: False, 1.0)  # discovery: the lifecycle services are seen, ours would be too

    def transition(transition_id: int) -> bool:
        future = change_state.call_async(ChangeState.Request(transition=Transition(id=transition_id)))
        assert peer.spin_until(future.done, 30), f"no answer to transition {transition_id}"
        return future.result().success

    def offered() -> set[str]:
        return services & {name for name, _ in peer.node.get_service_names_and_types()}

    def wait_offered(expected: set[str]) -> None:
        ok = peer.spin_until(lambda: offered() == expected, 15)
        assert ok, f"services {offered()}, expected {expected}:\n{log.read_text()[-3000:]}"

    def evaluate() -> EvaluatePolicy.Response:
        client = peer.node.create_client(EvaluatePolicy, "/trainer/evaluate")
        try:
            assert client.wait_for_service(timeout_sec=15)
            future = client.call_async(EvaluatePolicy.Request(episodes=1))
            assert peer.spin_until(future.done, 30), "no answer from ~/evaluate"
            return future.result()
        finally:
            peer.node.destroy_client(client)

    assert offered() == set()
    assert not transition(Transition.TRANSITION_CONFIGURE)
    wait_for_log(
        log, r"configure failed: trainer: invalid parameter: buffer_dir '.*buffer': File exists", 10, trainer
    )
    peer.spin_until(lambda: False, 0.5)
    assert offered() == set() and trainer.poll() is None

    (tmp_path / "buffer").unlink()
    (tmp_path / "not_a_dir").write_text("")  # ~/save_buffer into it: an error answer
    for _ in range(2):  # configure -> cleanup -> configure: nothing left over from the round before
        assert transition(Transition.TRANSITION_CONFIGURE), log.read_text()[-3000:]
        wait_offered(services)
        answer = evaluate()  # no policy trained yet: an error answer, the node keeps running
        assert not answer.success and answer.message == "no policy trained yet"
        save = peer.node.create_client(SaveBuffer, "/trainer/save_buffer")
        assert save.wait_for_service(timeout_sec=15)
        future = save.call_async(SaveBuffer.Request(path=str(tmp_path / "not_a_dir" / "dataset")))
        assert peer.spin_until(future.done, 30) and not future.result().success
        peer.node.destroy_client(save)
        assert transition(Transition.TRANSITION_CLEANUP)
        wait_offered(set())
        assert trainer.poll() is None
    assert transition(Transition.TRANSITION_CONFIGURE)
    wait_offered(services)
    assert stop(trainer) == 0, log.read_text()[-3000:]  # from inactive: cleanup at shutdown
    assert "Traceback" not in log.read_text()


# -- bag_player ----------------------------------------------------------------------------------------


def _subscribe_raw(peer: RosPeer, topic: str, msg_type: type, profile) -> list[tuple[float, bytes]]:
    received: list[tuple[float, bytes]] = []
    peer.node.create_subscription(
        msg_type, topic, lambda data: received.append((time.monotonic(), data)), profile, raw=True
    )
    return received


def test_bag_player_fast_delivers_every_message_in_order(
    procs: Processes, peer: RosPeer, tmp_path: Path
) -> None:
    bag = tmp_path / "play"
    write_play_bag(bag, _episodes(3), annotated=True)
    with BagReader(bag) as reader:
        want = [bytes(m.data) for m in reader.messages(["/play/steps"])]
    received = _subscribe_raw(peer, "/play/steps", PlayStep, qos.PLAY_STEPS)
    player, log = procs.node(
        "bag_player", "player", bag=bag, rate=0.0, wait_for_subscribers=1, topics=["/play/steps"], ratee=5.0
    )  # ratee: a misspelling, ignored with a warning
    assert peer.spin_until(lambda: len(received) >= len(want) or player.poll() is not None, 60)
    peer.spin_until(lambda: len(received) >= len(want), 5)
    assert player.wait(timeout=30) == 0, log.read_text()
    assert "parameters this node does not have, ignored: ratee" in log.read_text()
    got = [bytes(data) for _, data in received]
    assert len(got) == len(want), f"lost {len(want) - len(got)} of {len(want)}"
    # DDS pads a payload to a multiple of 4 bytes: the same CDR bytes, plus up to 3 zero bytes.
    for i, (g, w) in enumerate(zip(got, want, strict=True)):
        assert g[: len(w)] == w and len(g) - len(w) < 4 and not any(g[len(w) :]), f"message {i} differs"


def test_bag_player_plays_a_bag_of_an_earlier_playstep_definition_in_todays(
    procs: Processes, peer: RosPeer, tmp_path: Path
) -> None:
    """tests/data/play_bag_v1 holds PlayStep as it was before camera names: played, it decodes as today's."""
    bag = Path(__file__).parent / "data" / "play_bag_v1"
    want = [step for episode in read_play_bag(bag) for step in range(episode.num_steps + 1)]
    frames = {e.episode_id: e.images[CAMERA] for e in read_play_bag(bag)}
    received: list[PlayStep] = []
    peer.node.create_subscription(PlayStep, "/play/steps", received.append, qos.PLAY_STEPS)
    player, log = procs.node(
        "bag_player", "player", bag=bag, rate=0.0, wait_for_subscribers=1, topics=["/play/steps"], ratee=5.0
    )  # ratee: a misspelling, ignored with a warning
    assert peer.spin_until(lambda: len(received) >= len(want) or player.poll() is not None, 60)
    peer.spin_until(lambda: len(received) >= len(want), 5)
    assert player.wait(timeout=30) == 0, log.read_text()
    assert [msg.step for msg in received] == want
    for msg in received:
        assert list(msg.camera_names) == [] and len(msg.extra_observations) == 0
        frame = np.frombuffer(bytes(msg.observation.data), np.uint8).reshape(64, 64, 3)
        np.testing.assert_array_equal(frame, frames[msg.episode_id][msg.step])


def test_bag_player_plays_a_standard_message_robot_bag_with_timed_annotations(
    procs: Processes, peer: RosPeer, tmp_path: Path
) -> None:
    """Image, JointState, Twist and playseg_msgs TimedAnnotation topics, written by rosbags."""
    from playseg_msgs.msg import TimedAnnotation

    from playseg_ros.tabletop.bags import write_sample_bags

    (written,) = write_sample_bags(tmp_path / "robot", episodes=1, annotated=1, image_size=32)
    with BagReader(written.path) as reader:
        want = {topic: 0 for topic in reader.topics}
        for message in reader.messages():
            want[message.topic] += 1
    annotations = [t for t, ty in topic_info_types(written.path).items() if ty.endswith("/TimedAnnotation")]
    assert len(annotations) == 1 and want[annotations[0]] > 0
    received: list[TimedAnnotation] = []
    peer.node.create_subscription(TimedAnnotation, annotations[0], received.append, qos.ANNOTATIONS)
    player, log = procs.node(
        "bag_player", "player", bag=written.path, rate=0.0, wait_for_subscribers=1, wait_topics=annotations
    )
    assert player.wait(timeout=60) == 0, log.read_text()
    assert peer.spin_until(lambda: len(received) >= want[annotations[0]], 10)
    assert all(msg.instruction for msg in received) and "Traceback" not in log.read_text()
    assert f"played {sum(want.values())} messages" in log.read_text()


def topic_info_types(bag: Path) -> dict[str, str]:
    with BagReader(bag) as reader:
        return dict(reader.topics)


def test_bag_player_at_recorded_speed_delivers_every_message_in_order(
    procs: Processes, peer: RosPeer, tmp_path: Path
) -> None:
    """rate 1.0 paces the messages by their recorded times (2.0 s here); how long that takes on a busy
    machine is printed, not asserted."""
    bag, step_ns, count = tmp_path / "timed", 100_000_000, 21  # 2.0 s recorded
    episode = generate_episode(PlayConfig(), 0)
    with BagWriter(bag) as writer:
        writer.add_topic(topic_info("/play/steps", "playseg_msgs/msg/PlayStep"))
        for i in range(count):
            writer.write(
                "/play/steps",
                serialize_message(episode_step_message(episode, i, kind=RCLPY)),
                10**18 + i * step_ns,
            )
    received = _subscribe_raw(peer, "/play/steps", PlayStep, qos.PLAY_STEPS)
    player, _ = procs.node("bag_player", "player", bag=bag, rate=1.0, wait_for_subscribers=1)
    assert peer.spin_until(lambda: len(received) >= count, 60), f"received {len(received)} of {count}"
    with BagReader(bag) as reader:
        want = [bytes(m.data) for m in reader.messages(["/play/steps"])]
    assert [bytes(data)[: len(w)] for (_, data), w in zip(received, want, strict=True)] == want
    print(f"playback of a 2.0 s recording took {received[-1][0] - received[0][0]:.2f} s")
    assert player.wait(timeout=30) == 0


# -- playseg up ----------------------------------------------------------------------------------------


def test_playseg_up_sigint_stops_every_node_and_finishes_the_bag(procs: Processes, tmp_path: Path) -> None:
    out = tmp_path / "live"
    config = yaml.safe_load((Path(__file__).parent.parent / "config" / "live_play.yaml").read_text())
    del config["ros_domain_id"]  # the test's private domain
    config["nodes"][0]["parameters"]["output"] = str(out)
    config["nodes"][1]["parameters"]["rate_hz"] = 100  # an integer for a float parameter is accepted
    (tmp_path / "graph.yaml").write_text(yaml.safe_dump(config))
    launcher, log = procs.start(
        [sys.executable, "-m", "playseg_ros.cli", "up", str(tmp_path / "graph.yaml")], "up"
    )
    wait_for_log(log, r"play_source\]: 1 subscribers: starting", 60, launcher)
    time.sleep(1.0)
    nodes = descendants(launcher.pid)
    assert len(nodes) == 2
    assert stop(launcher, timeout=40) == 0, log.read_text()[-3000:]
    assert not [pid for pid in nodes if Path(f"/proc/{pid}").exists()]
    assert (out / "metadata.yaml").is_file() and not (tmp_path / "live.partial").exists()
    with BagReader(out) as reader:
        counts = {topic: 0 for topic in reader.topics}
        for message in reader.messages():
            counts[message.topic] += 1
    assert counts["/play/steps"] >= 50, counts
    assert counts["/play/ground_truth"] >= 1, counts


# -- write failures and damaged bags: exit codes -------------------------------------------------------


def test_bag_recover_refuses_a_live_recording_which_then_finishes_normally(
    procs: Processes, tmp_path: Path
) -> None:
    out = tmp_path / "live"
    recorder, log = procs.node("recorder", "recorder", output=out, topics=["/chatter"], flush_period_s=0.1)
    wait_for_log(log, r"recording", 30, recorder)  # the bag is open (and locked) from configure on
    result = subprocess.run(
        [sys.executable, "-m", "playseg_ros.cli", "bag", "recover", str(out)],
        env=node_env(), capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert result.returncode == 1
    assert f"is still being written by process {recorder.pid} " in result.stderr, result.stderr
    assert stop(recorder) == 0, log.read_text()[-3000:]
    assert (out / "metadata.yaml").is_file() and not (tmp_path / "live.partial").exists()
    with BagReader(out) as reader:
        assert reader.message_count == 0


def test_recorder_exits_1_when_it_cannot_finish_its_bag(procs: Processes, tmp_path: Path) -> None:
    """Its file lands on a full device (/dev/full): logged, exit 1, and the bag stays in `.partial`."""
    out = tmp_path / "full"
    recorder, log = procs.node("recorder", "recorder", output=out, topics=["/nothing_published"])
    wait_for_log(log, r"recording", 30, recorder)
    (tmp_path / "full.partial" / "full_0.mcap").symlink_to("/dev/full")  # created at close: no message
    assert stop(recorder) == 1, log.read_text()[-3000:]
    text = log.read_text()
    assert re.search(r"finishing \S*full failed: .*No space left on device; .*playseg bag recover", text), (
        text
    )
    assert "cleanup at shutdown failed" in text
    assert (tmp_path / "full.partial").is_dir() and not out.exists()
    assert not (tmp_path / "full.partial" / LOCK_FILE).exists()  # released: recovery is not refused


def test_recorder_exits_1_by_itself_when_the_disk_fills_while_recording(
    procs: Processes, peer: RosPeer, tmp_path: Path
) -> None:
    out = tmp_path / "full"
    pub = peer.node.create_publisher(String, "/chatter", qos.PLAY_STEPS)
    recorder, log = procs.node("recorder", "recorder", output=out, topics=["/chatter"], flush_period_s=0.1)
    wait_for_log(log, r"recording", 30, recorder)
    (tmp_path / "full.partial" / "full_0.mcap").symlink_to("/dev/full")  # created at the first message
    assert peer.spin_until(lambda: pub.get_subscription_count() > 0, 60), log.read_text()
    for i in range(20):
        pub.publish(String(data=f"message {i}"))
    assert recorder.wait(timeout=30) == 1, log.read_text()[-3000:]
    assert re.search(r"flushing \S*full failed: .*No space left on device", log.read_text())


def _damaged_play_bag(path: Path) -> None:
    """A play bag with 64 bytes of garbage inside a middle chunk (framing intact, CRC wrong)."""
    write_play_bag(path, _episodes(3), annotated=True, chunk_bytes=20_000)
    file = path / f"{path.name}_0.mcap"
    with file.open("rb") as stream:
        summary = make_reader(stream).get_summary()
    offsets = sorted(index.chunk_start_offset for index in summary.chunk_indexes)
    assert len(offsets) >= 3
    data = bytearray(file.read_bytes())
    at = offsets[len(offsets) // 2] + 200
    data[at : at + 64] = b"\xa5" * 64
    file.write_bytes(data)


def test_playseg_up_exits_1_when_its_bag_player_cannot_play_the_whole_bag(
    procs: Processes, tmp_path: Path
) -> None:
    bag = tmp_path / "play"
    _damaged_play_bag(bag)
    config = {"nodes": [{"name": "player", "node": "bag_player", "parameters": {"bag": str(bag), "rate": 0.0},
                         "exit_ends_graph": True}]}  # fmt: skip
    (tmp_path / "graph.yaml").write_text(yaml.safe_dump(config))
    launcher, log = procs.start(
        [sys.executable, "-m", "playseg_ros.cli", "up", str(tmp_path / "graph.yaml")], "up"
    )
    assert launcher.wait(timeout=60) == 1, log.read_text()[-3000:]
    text = log.read_text()
    assert re.search(
        rf"playback of {bag} failed after [1-9]\d* messages: bag '{bag}', file 'play_0.mcap'(, topic '/play/\w+')?: damaged chunk",
        text,
    ), text
    assert "[up] player exited with code 1" in text


def test_bag_player_refuses_a_truncated_bag_naming_the_file(procs: Processes, tmp_path: Path) -> None:
    bag = tmp_path / "play"
    write_play_bag(bag, _episodes(1), annotated=True)
    file = bag / "play_0.mcap"
    file.write_bytes(file.read_bytes()[: file.stat().st_size // 2])
    player, log = procs.node("bag_player", "player", bag=bag, rate=0.0)
    assert player.wait(timeout=30) == 2, log.read_text()
    assert re.search(
        r"file 'play_0.mcap': the file is truncated or unfinished .*playseg bag recover", log.read_text()
    )
    write_play_bag(bag := tmp_path / "whole", _episodes(1), annotated=True)
    player, log = procs.node("bag_player", "player_inf", bag=bag, rate=0.0, delivery_timeout_s=".inf")
    assert player.wait(timeout=30) == 2, log.read_text()
    assert "invalid parameter: delivery_timeout_s must be finite and >= 0" in log.read_text()


def test_a_parameter_value_shared_by_two_parameters_is_written_twice(tmp_path: Path) -> None:
    """The ROS 2 parameter parser refuses YAML aliases ("Will not support aliasing"): one list given as
    both `topics` and `wait_topics` (as the demo gives the bag player) must be written out twice."""
    from playseg_ros.launch import NodeSpec, node_command

    topics = ["/camera/image_raw", "/joint_states"]
    node_command(NodeSpec("bag_player", "bag_player", {"topics": topics, "wait_topics": topics}), tmp_path)
    text = (tmp_path / "bag_player.yaml").read_text()
    assert "&" not in text and "*" not in text
    assert yaml.safe_load(text)["bag_player"]["ros__parameters"] == {"topics": topics, "wait_topics": topics}


def test_graph_config_errors_name_the_file_and_the_entry(tmp_path: Path) -> None:
    from playseg_ros.launch import load_graph

    good = {"name": "player", "node": "bag_player", "parameters": {"bag": "x"}}
    cases = [
        ({"nodes": [{**good, "name": "my-player"}]}, "nodes[0]: name 'my-player': a ROS node name"),
        ({"nodes": [{**good, "parameters": ["bag", "x"]}]}, "nodes[0]: parameters must be a mapping"),
        ({"nodes": [good], "ros_domain_id": "seventy"}, "ros_domain_id 'seventy': expected a non-negative"),
        ({"nodes": [good], "shutdown_timeout_s": "soon"}, "shutdown_timeout_s 'soon': expected a positive"),
    ]
    config = tmp_path / "graph.yaml"
    for raw, detail in cases:
        config.write_text(yaml.safe_dump(raw))
        try:
            load_graph(config)
        except ValueError as error:
            assert str(error).startswith(f"{config}: ") and detail in str(error), error
        else:
            raise AssertionError(f"accepted: {raw}")
    config.write_text(yaml.safe_dump({"nodes": [good], "ros_domain_id": 7, "shutdown_timeout_s": 5}))
    assert load_graph(config).ros_domain_id == 7
