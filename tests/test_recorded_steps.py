"""A reference-form LabelledSegment's steps read back from a recorder's bag (recorded_steps.py), while the
bag is still being written and after it is finished: the same clip as the embedded form."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from playseg_core.data.episode import Episode, Segment
from playseg_core.domains.babyai.play import PlayConfig, generate_episode
from playseg_ros.bag import BagWriter, recover_bag, topic_info
from playseg_ros.messages import (
    PLAY_STEP,
    clip_from_labelled,
    episode_messages,
    labelled_segment_of_steps,
    labelled_segment_reference,
)
from playseg_ros.recorded_steps import RecordedSteps, StepsNotRecorded, reference_of
from playseg_ros.typestore import playseg_typestore

TOPIC = "/play/steps"
SECOND = 1_000_000_000


def _steps(episode: Episode, first_stamp: int) -> list:
    stamps = [first_stamp + t * SECOND // 10 for t in range(episode.num_steps + 1)]
    return list(episode_messages(episode, stamps))


def _write(writer: BagWriter, steps: list) -> None:
    for msg in steps:
        writer.write(TOPIC, bytes(playseg_typestore().serialize_cdr(msg, PLAY_STEP)), _time_ns(msg))


def _time_ns(msg) -> int:
    return msg.header.stamp.sec * SECOND + msg.header.stamp.nanosec


def _reference(bag: Path, steps: list, segment: Segment):
    first, last = steps[segment.start], steps[segment.end]
    msg = labelled_segment_reference(
        first.episode_id, segment, "ps", 0, (str(bag), TOPIC), (_time_ns(first), _time_ns(last))
    )
    return msg, reference_of(msg)


def _assert_same_clip(reference_msg, resolved: list, steps: list, segment: Segment) -> None:
    embedded = labelled_segment_of_steps(
        steps[0].episode_id, segment, steps[segment.start : segment.end + 1], "ps", 0
    )
    want, got = clip_from_labelled(embedded), clip_from_labelled(reference_msg, steps=resolved)
    assert (got.episode_id, got.segment, got.source) == (want.episode_id, want.segment, want.source)
    np.testing.assert_array_equal(got.actions, want.actions)
    np.testing.assert_array_equal(got.state, want.state)
    assert list(got.images) == list(want.images)
    for name, frames in want.images.items():
        np.testing.assert_array_equal(got.images[name], frames)


def test_steps_are_read_from_a_recording_in_progress_then_from_the_finished_bag(tmp_path: Path) -> None:
    bag = tmp_path / "recording"
    episode = generate_episode(PlayConfig(), 0)
    steps = _steps(episode, 100 * SECOND)
    segment = Segment(2, episode.num_steps - 1, "go to the red ball", 0.75, -2.0)
    msg, ref = _reference(bag, steps, segment)
    recorded = RecordedSteps(bag, TOPIC)
    with pytest.raises(StepsNotRecorded, match=r"no bag at .*recording \(nor recording.partial\)") as no_bag:
        recorded.steps(ref)
    assert not no_bag.value.recording

    writer = BagWriter(bag, chunk_bytes=1 << 30)  # chunks close only when flushed, as the recorder's
    writer.add_topic(topic_info(TOPIC, PLAY_STEP))
    _write(writer, steps[:5])
    writer.flush()
    _write(writer, steps[5:])  # written, not flushed: not on disk yet
    with pytest.raises(StepsNotRecorded) as not_yet:
        recorded.steps(ref)
    assert not_yet.value.recording
    assert str(not_yet.value) == (
        f"episode {episode.episode_id!r} steps 2..{segment.end} on {TOPIC} in bag {bag}: steps "
        f"5..{segment.end} not recorded yet (the recording in progress, read to its last complete chunk)"
    )
    writer.flush()
    resolved = recorded.steps(ref)  # read on from where the last scan stopped
    assert [int(s.step) for s in resolved] == list(range(segment.start, segment.end + 1))
    _assert_same_clip(msg, resolved, steps, segment)

    writer.close()  # metadata.yaml, and recording.partial renamed to recording
    assert recorded.directory() == bag
    _assert_same_clip(msg, recorded.steps(ref), steps, segment)
    too_far = Segment(segment.start, episode.num_steps + 2, "x")
    _, beyond = _reference(bag, [*steps, steps[-1], steps[-1], steps[-1]], too_far)
    with pytest.raises(StepsNotRecorded, match=r"steps .* not in the bag$") as finished:
        recorded.steps(beyond)
    assert not finished.value.recording


def test_a_replayed_episode_id_is_told_apart_by_the_stamps(tmp_path: Path) -> None:
    """The same episode id recorded twice (a bag replayed, another play with the same id): the reference's
    stamps pick the steps it was cut from."""
    bag = tmp_path / "recording"
    first, second = generate_episode(PlayConfig(), 1), generate_episode(PlayConfig(), 2)
    second.episode_id = first.episode_id
    first_steps, second_steps = _steps(first, 10 * SECOND), _steps(second, 500 * SECOND)
    with BagWriter(bag) as writer:
        writer.add_topic(topic_info(TOPIC, PLAY_STEP))
        _write(writer, first_steps + second_steps)
    segment = Segment(1, 4, "go to the red ball")
    for steps in (first_steps, second_steps):
        msg, ref = _reference(bag, steps, segment)
        _assert_same_clip(msg, RecordedSteps(bag, TOPIC).steps(ref), steps, segment)


def test_a_killed_recording_is_read_up_to_its_last_chunk_and_after_recovery(tmp_path: Path) -> None:
    bag = tmp_path / "recording"
    episode = generate_episode(PlayConfig(), 3)
    steps = _steps(episode, 7 * SECOND)
    writer = BagWriter(bag, chunk_bytes=1 << 30)
    writer.add_topic(topic_info(TOPIC, PLAY_STEP))
    _write(writer, steps)
    writer.flush()
    writer.abandon()  # what a killed recorder leaves: recording.partial, no footer
    with (writer.directory / f"{bag.name}_0.mcap").open("ab") as out:
        out.write(b"\x06\xff\xff\x00")  # the head of a chunk record the crash cut
    segment = Segment(0, 3, "go to the red ball")
    msg, ref = _reference(bag, steps, segment)
    recorded = RecordedSteps(bag, TOPIC)
    _assert_same_clip(msg, recorded.steps(ref), steps, segment)
    recover_bag(bag)  # rewrites the file: read anew from the finished bag
    _assert_same_clip(msg, recorded.steps(ref), steps, segment)


def test_a_chunk_damaged_after_it_was_indexed_is_a_one_line_error_not_a_crash(tmp_path: Path) -> None:
    bag = tmp_path / "recording"
    episode = generate_episode(PlayConfig(), 5)
    steps = _steps(episode, 3 * SECOND)
    with BagWriter(bag) as writer:
        writer.add_topic(topic_info(TOPIC, PLAY_STEP))
        _write(writer, steps)
    segment = Segment(0, 3, "go to the red ball")
    msg, ref = _reference(bag, steps, segment)
    recorded = RecordedSteps(bag, TOPIC)
    recorded.steps(ref)  # indexed
    file = bag / f"{bag.name}_0.mcap"
    data = bytearray(file.read_bytes())
    data[200:400] = bytes(200)  # inside the first chunk's compressed records
    file.write_bytes(bytes(data))  # in place: same inode, the index is kept
    with pytest.raises(
        StepsNotRecorded, match=r"steps 0\.\.3 on /play/steps in bag .*: cannot read: "
    ) as error:
        recorded.steps(ref)
    assert "\n" not in str(error.value) and not error.value.recording
