"""Bag I/O without rclpy: round trips, interoperability with rosbags and mcap_ros2, splitting, recovery,
and clear errors for bad bags."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import textwrap
import warnings
from pathlib import Path

import numpy as np
import pytest
import yaml
from mcap.reader import make_reader
from rosbags.highlevel import AnyReader
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as RosbagsWriter
from rosbags.typesys import get_types_from_msg

from playseg_core.data.episode import Episode, Segment, SegmentClip
from playseg_core.data.features import ACTION, DEFAULT_CAMERA, STATE, Feature, Features
from playseg_core.domains.babyai.spec import CAMERA
from playseg_ros.bag import BagError, BagReader, BagWriter, recover_bag, ros2msg_definition, topic_info
from playseg_ros.cli import main as cli_main
from playseg_ros.messages import (
    ANNOTATION,
    PLAY_STEP,
    annotation_message,
    episode_messages,
    stamp_ns,
)
from playseg_ros.play_bags import (
    ANNOTATIONS_TOPIC,
    GROUND_TRUTH_TOPIC,
    STEPS_TOPIC,
    DataInfo,
    iter_play_bag,
    read_play_bag,
    read_play_bag_info,
    read_segment_bag,
    write_play_bag,
    write_segment_bag,
)
from playseg_ros.typestore import playseg_typestore

ROOT = Path(__file__).resolve().parent.parent
DATA = ROOT / "tests" / "data"

INSTRUCTIONS = ("go to the red ball", "go to a blue key", "go to the grey box")


def make_episode(index: int, num_steps: int, size: int = 8, with_state: bool = True) -> Episode:
    """A random episode split into 1-3 labelled segments."""
    rng = np.random.default_rng(index)
    cuts = sorted(rng.choice(np.arange(1, num_steps), size=min(2, num_steps - 1), replace=False).tolist())
    bounds = [0, *cuts, num_steps]
    segments = [
        Segment(a, b, INSTRUCTIONS[(index + i) % 3])
        for i, (a, b) in enumerate(zip(bounds, bounds[1:], strict=False))
    ]
    return Episode(
        episode_id=f"ep-{index:03d}",
        images={DEFAULT_CAMERA: rng.integers(0, 256, (num_steps + 1, size, size, 3), dtype=np.uint8)},
        actions=rng.integers(0, 7, (num_steps, 1)).astype(np.float32),
        state=rng.integers(0, 11, (num_steps + 1, 4, 4, 3)).astype(np.uint8) if with_state else None,
        segments=segments,
    )


def assert_same_episode(got: Episode, want: Episode, segments: list[Segment]) -> None:
    assert got.episode_id == want.episode_id
    assert sorted(got.images) == sorted(want.images)
    for name, frames in want.images.items():
        assert np.array_equal(got.images[name], frames)
    assert np.array_equal(got.actions, want.actions) and got.actions.dtype == np.float32
    if want.state is None:
        assert got.state is None
    else:
        # without a declared schema a bag's state reads back as float32 (PlayStep.state)
        assert np.array_equal(got.state, want.state.astype(np.float32))
    assert got.segments == segments


@pytest.fixture()
def episodes() -> list[Episode]:
    return [make_episode(0, 9, size=64), make_episode(1, 5, with_state=False), make_episode(2, 12)]


def test_play_bag_round_trip(tmp_path: Path, episodes: list[Episode]) -> None:
    summary = write_play_bag(tmp_path / "play", episodes, annotated={"ep-001"})
    assert summary.topic_counts[STEPS_TOPIC] == sum(e.num_steps + 1 for e in episodes)
    assert summary.topic_counts[ANNOTATIONS_TOPIC] == len(episodes[1].segments)
    for got, want in zip(read_play_bag(tmp_path / "play"), episodes, strict=True):
        assert_same_episode(got, want, want.segments if want.episode_id == "ep-001" else [])
    for got, want in zip(read_play_bag(tmp_path / "play", truth=True), episodes, strict=True):
        assert_same_episode(got, want, want.segments)
    assert sorted(os.listdir(tmp_path)) == ["play"]  # the .partial directory was renamed


def test_a_bag_declaring_its_features_reads_back_under_them(tmp_path: Path) -> None:
    wrist = "observation.images.wrist"
    episodes = [make_episode(i, 6) for i in range(2)]
    for episode in episodes:
        episode.images = {wrist: episode.images.pop(DEFAULT_CAMERA)}
    features = Features.of(
        [
            Feature(wrist, "image", "uint8", (8, 8, 3)),
            Feature(STATE, "state", "uint8", (4, 4, 3)),
            Feature(ACTION, "action", "float32", (1,), num_values=7),
        ],
        fps=10.0,
    )
    info = DataInfo(features, domain="babyai", instructions=INSTRUCTIONS)
    write_play_bag(tmp_path / "play", episodes, annotated=True, info=info)
    assert read_play_bag_info(tmp_path / "play") == info
    for got, want in zip(read_play_bag(tmp_path / "play"), episodes, strict=True):
        assert list(got.images) == [wrist] and got.state.dtype == np.uint8  # the declared camera and dtype
        np.testing.assert_array_equal(got.images[wrist], want.images[wrist])
        np.testing.assert_array_equal(got.state, want.state)
    # Data that contradicts its declaration is refused, naming the episode and feature; nothing is left.
    bad = tmp_path / "bad"
    wrong = Features.of(
        [features[wrist], features.action], fps=10.0
    )  # declares no state, the steps carry one
    with pytest.raises(BagError, match="episode 'ep-000'.*has \\['observation.state'\\] features"):
        write_play_bag(bad, episodes, annotated=True, info=DataInfo(wrong))
    assert not bad.exists() and not (tmp_path / "bad.partial").exists()


def test_a_state_only_episode_round_trips_through_a_play_bag(tmp_path: Path) -> None:
    rng = np.random.default_rng(3)
    episode = Episode(
        "arm-0",
        actions=rng.normal(size=(5, 7)).astype(np.float32),
        state=rng.normal(size=(6, 7)).astype(np.float32),
        segments=[Segment(0, 5, "go to a blue key")],
    )
    write_play_bag(tmp_path / "play", [episode], annotated=True)
    (got,) = read_play_bag(tmp_path / "play")
    assert got.images == {}  # an empty (0x0) image: no camera
    assert_same_episode(got, episode, episode.segments)


def test_cameras_of_different_sizes_round_trip_through_a_play_bag_by_name(tmp_path: Path) -> None:
    rng = np.random.default_rng(4)
    images = {  # not in name order: names, not positions, say which frame is which
        "observation.images.wrist": rng.integers(0, 256, (6, 4, 6, 3), dtype=np.uint8),
        "observation.images.front": rng.integers(0, 256, (6, 8, 10, 3), dtype=np.uint8),
    }
    episode = Episode(
        "two", rng.normal(size=(5, 7)).astype(np.float32), images, segments=[Segment(0, 5, "x")]
    )
    write_play_bag(tmp_path / "two", [episode], annotated=True)
    (got,) = read_play_bag(tmp_path / "two")
    assert sorted(got.images) == sorted(images)
    assert_same_episode(got, episode, episode.segments)


def test_a_bag_recorded_before_playstep_named_its_cameras_still_reads() -> None:
    """tests/data/play_bag_v1: the sample test bag as written with the one-camera PlayStep."""
    old = read_play_bag(DATA / "play_bag_v1", truth=True)
    new = read_play_bag(ROOT / "bags" / "test", truth=True)
    assert len(old) == len(new) > 0
    for before, now in zip(old, new, strict=True):
        assert (
            list(before.images) == list(now.images) == [CAMERA]
        )  # the declared camera, unnamed in the steps
        assert_same_episode(before, now, now.segments)


def test_unannotated_bag_without_ground_truth_has_no_segments(
    tmp_path: Path, episodes: list[Episode]
) -> None:
    write_play_bag(tmp_path / "play", episodes, annotated=False, ground_truth=False)
    with BagReader(tmp_path / "play") as reader:
        assert set(reader.topics) == {STEPS_TOPIC}
    assert [e.segments for e in read_play_bag(tmp_path / "play")] == [[], [], []]
    with pytest.raises(BagError, match=f"topic '{GROUND_TRUTH_TOPIC}'.*missing"):
        read_play_bag(tmp_path / "play", truth=True)


def test_segment_bag_round_trip(tmp_path: Path, episodes: list[Episode]) -> None:
    labelled = Segment(3, 7, "go to a blue key", confidence=0.75, log_prob=-2.5)
    clips = [
        SegmentClip.from_episode(episodes[0], labelled, "ps-test"),
        SegmentClip.from_episode(episodes[1], episodes[1].segments[0], "ps-test"),
    ]
    write_segment_bag(tmp_path / "seg", clips)
    got = read_segment_bag(tmp_path / "seg")
    assert [(c.episode_id, c.segment, c.source) for c in got] == [
        ("ep-000", labelled, "ps-test"),
        ("ep-001", episodes[1].segments[0], "ps-test"),
    ]
    assert np.array_equal(got[0].images[DEFAULT_CAMERA], episodes[0].images[DEFAULT_CAMERA][3:8])
    assert np.array_equal(got[0].actions, episodes[0].actions[3:7])
    assert np.array_equal(got[0].state, episodes[0].state[3:8].astype(np.float32))
    assert got[1].state is None


def test_schema_text_is_rosbag2_ros2msg_and_hashes_like_the_installed_package() -> None:
    text = ros2msg_definition(PLAY_STEP)
    store = playseg_typestore()
    assert text.startswith((Path(sys.prefix) / "share/playseg_msgs/msg/PlayStep.msg").read_text())
    headers = [line for line in text.splitlines() if line.startswith("MSG: ")]
    assert headers == ["MSG: sensor_msgs/Image", "MSG: std_msgs/Header", "MSG: builtin_interfaces/Time"]
    assert text.count("=" * 80 + "\nMSG: ") == 3
    # Parsed back by rosbags, the text defines the same types: same RIHS01 hash as rosidl generated.
    installed = json.loads((Path(sys.prefix) / "share/playseg_msgs/msg/PlayStep.json").read_text())
    parsed = get_types_from_msg(text, PLAY_STEP)
    assert set(parsed) == {
        PLAY_STEP,
        "sensor_msgs/msg/Image",
        "std_msgs/msg/Header",
        "builtin_interfaces/msg/Time",
    }
    assert store.hash_rihs01(PLAY_STEP) == installed["type_hashes"][0]["hash_string"]
    assert topic_info(STEPS_TOPIC, PLAY_STEP).type_hash == installed["type_hashes"][0]["hash_string"]


def test_our_bag_is_read_by_rosbags_anyreader(tmp_path: Path, episodes: list[Episode]) -> None:
    write_play_bag(tmp_path / "play", episodes, annotated=True)
    steps, annotations = [], []
    with AnyReader([tmp_path / "play"], default_typestore=playseg_typestore()) as reader:
        assert {c.topic: c.msgtype for c in reader.connections} == {
            STEPS_TOPIC: PLAY_STEP,
            ANNOTATIONS_TOPIC: ANNOTATION,
            GROUND_TRUTH_TOPIC: ANNOTATION,
        }
        qos = next(c for c in reader.connections if c.topic == STEPS_TOPIC).ext.offered_qos_profiles
        assert qos and qos[0].depth == 10
        for connection, timestamp, raw in reader.messages():
            msg = reader.deserialize(raw, connection.msgtype)
            assert stamp_ns(msg.header) == timestamp
            (steps if connection.topic == STEPS_TOPIC else annotations).append((connection.topic, msg))
    first = [m for _, m in steps if m.episode_id == "ep-000"]
    assert [m.step for m in first] == list(range(10))
    for t, msg in enumerate(first):
        assert (msg.observation.height, msg.observation.width, msg.observation.encoding) == (64, 64, "rgb8")
        assert bytes(msg.observation.data) == episodes[0].images[DEFAULT_CAMERA][t].tobytes()
        assert list(msg.state_shape) == [4, 4, 3]
        assert np.array_equal(msg.state, episodes[0].state[t].reshape(-1))
        assert msg.episode_end == (t == 9)
        assert list(msg.action) == ([] if t == 9 else episodes[0].actions[t].tolist())
    labels = [
        (m.episode_id, m.start_step, m.end_step, m.instruction)
        for topic, m in annotations
        if topic == ANNOTATIONS_TOPIC
    ]
    assert labels == [(e.episode_id, s.start, s.end, s.instruction) for e in episodes for s in e.segments]


def test_our_bag_is_read_by_mcap_ros2(tmp_path: Path, episodes: list[Episode]) -> None:
    write_play_bag(tmp_path / "play", episodes, annotated=True)
    (mcap_file,) = sorted((tmp_path / "play").glob("*.mcap"))
    with mcap_file.open("rb") as stream:
        reader = make_reader(stream)
        assert reader.get_header().profile == "ros2"
        summary = reader.get_summary()
        assert {s.encoding for s in summary.schemas.values()} == {"ros2msg"}
        assert {c.message_encoding for c in summary.channels.values()} == {"cdr"}
        assert {i.compression for i in summary.chunk_indexes} == {"zstd"}
        for channel in summary.channels.values():
            assert yaml.safe_load(channel.metadata["offered_qos_profiles"])[0]["reliability"] == "reliable"
            assert channel.metadata["topic_type_hash"].startswith("RIHS01_")
        (record,) = [m for m in reader.iter_metadata() if m.name == "rosbag2"]
        assert yaml.safe_load(record.metadata["serialized_metadata"])["message_count"] > 0
        assert record.metadata["ros_distro"]
    with warnings.catch_warnings():  # mcap_ros2.reader warns about mcap_ros1 on import
        warnings.simplefilter("ignore", DeprecationWarning)
        from mcap_ros2.reader import read_ros2_messages
    frames = {}
    for item in read_ros2_messages(str(mcap_file), topics=[STEPS_TOPIC]):
        msg = item.ros_msg
        frames[(msg.episode_id, msg.step)] = (bytes(msg.observation.data), list(msg.action), msg.episode_end)
    for episode in episodes:
        for t in range(episode.num_steps + 1):
            data, action, end = frames[(episode.episode_id, t)]
            assert data == episode.images[DEFAULT_CAMERA][t].tobytes()
            assert action == ([] if t == episode.num_steps else episode.actions[t].tolist())
            assert end == (t == episode.num_steps)


@pytest.mark.parametrize("storage", [StoragePlugin.SQLITE3, StoragePlugin.MCAP])
def test_bags_written_by_rosbags_are_read(
    tmp_path: Path, episodes: list[Episode], storage: StoragePlugin
) -> None:
    store = playseg_typestore()
    with RosbagsWriter(tmp_path / "theirs", version=9, storage_plugin=storage) as writer:
        steps = writer.add_connection(STEPS_TOPIC, PLAY_STEP, typestore=store)
        notes = writer.add_connection(ANNOTATIONS_TOPIC, ANNOTATION, typestore=store)
        now = 1_000
        for episode in episodes:
            stamps = list(range(now, now + episode.num_steps + 1))
            for msg in episode_messages(episode, stamps):
                writer.write(steps, stamp_ns(msg.header), store.serialize_cdr(msg, PLAY_STEP))
            for segment in episode.segments:
                writer.write(
                    notes,
                    stamps[-1],
                    store.serialize_cdr(
                        annotation_message(episode.episode_id, segment, stamps[-1]), ANNOTATION
                    ),
                )
            now = stamps[-1] + 1
    for got, want in zip(read_play_bag(tmp_path / "theirs"), episodes, strict=True):
        assert_same_episode(got, want, want.segments)


def test_split_by_size_lists_every_file_in_order(tmp_path: Path) -> None:
    episodes = [make_episode(i, 20, size=32) for i in range(4)]
    summary = write_play_bag(
        tmp_path / "split",
        episodes,
        annotated=True,
        max_file_bytes=40_000,
        chunk_bytes=8_000,
        compression="none",
    )
    meta = yaml.safe_load((tmp_path / "split" / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    names = [f"split_{i}.mcap" for i in range(len(summary.files))]
    assert len(names) >= 3
    assert meta["relative_file_paths"] == names == [f["path"] for f in meta["files"]]
    assert sorted(p.name for p in (tmp_path / "split").glob("*.mcap")) == sorted(names)
    assert sum(f["message_count"] for f in meta["files"]) == meta["message_count"] == summary.message_count
    for name in names[:-1]:
        # one chunk of slack at most, plus the summary written at close (schemas, channels, indexes)
        assert (tmp_path / "split" / name).stat().st_size <= 40_000 + 8_000 + 2_000
    for got, want in zip(read_play_bag(tmp_path / "split"), episodes, strict=True):
        assert_same_episode(got, want, want.segments)
    with AnyReader([tmp_path / "split"], default_typestore=playseg_typestore()) as reader:
        assert sum(1 for _ in reader.messages()) == summary.message_count


def test_split_by_duration(tmp_path: Path) -> None:
    episodes = [make_episode(i, 9) for i in range(3)]  # 10 steps of 0.1 s each
    summary = write_play_bag(
        tmp_path / "d", episodes, annotated=False, ground_truth=False, max_file_duration_ns=500_000_000
    )
    assert [f.message_count for f in summary.files] == [5] * 6
    assert all(f.end_ns - f.start_ns < 500_000_000 for f in summary.files)
    assert len(read_play_bag(tmp_path / "d")) == 3


RECORDER_CHILD = textwrap.dedent(
    """
    import sys, time
    from playseg_ros.bag import BagWriter, topic_info
    from playseg_ros.typestore import playseg_typestore
    store = playseg_typestore()
    String = store.types["std_msgs/msg/String"]
    writer = BagWriter(sys.argv[1], chunk_bytes=600, max_file_bytes=3000, compression="zstd")
    writer.add_topic(topic_info("/chatter", "std_msgs/msg/String"))
    for i in range(60):
        writer.write("/chatter", store.serialize_cdr(String(data=f"message {i:04d} " + "x" * 80), "std_msgs/msg/String"), 1000 + i)
    writer.flush()
    for i in range(60, 63):  # left in the open chunk: lost by the crash
        writer.write("/chatter", store.serialize_cdr(String(data=f"message {i:04d}"), "std_msgs/msg/String"), 1000 + i)
    print("flushed 60", flush=True)
    time.sleep(60)
    """
)


def test_recover_after_sigkill_restores_every_flushed_message(tmp_path: Path) -> None:
    bag = tmp_path / "rec"
    child = subprocess.Popen(
        [sys.executable, "-c", RECORDER_CHILD, str(bag)], stdout=subprocess.PIPE, text=True
    )
    try:
        assert child.stdout.readline().strip() == "flushed 60"
    finally:
        child.send_signal(signal.SIGKILL)
        child.wait(timeout=10)
    assert not bag.exists() and (tmp_path / "rec.partial").is_dir()
    with pytest.raises(BagError, match="recover"):
        BagReader(bag)
    report = recover_bag(bag)
    assert len(report) >= 2 and report[-1].rebuilt  # earlier files were finished, the last is rebuilt
    assert [r.rebuilt for r in report[:-1]] == [False] * (len(report) - 1)
    assert sum(r.messages for r in report) == 60
    store = playseg_typestore()
    with AnyReader([bag], default_typestore=store) as reader:
        texts = [reader.deserialize(raw, c.msgtype).data for c, _, raw in reader.messages()]
    assert [t.split()[1] for t in texts] == [f"{i:04d}" for i in range(60)]
    meta = yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert meta["message_count"] == 60 and len(meta["relative_file_paths"]) == len(report)


def test_recover_drops_a_chunk_cut_in_the_middle(tmp_path: Path) -> None:
    store = playseg_typestore()
    String = store.types["std_msgs/msg/String"]
    writer = BagWriter(tmp_path / "live", chunk_bytes=1000, compression="none")
    writer.add_topic(topic_info("/chatter", "std_msgs/msg/String"))
    for i in range(30):  # ~345 bytes each: a chunk every 3 messages
        text = f"{i:04d} " + "y" * 300
        writer.write("/chatter", store.serialize_cdr(String(data=text), "std_msgs/msg/String"), 10 + i)
    writer.flush()
    data = (tmp_path / "live.partial" / "live_0.mcap").read_bytes()  # copied while the writer is open
    writer.abort()
    assert list(tmp_path.iterdir()) == []
    (tmp_path / "cut.partial").mkdir()
    (tmp_path / "cut.partial" / "cut_0.mcap").write_bytes(data[:-300])  # inside the last chunk
    (report,) = recover_bag(tmp_path / "cut.partial")
    assert report.rebuilt and report.messages == 27 and report.dropped_bytes > 0
    with AnyReader([tmp_path / "cut"], default_typestore=store) as reader:
        texts = [reader.deserialize(raw, c.msgtype).data for c, _, raw in reader.messages()]
    assert [t[:4] for t in texts] == [f"{i:04d}" for i in range(27)]


# --- bad input -----------------------------------------------------------------------------------------


def write_messages(path: Path, messages: list[tuple[str, str, object]]) -> None:
    """A bag of (topic, type, message) written as given, however wrong."""
    store = playseg_typestore()
    with BagWriter(path) as writer:
        for i, (topic, type_name, msg) in enumerate(messages):
            writer.add_topic(topic_info(topic, type_name))
            writer.write(topic, store.serialize_cdr(msg, type_name), 1000 + i)


def step_messages(episode: Episode) -> list[tuple[str, str, object]]:
    stamps = list(range(1000, 1000 + episode.num_steps + 1))
    return [(STEPS_TOPIC, PLAY_STEP, m) for m in episode_messages(episode, stamps)]


def test_missing_steps_topic(tmp_path: Path) -> None:
    note = annotation_message("ep-000", Segment(0, 2, "go to the red ball"), 5)
    write_messages(tmp_path / "bad", [(ANNOTATIONS_TOPIC, ANNOTATION, note)])
    with pytest.raises(BagError, match=rf"bag '{tmp_path / 'bad'}', topic '/play/steps': topic missing"):
        read_play_bag(tmp_path / "bad")


def test_topic_with_wrong_type(tmp_path: Path) -> None:
    wrong = playseg_typestore().types["std_msgs/msg/String"](data="not a step")
    write_messages(tmp_path / "bad", [(STEPS_TOPIC, "std_msgs/msg/String", wrong)])
    with pytest.raises(
        BagError,
        match=r"topic '/play/steps': message type is 'std_msgs/msg/String', expected 'playseg_msgs/msg/PlayStep'",
    ):
        read_play_bag(tmp_path / "bad")


def _set_width(msg: object) -> None:
    msg.observation.width = 7


def _set_encoding(msg: object) -> None:
    msg.observation.encoding = "bgr8"


def _cut_data(msg: object) -> None:
    msg.observation.data = msg.observation.data[:-3]


def _other_size(msg: object) -> None:
    msg.observation.height, msg.observation.width, msg.observation.step = 4, 16, 48


@pytest.mark.parametrize(
    ("corrupt", "detail"),
    [
        (_set_width, "observation.step is 24 bytes, expected 21"),
        (_set_encoding, "observation.encoding is 'bgr8', expected 'rgb8'"),
        (_cut_data, "observation.data holds 189 bytes, expected 8 x 24 = 192"),
        (_other_size, "observation is 4x16, expected 8x8"),
    ],
)
def test_frame_of_wrong_size_or_encoding(tmp_path: Path, corrupt, detail: str) -> None:
    messages = step_messages(make_episode(0, 6))
    corrupt(messages[4][2])
    write_messages(tmp_path / "bad", messages)
    with pytest.raises(
        BagError, match=rf"bag '.*bad', topic '/play/steps', episode 'ep-000', step 4: .*{detail}"
    ):
        read_play_bag(tmp_path / "bad")


@pytest.mark.parametrize(
    ("drop", "repeat", "step", "detail"),
    [(3, None, 4, "step gap, expected step 3"), (None, 2, 2, "step repeat, expected step 3")],
)
def test_gap_or_repeat_in_step_numbers(tmp_path: Path, drop, repeat, step: int, detail: str) -> None:
    messages = step_messages(make_episode(0, 6))
    if drop is not None:
        del messages[drop]
    else:
        messages.insert(repeat + 1, messages[repeat])
    write_messages(tmp_path / "bad", messages)
    with pytest.raises(BagError, match=rf"topic '/play/steps', episode 'ep-000', step {step}: {detail}"):
        read_play_bag(tmp_path / "bad")


def test_annotation_outside_its_episode(tmp_path: Path) -> None:
    episode = make_episode(0, 6)
    outside = annotation_message("ep-000", Segment(4, 9, "go to the red ball"), 2000)
    write_messages(tmp_path / "bad", [*step_messages(episode), (ANNOTATIONS_TOPIC, ANNOTATION, outside)])
    with pytest.raises(
        BagError,
        match=r"topic '/play/annotations', episode 'ep-000', step 9: annotation \[4, 9\) ends after the episode's last step 6",
    ):
        read_play_bag(tmp_path / "bad")
    orphan = annotation_message("ep-404", Segment(0, 2, "go to the red ball"), 2000)
    write_messages(tmp_path / "bad2", [*step_messages(episode), (ANNOTATIONS_TOPIC, ANNOTATION, orphan)])
    with pytest.raises(BagError, match=r"episode 'ep-404', step 0: .*no steps in the bag"):
        read_play_bag(tmp_path / "bad2")


def test_reading_a_bad_bag_writes_nothing(tmp_path: Path) -> None:
    messages = step_messages(make_episode(0, 6))
    del messages[2]
    write_messages(tmp_path / "bad", messages)
    before = {p: p.stat().st_mtime_ns for p in tmp_path.rglob("*")}
    with pytest.raises(BagError):
        read_play_bag(tmp_path / "bad")
    assert {p: p.stat().st_mtime_ns for p in tmp_path.rglob("*")} == before


def test_an_aborted_write_leaves_no_bag(tmp_path: Path) -> None:
    def episodes_then_failure():
        yield make_episode(0, 5)
        raise RuntimeError("generator failed")

    with pytest.raises(RuntimeError, match="generator failed"):
        write_play_bag(tmp_path / "aborted", episodes_then_failure(), annotated=True)
    assert list(tmp_path.iterdir()) == []
    write_play_bag(tmp_path / "exists", [make_episode(0, 3)], annotated=True)
    with pytest.raises(FileExistsError):
        write_play_bag(tmp_path / "exists", [make_episode(1, 3)], annotated=True)
    assert len(read_play_bag(tmp_path / "exists")) == 1


def test_cli_bag_info_and_recover(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    write_play_bag(tmp_path / "play", [make_episode(0, 4)], annotated=True)
    assert cli_main(["bag", "info", str(tmp_path / "play")]) == 0
    out = capsys.readouterr().out
    assert "/play/steps  playseg_msgs/msg/PlayStep  5 messages" in out and "compression zstd" in out
    writer = BagWriter(tmp_path / "crashed", chunk_bytes=1)
    writer.add_topic(topic_info(STEPS_TOPIC, PLAY_STEP))
    for msg in episode_messages(make_episode(1, 3), [1, 2, 3, 4]):
        writer.write(STEPS_TOPIC, playseg_typestore().serialize_cdr(msg, PLAY_STEP), stamp_ns(msg.header))
    writer.abandon()  # the writer dies here (its lock would refuse the recovery while it lives)
    assert cli_main(["bag", "recover", str(tmp_path / "crashed")]) == 0
    assert "4 messages" in capsys.readouterr().out
    assert len(read_play_bag(tmp_path / "crashed")) == 1
    assert cli_main(["bag", "info", str(tmp_path / "missing")]) == 1
    assert "no such bag directory" in capsys.readouterr().err


def _bag_cut_inside_the_last_episode(path: Path, episodes: list[Episode], keep_steps: int) -> None:
    """A play bag whose last episode stops after ``keep_steps`` observations, as a recovered recording."""
    with BagWriter(path) as writer:
        writer.add_topic(topic_info(STEPS_TOPIC, PLAY_STEP))
        writer.add_topic(topic_info(GROUND_TRUTH_TOPIC, ANNOTATION))
        store, stamp = playseg_typestore(), 0
        for index, episode in enumerate(episodes):
            messages = list(episode_messages(episode, list(range(stamp, stamp + episode.num_steps + 1))))
            if index == len(episodes) - 1:
                messages = messages[:keep_steps]
            for msg in messages:
                writer.write(STEPS_TOPIC, store.serialize_cdr(msg, PLAY_STEP), stamp)
                stamp += 1
            for segment in episode.segments:
                note = annotation_message(episode.episode_id, segment, stamp)
                writer.write(GROUND_TRUTH_TOPIC, store.serialize_cdr(note, ANNOTATION), stamp)


def test_an_episode_cut_off_by_the_end_of_the_bag_is_an_error_skipped_or_kept(
    tmp_path: Path, episodes: list[Episode]
) -> None:
    last = episodes[2]  # 12 steps, segments ending inside and after the cut
    _bag_cut_inside_the_last_episode(tmp_path / "cut", episodes, keep_steps=8)
    with pytest.raises(
        BagError, match="episode 'ep-002', step 7: the bag ends before this episode's episode_end"
    ):
        read_play_bag(tmp_path / "cut", truth=True)
    told = []
    dropped = list(
        iter_play_bag(
            tmp_path / "cut", truth=True, incomplete="drop", on_incomplete=lambda *a: told.append(a)
        )
    )
    assert [e.episode_id for e in dropped] == ["ep-000", "ep-001"] and told == [("ep-002", 7)]
    kept = read_play_bag(tmp_path / "cut", truth=True, incomplete="keep")
    assert [e.episode_id for e in kept] == ["ep-000", "ep-001", "ep-002"]
    cut = kept[-1]
    assert cut.num_steps == 7  # ends at its last observation, o_7; a_7 led nowhere
    np.testing.assert_array_equal(cut.images[DEFAULT_CAMERA], last.images[DEFAULT_CAMERA][:8])
    np.testing.assert_array_equal(cut.actions, last.actions[:7])
    assert cut.segments == [s for s in last.segments if s.end <= 7]
