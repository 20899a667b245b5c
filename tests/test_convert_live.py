"""The live mapping (convert/live.py, what the topic_adapter node runs) fed a bag's messages one by one, in
the recorded order and with the topics interleaved at random: the same episodes, steps and labels as
`playseg convert` on the bag. No ROS graph: tests/test_topic_adapter.py runs the node on DDS."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest
from rosbags.highlevel import AnyReader
from test_convert import MAPPING, RobotBag, write_mapping, write_rosbag2

from playseg_core.data.features import STATE
from playseg_ros.convert.build import convert_bag
from playseg_ros.convert.live import LiveMapping, LiveStep
from playseg_ros.convert.mapping import load_mapping
from playseg_ros.convert.source import convert_typestore

CAMERA = "observation.images.front"


def messages_of(bag: Path) -> list[tuple[str, str, Any, int]]:
    with AnyReader([bag], default_typestore=convert_typestore()) as reader:
        return [
            (c.topic, c.msgtype, reader.deserialize(raw, c.msgtype), t) for c, t, raw in reader.messages()
        ]


def interleaved(messages: list, seed: int) -> list:
    """The messages with the topics interleaved at random, each topic's own order kept (what DDS may
    deliver: one reader queue per topic)."""
    rng = np.random.default_rng(seed)
    queues: dict[str, list] = {}
    for message in messages:
        queues.setdefault(message[0], []).append(message)
    out = []
    while queues:
        topic = sorted(queues)[rng.integers(len(queues))]
        out.append(queues[topic].pop(0))
        if not queues[topic]:
            del queues[topic]
    return out


CASES = {
    "labels": (RobotBag(seconds=3.0), {}),
    "joint gap": (RobotBag(seconds=3.0, labels=[], joint_gap=(1.05, 1.35)), {}),
    "gap split": (
        RobotBag(seconds=3.0, labels=[], silence=(1.0, 2.0)),
        {"episodes": {"split": "gap", "gap_s": 0.5}},
    ),
    "marker split": (
        RobotBag(seconds=3.0, labels=[], markers=[1.45]),
        {"episodes": {"split": "marker", "topic": "/episode_start"}},
    ),
    "derived delta, min_steps": (
        RobotBag(seconds=3.0, labels=[], silence=(0.55, 1.0)),
        {
            "features": {**MAPPING["features"], "action": {"derive": "delta", "of": STATE}},
            "episodes": {"split": "gap", "gap_s": 0.3, "min_steps": 6},
        },
    ),
}


@pytest.mark.parametrize("order", ["recorded", "interleaved"])
@pytest.mark.parametrize("case", sorted(CASES))
def test_live_mapping_gives_the_converted_episodes(tmp_path: Path, case: str, order: str) -> None:
    spec, changes = CASES[case]
    bag = write_rosbag2(tmp_path / "robot", spec)
    mapping = load_mapping(write_mapping(tmp_path / "map.yaml", dict(MAPPING, **changes)))
    converted = convert_bag(bag, mapping)
    assert converted.episodes
    messages = messages_of(bag)
    if order == "interleaved":
        messages = interleaved(messages, seed=len(case))
    live = LiveMapping(mapping, "robot")
    steps: list[LiveStep] = []
    annotations = []
    for topic, msgtype, msg, received in messages:
        out = live.add(topic, msgtype, msg, received)
        steps += out.steps
        annotations += out.annotations
    end = live.end_stream()
    steps += end.steps
    annotations += end.annotations
    assert len(steps) == sum(e.num_steps + 1 for e in converted.episodes)
    by_episode: dict[str, list[LiveStep]] = {}
    for step in steps:
        by_episode.setdefault(step.episode_id, []).append(step)
    assert list(by_episode) == [e.episode_id for e in converted.episodes]
    for episode in converted.episodes:
        live_steps = by_episode[episode.episode_id]
        assert [s.step for s in live_steps] == list(range(episode.num_steps + 1))
        np.testing.assert_array_equal(
            np.stack([s.frames[CAMERA] for s in live_steps]), episode.images[CAMERA]
        )
        np.testing.assert_array_equal(np.stack([s.state for s in live_steps]), episode.state)
        np.testing.assert_array_equal(np.stack([s.action for s in live_steps[:-1]]), episode.actions)
        assert live_steps[-1].action is None
        assert [(e, s.start, s.end, s.instruction) for e, s in annotations if e == episode.episode_id] == [
            (episode.episode_id, s.start, s.end, s.instruction) for s in episode.segments
        ]
    # the same drops, reported the same way once the stream ended
    dropped = [n.removeprefix("stream ended: ") for n in end.notes if n.startswith("stream ended: ")]
    assert dropped == [n for n in converted.notes if "step(s)" in n or "episode(s)" in n]
