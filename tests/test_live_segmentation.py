"""The segmenter node on a real ROS graph: live segments equal offline segmentation; bad steps are
logged and survived."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest
import rclpy
import torch
from playseg_msgs.msg import LabelledSegment, PlayStep

from playseg_core.domains.babyai.play import PlayConfig, generate_episode
from playseg_core.domains.babyai.spec import CAMERA, DOMAIN, INSTRUCTIONS
from playseg_core.ps.model import PSModel, load_model, save_model
from playseg_core.ps.segmentation import segment_episode
from playseg_core.ps.training import model_config_for
from playseg_ros import qos
from playseg_ros.launch import Graph, GraphSpec, NodeSpec
from playseg_ros.messages import RCLPY, episode_step_message
from playseg_ros.play_bags import DataInfo, read_play_bag, write_play_bag

pytestmark = pytest.mark.dds  # every test runs a graph of nodes


@pytest.fixture(scope="module")
def model_path(tmp_path_factory) -> Path:
    # An untrained model segments arbitrarily, which is all the equality needs (and exercises many cuts).
    # It reads actions, as the trained default does: the node must hand each step's action over.
    torch.manual_seed(3)
    path = tmp_path_factory.mktemp("model") / "ps.pt"
    config = model_config_for(PlayConfig().features, DOMAIN, len(INSTRUCTIONS))
    model = PSModel(config, list(INSTRUCTIONS))
    model.end_bias.fill_(-0.5)  # a calibrated checkpoint's bias must apply live as offline
    save_model(path, model)
    return path


def _start(tmp_path: Path, kind: str, **parameters: object) -> Graph:
    """One node process, logging to tmp_path/<kind>.log (the `playseg up` machinery)."""
    graph = Graph(GraphSpec([NodeSpec(kind, kind, parameters)], shutdown_timeout_s=10), log_dir=tmp_path)
    graph.start()
    return graph


def _play_bag(tmp_path: Path, model_path: Path, seeds: tuple[int, ...]) -> tuple[Path, int]:
    """A play bag of the episodes of ``seeds`` and how many segments the model finds in it."""
    bag = tmp_path / "play"
    episodes = [generate_episode(PlayConfig(), seed) for seed in seeds]
    write_play_bag(bag, episodes, annotated=False, info=DataInfo(PlayConfig().features, DOMAIN, INSTRUCTIONS))
    model, _ = load_model(model_path)
    return bag, sum(len(segment_episode(model, episode)) for episode in read_play_bag(bag))


class _Collector:
    def __init__(self, topic: str = "/segments") -> None:
        rclpy.init()
        self.node = rclpy.create_node("test_segment_collector")
        self.segments: list[LabelledSegment] = []
        self.node.create_subscription(LabelledSegment, topic, self.segments.append, qos.SEGMENTS)
        self.steps_pub = self.node.create_publisher(PlayStep, "/play/steps", qos.PLAY_STEPS)

    def spin_until(self, condition, timeout_s: float) -> bool:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline and not condition():
            rclpy.spin_once(self.node, timeout_sec=0.05)
        return condition()

    def close(self) -> None:
        self.node.destroy_node()
        rclpy.shutdown()


def test_live_segments_equal_offline_segmentation(tmp_path, model_path):
    episodes = [generate_episode(PlayConfig(), seed) for seed in (11, 12, 13)]
    bag = tmp_path / "play"
    # The bag declares BabyAI's features, so offline its image reads as the model's camera.
    info = DataInfo(PlayConfig().features, DOMAIN, INSTRUCTIONS)
    write_play_bag(bag, episodes, annotated=False, info=info)
    segmenter = _start(tmp_path, "segmenter", model=str(model_path))
    collector = _Collector()
    try:
        # Play only once the segmenter listens: volatile play steps are not replayed to late joiners.
        assert collector.spin_until(lambda: collector.steps_pub.get_subscription_count() >= 1, 30)
        player = _start(tmp_path, "bag_player", bag=str(bag), rate=0.0, wait_for_subscribers=1)
        ends = {e.episode_id: e.num_steps for e in episodes}
        done = lambda: sum(s.end_step == ends[s.episode_id] for s in collector.segments) == len(ends)  # noqa: E731
        assert collector.spin_until(done, 90), (tmp_path / "segmenter.log").read_text()
        player.stop()
    finally:
        collector.close()
        segmenter.stop()

    model, _ = load_model(model_path)
    for episode in read_play_bag(bag):
        offline = segment_episode(model, episode)
        live = [s for s in collector.segments if s.episode_id == episode.episode_id]
        assert [(s.start_step, s.end_step, s.instruction) for s in live] == [
            (s.start, s.end, s.instruction) for s in offline
        ]
        np.testing.assert_allclose(
            [s.label_confidence for s in live], [s.confidence for s in offline], atol=1e-4
        )
        np.testing.assert_allclose(
            [s.segment_log_prob for s in live], [s.log_prob for s in offline], atol=1e-3
        )
        for msg in live:  # self-contained: the segment's own steps, frames equal to the episode's
            assert [p.step for p in msg.steps] == list(range(msg.start_step, msg.end_step + 1))
            frame = np.frombuffer(bytes(msg.steps[-1].observation.data), np.uint8).reshape(64, 64, 3)
            np.testing.assert_array_equal(frame, episode.images[CAMERA][msg.end_step])


def test_malformed_steps_are_logged_and_the_node_keeps_running(tmp_path, model_path):
    good = generate_episode(PlayConfig(), 21)
    segmenter = _start(tmp_path, "segmenter", model=str(model_path))
    collector = _Collector()
    try:
        assert collector.spin_until(lambda: collector.steps_pub.get_subscription_count() >= 1, 30)
        bad_encoding = episode_step_message(good, 0, kind=RCLPY)
        bad_encoding.episode_id = "bad-encoding"
        bad_encoding.observation.encoding = "bgr8"
        bad_size = episode_step_message(good, 0, kind=RCLPY)
        bad_size.episode_id = "bad-size"
        bad_size.observation.data = bytes(10)
        nan_action = episode_step_message(good, 0, kind=RCLPY)
        nan_action.episode_id = "nan-action"
        nan_action.action = [float("nan")]
        bad_action = [episode_step_message(good, t, kind=RCLPY) for t in (0, 1)]
        for msg in bad_action:
            msg.episode_id = "bad-action"
        bad_action[0].action = [9.0]  # BabyAI has actions 0..6
        gap = [episode_step_message(good, t, kind=RCLPY) for t in (0, 1, 3)]
        for msg in gap:
            msg.episode_id = "gap"
        ends_early = [episode_step_message(good, t, kind=RCLPY) for t in range(6)]
        for msg in ends_early:
            msg.episode_id = "ends-early"
        ends_early[3].episode_end, ends_early[3].action = True, []  # then steps 4 and 5 go on
        for msg in [bad_encoding, bad_size, nan_action, *bad_action, *gap, *ends_early]:
            collector.steps_pub.publish(msg)
        for t in range(good.num_steps + 1):
            collector.steps_pub.publish(episode_step_message(good, t, kind=RCLPY))
        done = lambda: any(s.end_step == good.num_steps for s in collector.segments)  # noqa: E731
        assert collector.spin_until(done, 60), (tmp_path / "segmenter.log").read_text()
        assert segmenter.processes["segmenter"].poll() is None
    finally:
        collector.close()
        segmenter.stop()
    log = (tmp_path / "segmenter.log").read_text()
    assert "'bad-encoding' step 0: observation.encoding is 'bgr8'" in log
    assert "'bad-size' step 0: observation.data holds 10 bytes" in log
    assert "'nan-action' step 0: action contains NaN" in log
    assert "'gap' step 3: step gap, expected step 2" in log
    assert log.count("'ends-early' goes on after its episode_end (step 4)") == 1  # once, not per step
    assert "'bad-action' step 0: segmentation failed" in log and "= 9.0: not a discrete action index" in log
    assert {s.episode_id for s in collector.segments} == {good.episode_id, "ends-early"}
    assert [s.end_step for s in collector.segments if s.episode_id == "ends-early"][-1] == 3  # its own end


def test_a_keep_rule_the_checkpoint_has_no_threshold_for_fails_configure_in_one_line(tmp_path, model_path):
    segmenter = _start(tmp_path, "segmenter", model=str(model_path), keep="own_cuts")
    log = tmp_path / "segmenter.log"
    try:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and "own-cut calibration" not in log.read_text():
            time.sleep(0.2)
        assert segmenter.processes["segmenter"].poll() is None  # unconfigured, still there to retry
    finally:
        segmenter.stop()
    text = log.read_text()
    assert f"segmenter: model {model_path}: records no own-cut calibration" in text, text[-2000:]
    assert "Traceback" not in text


def test_reference_form_segments_give_the_trainer_the_same_buffer_as_embedded_ones(tmp_path, model_path):
    """Two pipelines on the same play: segmenter (embedded form) -> trainer, and segmenter (reference form)
    + recorder -> trainer. The reference segments carry no steps (a few hundred bytes); their trainer
    reads the steps from the recording while it is still being written; both buffers end up with the
    same segments and the same steps."""
    from playseg_msgs.msg import TrainerStatus
    from rclpy.serialization import serialize_message

    from playseg_core.augment.buffer import AugmentationBuffer

    bag, expected = _play_bag(tmp_path, model_path, (31, 32))
    recording = tmp_path / "recording"

    def trainer(form: str, **parameters: object) -> NodeSpec:
        return NodeSpec(f"trainer_{form}", "trainer", {
            "buffer_dir": str(tmp_path / f"buffer_{form}"), "checkpoint_dir": str(tmp_path / f"ckpt_{form}"),
            "segments_topic": f"/segments_{form}", "status_topic": f"/status_{form}", "status_period_s": 0.5,
            **parameters,
        })  # fmt: skip

    graph = Graph(
        GraphSpec(
            [
                NodeSpec("recorder", "recorder", {"output": str(recording), "topics": ["/play/steps"]}),
                trainer("embedded"),
                trainer("reference", resolve_period_s=0.2),
                NodeSpec("segmenter_embedded", "segmenter", {
                    "model": str(model_path), "segments_topic": "/segments_embedded"}),
                NodeSpec("segmenter_reference", "segmenter", {
                    "model": str(model_path), "segments_topic": "/segments_reference",
                    "segment_form": "reference", "recording_bag": str(recording)}),
            ],
            shutdown_timeout_s=20,
        ),
        log_dir=tmp_path,
    )  # fmt: skip
    graph.start()
    collector = _Collector("/segments_reference")
    buffered = {"embedded": 0, "reference": 0}
    for form in buffered:
        collector.node.create_subscription(
            TrainerStatus, f"/status_{form}", lambda s, f=form: buffered.__setitem__(f, s.buffer_segments),
            qos.STATUS,
        )  # fmt: skip
    try:
        # both segmenters and the recorder (it subscribes once a publisher, ours, shows the type)
        assert collector.spin_until(lambda: collector.steps_pub.get_subscription_count() >= 3, 60)
        player = _start(tmp_path, "bag_player", bag=str(bag), rate=0.0, wait_for_subscribers=3)
        done = lambda: buffered == {"embedded": expected, "reference": expected}  # noqa: E731
        logs = lambda: "\n".join(p.read_text()[-2000:] for p in sorted(tmp_path.glob("*.log")))  # noqa: E731
        assert collector.spin_until(done, 120), (buffered, expected, logs())
        assert (tmp_path / "recording.partial").is_dir()  # read while the recorder still writes
        player.stop()
    finally:
        collector.close()
        codes = graph.stop()
    assert set(codes.values()) == {0}, codes
    assert not graph.params_dir.exists()  # the nodes' parameter files go with the graph
    reference_log = (tmp_path / "trainer_reference.log").read_text()
    assert "dropped" not in reference_log and "Traceback" not in reference_log
    assert len(collector.segments) == expected
    sizes = [len(serialize_message(msg)) for msg in collector.segments]
    assert all(len(msg.steps) == 0 and msg.recording_bag == str(recording) for msg in collector.segments)
    assert all(msg.steps_topic == "/play/steps" for msg in collector.segments) and max(sizes) < 400, sizes

    def clips(form: str) -> dict:
        with AugmentationBuffer(tmp_path / f"buffer_{form}") as buffer:
            return {(c.episode_id, c.segment.start, c.segment.end): c for c in buffer}

    embedded, referenced = clips("embedded"), clips("reference")
    assert len(embedded) == expected and sorted(referenced) == sorted(embedded)
    for key, want in embedded.items():
        got = referenced[key]
        assert (got.segment, got.source) == (want.segment, want.source)
        np.testing.assert_array_equal(got.actions, want.actions)
        np.testing.assert_array_equal(got.state, want.state)
        assert list(got.images) == list(want.images) == [CAMERA]
        np.testing.assert_array_equal(got.images[CAMERA], want.images[CAMERA])


def test_two_segmenters_of_one_name_are_warned_about_and_the_trainer_stores_each_segment_once(
    tmp_path, model_path
):
    """The issue's case: two segmenters started with the same node name both run and every segment is
    published twice. Each warns about the other (a graph query), and the trainer stores each segment
    once: segments are keyed by (episode, start, end, checkpoint digest), so a copy of the checkpoint
    under another file name is the same model."""
    import shutil

    from playseg_msgs.msg import TrainerStatus

    from playseg_core.augment.buffer import AugmentationBuffer

    bag, expected = _play_bag(tmp_path, model_path, (41, 42))
    copy = tmp_path / "ps-copy.pt"
    shutil.copy(model_path, copy)
    trainer = _start(
        tmp_path, "trainer", buffer_dir=str(tmp_path / "buffer"), checkpoint_dir=str(tmp_path / "ckpt"),
        status_period_s=0.5,
    )  # fmt: skip
    # two processes, one node name (`segmenter`, each node's default): what starting one twice gives
    first = Graph(
        GraphSpec([NodeSpec("segmenter", "segmenter", {"model": str(model_path)})]), log_dir=tmp_path / "a"
    )
    second = Graph(
        GraphSpec([NodeSpec("segmenter", "segmenter", {"model": str(copy)})]), log_dir=tmp_path / "b"
    )
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    first.start()
    second.start()
    collector = _Collector()
    buffered = [0]
    collector.node.create_subscription(
        TrainerStatus, "/trainer/status", lambda s: buffered.__setitem__(0, s.buffer_segments), qos.STATUS
    )
    logs = lambda: "\n".join(p.read_text()[-2000:] for p in sorted(tmp_path.rglob("*.log")))  # noqa: E731
    try:
        assert collector.spin_until(lambda: collector.steps_pub.get_subscription_count() >= 2, 60), logs()
        player = _start(tmp_path, "bag_player", bag=str(bag), rate=0.0, wait_for_subscribers=2)
        twice = lambda: len(collector.segments) >= 2 * expected  # noqa: E731
        assert collector.spin_until(twice, 120), (len(collector.segments), expected, logs())
        assert collector.spin_until(lambda: buffered[0] == expected, 30), (buffered, expected, logs())
        collector.spin_until(lambda: False, 1.5)  # nothing more is stored
        assert buffered[0] == expected
        player.stop()
    finally:
        collector.close()
        codes = {**first.stop(), **second.stop(), **trainer.stop()}
    assert set(codes.values()) == {0}, codes
    ids = {s.model_id for s in collector.segments}
    assert len(ids) == 2 and len({i.rsplit("@sha256:", 1)[1] for i in ids}) == 1, ids
    for log in (tmp_path / "a" / "segmenter.log", tmp_path / "b" / "segmenter.log"):
        assert "2 nodes named /segmenter on the graph" in log.read_text(), log.read_text()[-2000:]
    with AugmentationBuffer(tmp_path / "buffer") as buffer:
        assert len(buffer) == expected
