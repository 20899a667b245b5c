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
from playseg_ros.convert.live import LiveMapping, LiveStep, ReplayStamps
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


@pytest.mark.parametrize(
    ("silent", "spec"),
    [
        ("/joint_states", RobotBag(seconds=14.0, labels=[], joint_gap=(1.0, 13.0))),
        ("/camera/image_raw", RobotBag(seconds=14.0, labels=[], camera_gap=(1.0, 13.0))),
    ],
)
def test_a_silent_topic_keeps_the_other_buffers_bounded_and_the_steps_of_convert(
    tmp_path: Path, silent: str, spec: RobotBag
) -> None:
    """One topic silent for 12 s while the others go on (a camera or the joint driver died): with
    max_lag 1 s the buffers never hold more than about a second of samples, one warning names the silent
    topic, and the steps are still the ones `playseg convert` keeps of the same bag (a silent feature
    drops the steps it has no sample for; a silent primary has no steps)."""
    bag = write_rosbag2(tmp_path / "robot", spec)
    mapping = load_mapping(write_mapping(tmp_path / "map.yaml", MAPPING))
    converted = convert_bag(bag, mapping)
    live = LiveMapping(mapping, "robot", max_lag_s=1.0)
    steps: list[LiveStep] = []
    notes: list[str] = []
    longest = dict.fromkeys(live.builder.buffers, 0)
    for topic, msgtype, msg, received in messages_of(bag):
        out = live.add(topic, msgtype, msg, received)
        steps, notes = steps + out.steps, notes + out.notes
        for name, buffer in live.builder.buffers.items():
            longest[name] = max(longest[name], len(buffer.stamps))
    end = live.end_stream()
    steps += end.steps
    # a second of each topic (100 Hz joints, 30 Hz camera, 10 Hz commands) and the tolerance on top;
    # unbounded, the 12 s of silence would leave 1,200 joint samples or 360 frames waiting
    assert longest["/joint_states"] <= 110 and longest["/camera/image_raw"] <= 35, longest
    assert longest["/cmd_vel"] <= 13, longest
    silences = [n for n in notes if "is silent" in n]
    assert len(silences) == 1, notes
    assert silences[0].startswith(f"topic {silent} is silent: its newest sample is 1.0")
    assert "behind" in silences[0] and "(more than max_lag 1 s)" in silences[0]
    (episode,) = converted.episodes
    assert len(steps) == episode.num_steps + 1 < 14 * 10 - 100  # the 12 s of silence are not steps
    np.testing.assert_array_equal(np.stack([s.frames[CAMERA] for s in steps]), episode.images[CAMERA])
    np.testing.assert_array_equal(np.stack([s.state for s in steps]), episode.state)
    np.testing.assert_array_equal(np.stack([s.action for s in steps[:-1]]), episode.actions)
    dropped = [n.removeprefix("stream ended: ") for n in end.notes if n.startswith("stream ended: ")]
    assert dropped == [n for n in converted.notes if "step(s)" in n or "episode(s)" in n]


def test_a_wrong_message_on_the_annotation_topic_and_a_late_label_are_reported(tmp_path: Path) -> None:
    """Neither stops the stream: a message that is not a TimedAnnotation is a note naming the topic; a
    label that arrives after its episode closed is not applied, and a note says so."""
    from types import SimpleNamespace

    bag = write_rosbag2(tmp_path / "robot", RobotBag(seconds=3.0, labels=[], silence=(1.0, 2.0)))
    changes = {"episodes": {"split": "gap", "gap_s": 0.5}}
    live = LiveMapping(load_mapping(write_mapping(tmp_path / "map.yaml", dict(MAPPING, **changes))), "robot")
    messages = messages_of(bag)
    first_time = messages[0][3]
    wrong = SimpleNamespace(data="go")
    notes = live.add("/annotations", "std_msgs/msg/String", wrong, first_time).notes
    assert notes == [
        "bag 'live', topic '/annotations': message type is 'std_msgs/msg/String', expected "
        "'playseg_msgs/msg/TimedAnnotation'"
    ]
    cut = next(i for i, m in enumerate(messages) if m[3] > first_time + 2_500_000_000)  # episode 2 runs
    for topic, msgtype, msg, received in messages[:cut]:
        live.add(topic, msgtype, msg, received)
    time = lambda ns: SimpleNamespace(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)  # noqa: E731
    late = SimpleNamespace(start=time(first_time), end=time(first_time + 300_000_000), instruction="late")
    later_notes = live.add("/annotations", "playseg_msgs/msg/TimedAnnotation", late, messages[cut][3]).notes
    for topic, msgtype, msg, received in messages[cut:]:
        later_notes += live.add(topic, msgtype, msg, received).notes
    end = live.end_stream()
    later_notes += end.notes
    assert any("'late'" in n and "arrived after its episode closed: not applied" in n for n in later_notes)


def test_replay_stamps_give_a_headerless_command_its_recorded_time_however_late_it_is_taken(
    tmp_path: Path,
) -> None:
    """A replay: the player publishes each message's recorded time on /clock, then the message (source
    timestamps 2k and 2k + 1); the adapter takes /clock and each topic from its own reader, interleaved at
    random and late. The header-less Twist gets the /clock of its publication: convert's episode."""
    bag = write_rosbag2(tmp_path / "robot", RobotBag(seconds=3.0, labels=[]))
    mapping = load_mapping(write_mapping(tmp_path / "map.yaml"))
    (episode,) = convert_bag(bag, mapping).episodes
    played = []
    for k, (topic, msgtype, msg, t) in enumerate(messages_of(bag)):
        played += [("/clock", "", t, 2 * k), (topic, msgtype, msg, 2 * k + 1)]
    for seed in range(3):
        replay, live, steps = ReplayStamps(), LiveMapping(mapping, "robot"), []
        for topic, msgtype, payload, source in interleaved(played, seed):
            if topic == "/clock":
                released = replay.clock(source, payload)
            elif msgtype == "geometry_msgs/msg/Twist":
                released = replay.stamp(source, (topic, msgtype, payload))
            else:  # stamped: the receive time is not used
                released = [(-1, (topic, msgtype, payload))]
            for stamp, (t, mt, m) in released:
                steps += live.add(t, mt, m, stamp).steps
        for stamp, (t, mt, m) in replay.flush():
            steps += live.add(t, mt, m, stamp).steps
        steps += live.end_stream().steps
        assert replay.refused == 0 and replay.forced == 0
        assert [(s.episode_id, s.step) for s in steps] == [
            ("robot:0", i) for i in range(episode.num_steps + 1)
        ]
        np.testing.assert_array_equal(np.stack([s.action for s in steps[:-1]]), episode.actions)
        np.testing.assert_array_equal(np.stack([s.state for s in steps]), episode.state)


def test_replay_stamps_hold_until_a_later_clock_and_refuse_what_came_before_any() -> None:
    replay = ReplayStamps(held_max=2)
    assert replay.stamp(5, "early") == [] and not replay.started  # held: a /clock may still precede it
    assert replay.clock(10, 1_000) == [] and replay.refused == 1  # published before any /clock: no time
    assert replay.stamp(11, "a") == [] and replay.stamp(12, "b") == []  # held for a later /clock
    assert replay.clock(12, 2_000) == [(1_000, "a")]  # "b" may have been published after this /clock
    assert replay.stamp(11, "late") == [(1_000, "late")]  # taken late: the /clock of its publication
    assert replay.clock(20, 3_000) == [(2_000, "b")]
    assert replay.stamp(21, "c") == [] and replay.stamp(22, "d") == []
    assert replay.stamp(23, "e") == [(3_000, "c")] and replay.forced == 1  # no /clock any more: bounded
    assert replay.flush() == [(3_000, "d"), (3_000, "e")]


def test_episode_ids_count_on_over_streams_and_configurations(tmp_path: Path) -> None:
    mapping = load_mapping(write_mapping(tmp_path / "map.yaml"))
    live = LiveMapping(mapping, "robot", first_episode=3)
    assert live.episodes_done == 3
    bag = write_rosbag2(tmp_path / "robot", RobotBag(seconds=2.0, labels=[]))
    steps = []
    for topic, msgtype, msg, received in messages_of(bag):
        steps += live.add(topic, msgtype, msg, received).steps
    steps += live.end_stream().steps
    assert {s.episode_id for s in steps} == {"robot:3"} and live.episodes_done == 4
