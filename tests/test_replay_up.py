"""Replay without traps: a robot bag played into a live graph by `playseg up` with a minimal config (player
with its /clock ending the graph, topic_adapter on sim time, segmenter, recorder; no hand-set waits) loses
nothing: the recorded PlaySteps are `playseg convert`'s episode step for step and the recorded segments are
`playseg convert --segment`'s segment for segment. `playseg up` wires the waits (who subscribes to what)
and stops the graph upstream first, each node handing on what it still holds."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml
from msg_samples import play_step
from node_procs import ROOT, Processes, RosPeer, node_env, stop, wait_for_log
from playseg_msgs.msg import PlayStep
from std_msgs.msg import String
from test_demo_robot import _untrained_tabletop_model

from playseg_core.data.dataset import PlayDataset
from playseg_core.data.episode import Episode, Segment
from playseg_ros import qos
from playseg_ros.cli import main
from playseg_ros.launch import load_graph
from playseg_ros.play_bags import read_play_bag, read_segment_bag
from playseg_ros.wiring import stop_order

TABLETOP = ROOT / "bags" / "tabletop"
BAG = TABLETOP / "tabletop-1"
MAPPING = TABLETOP / "mapping.yaml"
INPUTS = ["/camera/image_raw/compressed", "/cmd_vel", "/joint_states"]


def minimal_config(path: Path, model: Path, recorded: Path) -> Path:
    """The graph a user writes first: nothing about waiting or draining."""
    config = {
        "ros_domain_id": int(os.environ["ROS_DOMAIN_ID"]),
        "nodes": [
            {"name": "player", "node": "bag_player", "parameters": {"bag": str(BAG), "clock": True},
             "exit_ends_graph": True},
            {"name": "adapter", "node": "topic_adapter",
             "parameters": {"mapping": str(MAPPING), "episode_id": "tabletop-1", "use_sim_time": True}},
            {"name": "segmenter", "node": "segmenter", "parameters": {"model": str(model)}},
            {"name": "recorder", "node": "recorder",
             "parameters": {"output": str(recorded), "topics": ["/play/steps", "/segments"]}},
        ],
    }  # fmt: skip
    path.write_text(yaml.safe_dump(config))
    return path


def test_up_wires_the_waits_and_stops_upstream_first(tmp_path: Path) -> None:
    spec = load_graph(minimal_config(tmp_path / "graph.yaml", tmp_path / "ps.pt", tmp_path / "rec"))
    params = {node.name: node.parameters for node in spec.nodes}
    # the player waits for the adapter on each mapped topic and for the sim-time clocks (adapter: its time
    # source and its own /clock reader); the bag's other topics (annotations, tf) have no subscriber here
    assert sorted(params["player"]["wait_topics"]) == sorted([f"{t}=1" for t in INPUTS] + ["/clock=2"])
    assert params["player"]["wait_for_subscribers"] == 1
    # the adapter subscribes to its inputs once the segmenter and the recorder read its steps
    assert params["adapter"]["wait_for_subscribers"] == 2
    # the segmenter subscribes to steps once the recorder reads its segments
    assert params["segmenter"]["wait_for_subscribers"] == 1
    assert [node.name for node in stop_order(spec)] == ["player", "adapter", "segmenter", "recorder"]


def test_set_waits_are_kept(tmp_path: Path) -> None:
    path = minimal_config(tmp_path / "graph.yaml", tmp_path / "ps.pt", tmp_path / "rec")
    config = yaml.safe_load(path.read_text())
    config["nodes"][1]["parameters"]["wait_for_subscribers"] = 5
    path.write_text(yaml.safe_dump(config))
    assert {n.name: n.parameters for n in load_graph(path).nodes}["adapter"]["wait_for_subscribers"] == 5


@pytest.mark.dds
def assert_recorded_as_converted(recorded: Path, episode: Episode, expected: list[Segment]) -> list[Segment]:
    """The recorded PlaySteps are the converted episode step for step (frames, joint state, commands, all
    of it), and the recorded segments what convert --segment stored, the final one included."""
    [live] = read_play_bag(recorded)
    assert live.episode_id == "tabletop-1:0"
    assert live.num_steps == episode.num_steps, (live.num_steps, episode.num_steps)
    for camera, frames in episode.images.items():
        np.testing.assert_array_equal(live.images[camera], frames)
    np.testing.assert_array_equal(live.state, episode.state)
    np.testing.assert_array_equal(live.actions, episode.actions)
    segments = [clip.segment for clip in read_segment_bag(recorded)]
    assert [(s.start, s.end, s.instruction) for s in segments] == [
        (s.start, s.end, s.instruction) for s in expected
    ]
    assert segments[-1].end == episode.num_steps
    return segments


def test_minimal_replay_through_up_equals_convert_segment(tmp_path: Path) -> None:
    model = _untrained_tabletop_model(tmp_path / "tabletop.pt")
    quiet = ["--mapping", str(MAPPING), "--quiet"]
    assert main(["convert", str(BAG), "--out", str(tmp_path / "data"), *quiet, "--segment", str(model)]) == 0
    converted = PlayDataset.open(tmp_path / "data")
    episode = converted.episode(0)
    expected = converted.segments(0, truth=True)
    assert converted.records[0].episode_id == "tabletop-1:0" and expected

    recorded = tmp_path / "recorded"
    config = minimal_config(tmp_path / "graph.yaml", model, recorded)
    logs = tmp_path / "up.log"
    with open(logs, "wb") as out:
        up = subprocess.run(
            [sys.executable, "-m", "playseg_ros.cli", "up", str(config)], cwd=ROOT, env=node_env(),
            stdout=out, stderr=subprocess.STDOUT, timeout=300,
        )  # fmt: skip
    text = logs.read_text()
    assert up.returncode == 0, text[-4000:]
    assert "Traceback" not in text and "unfinished episodes" not in text, text[-4000:]
    assert "gap at the start" not in text, text[-4000:]

    segments = assert_recorded_as_converted(recorded, episode, expected)
    np.testing.assert_allclose([s.confidence for s in segments], [s.confidence for s in expected], atol=1e-4)


def test_a_node_that_subscribed_after_the_stream_began_warns_once(
    procs: Processes, peer: RosPeer, tmp_path: Path
) -> None:
    """Five PlaySteps published before anyone listens: the recorder and the segmenter each warn once
    that their first message is the publisher's sixth; a topic they heard from its start gives none."""
    model = _untrained_tabletop_model(tmp_path / "tabletop.pt")
    steps = peer.node.create_publisher(PlayStep, "/play/steps", qos.PLAY_STEPS)
    late = peer.node.create_publisher(String, "/late", qos.PLAY_STEPS)
    for step in range(5):
        steps.publish(play_step(step))
    recorder, recorder_log = procs.node(
        "recorder", "recorder", output=str(tmp_path / "rec"), topics=["/play/steps", "/late"]
    )
    segmenter, segmenter_log = procs.node("segmenter", "segmenter", model=str(model))
    heard = lambda: steps.get_subscription_count() >= 2 and late.get_subscription_count() >= 1  # noqa: E731
    assert peer.spin_until(heard, 60), recorder_log.read_text()[-2000:] + segmenter_log.read_text()[-2000:]
    for step in range(5, 10):
        steps.publish(play_step(step))
        late.publish(String(data=str(step)))
    wait_for_log(recorder_log, "gap at the start", 30, recorder)
    wait_for_log(segmenter_log, "gap at the start", 30, segmenter)
    assert stop(segmenter) == 0 and stop(recorder) == 0
    wait_for_log(recorder_log, r"closed .*'/play/steps': 5, '/late': 5", 5)
    for log in (recorder_log, segmenter_log):
        text = log.read_text()
        assert text.count("gap at the start") == 1, text
        assert (
            "/play/steps: gap at the start: the first message received is its publisher's message 6" in text
        )
        assert "Traceback" not in text
