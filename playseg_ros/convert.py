"""Core Episode/Segment <-> playseg_msgs messages as rosbags typestore dataclasses (no rclpy).

An episode ``(o_0, a_0, ..., o_T)`` is T+1 PlayStep messages with ``step = 0..T``; step t carries the
frame o_t as a ``sensor_msgs/Image`` (rgb8), the state flattened with its shape, and the action a_t
(empty on the last step, which has ``episode_end = true``). Reading validates every field and raises
`StepError` naming the episode and step, so callers can add where the message came from.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from playseg_core.data_model import Episode, Segment, check_segments
from playseg_ros.typestore import playseg_typestore

PLAY_STEP = "playseg_msgs/msg/PlayStep"
ANNOTATION = "playseg_msgs/msg/Annotation"
LABELLED_SEGMENT = "playseg_msgs/msg/LabelledSegment"
RGB8 = "rgb8"


class StepError(ValueError):
    """A message that does not fit its episode; names the episode and step."""

    def __init__(self, episode: str, step: int | None, detail: str) -> None:
        self.episode, self.step, self.detail = episode, step, detail
        where = f"episode {episode!r}" + (f", step {step}" if step is not None else "")
        super().__init__(f"{where}: {detail}")


def _types() -> dict[str, Any]:
    return playseg_typestore().types


def header(stamp_ns: int, frame_id: str) -> Any:
    """A std_msgs/Header with the stamp in nanoseconds since the epoch."""
    types = _types()
    sec, nanosec = divmod(int(stamp_ns), 1_000_000_000)
    return types["std_msgs/msg/Header"](
        stamp=types["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec), frame_id=frame_id
    )


def stamp_ns(msg_header: Any) -> int:
    return int(msg_header.stamp.sec) * 1_000_000_000 + int(msg_header.stamp.nanosec)


def image_message(frame: np.ndarray, msg_header: Any) -> Any:
    """An rgb8 sensor_msgs/Image of an (H, W, 3) uint8 frame."""
    height, width, _ = frame.shape
    return _types()["sensor_msgs/msg/Image"](
        header=msg_header,
        height=height,
        width=width,
        encoding=RGB8,
        is_bigendian=0,
        step=width * 3,
        data=np.ascontiguousarray(frame, dtype=np.uint8).reshape(-1),
    )


def frame_from_image(image: Any) -> np.ndarray:
    """The (H, W, 3) uint8 frame of an rgb8 Image; ValueError for any other encoding or layout."""
    if image.encoding != RGB8:
        raise ValueError(f"observation encoding is {image.encoding!r}, expected {RGB8!r}")
    height, width, row = int(image.height), int(image.width), int(image.step)
    if row != width * 3:
        raise ValueError(f"observation row step is {row} bytes, expected {width * 3} for width {width}")
    data = np.asarray(image.data, dtype=np.uint8)
    if data.size != height * row:
        raise ValueError(f"observation has {data.size} bytes, expected {height} x {row} = {height * row}")
    return data.reshape(height, width, 3)


def play_step_message(
    episode_id: str,
    step: int,
    frame: np.ndarray,
    state: np.ndarray | None,
    action: np.ndarray | None,
    stamp: int,
    frame_id: str = "play",
) -> Any:
    """PlayStep for observation ``step``; ``action`` None marks the episode's last step."""
    msg_header = header(stamp, frame_id)
    flat_state = np.zeros(0, np.float32) if state is None else np.asarray(state, np.float32).reshape(-1)
    shape = np.zeros(0, np.uint32) if state is None else np.asarray(np.shape(state), np.uint32)
    return _types()[PLAY_STEP](
        header=msg_header,
        episode_id=episode_id,
        step=step,
        observation=image_message(frame, msg_header),
        state=flat_state,
        state_shape=shape,
        action=np.zeros(0, np.float32) if action is None else np.asarray(action, np.float32).reshape(-1),
        episode_end=action is None,
    )


def play_step_messages(
    episode_id: str,
    frames: np.ndarray,
    actions: np.ndarray,
    states: np.ndarray | None,
    stamps: Sequence[int],
    first_step: int = 0,
    frame_id: str = "play",
) -> Iterator[Any]:
    """PlayStep messages of ``len(frames)`` observations numbered from ``first_step``.

    ``actions`` holds one action fewer than ``frames``; the last message has no action and
    ``episode_end = true``. ``stamps[i]`` is the stamp of observation i.
    """
    last = len(frames) - 1
    for i in range(last + 1):
        state = None if states is None else states[i]
        action = None if i == last else actions[i]
        yield play_step_message(episode_id, first_step + i, frames[i], state, action, stamps[i], frame_id)


def episode_messages(episode: Episode, stamps: Sequence[int], frame_id: str = "play") -> Iterator[Any]:
    """The T+1 PlayStep messages of an episode."""
    return play_step_messages(
        episode.episode_id, episode.frames, episode.actions, episode.states, stamps, 0, frame_id
    )


def annotation_message(episode_id: str, segment: Segment, stamp: int, frame_id: str = "play") -> Any:
    return _types()[ANNOTATION](
        header=header(stamp, frame_id),
        episode_id=episode_id,
        start_step=segment.start,
        end_step=segment.end,
        instruction=segment.instruction,
    )


def segment_from_annotation(msg: Any) -> Segment:
    """The Segment of an Annotation; StepError when its range is empty or reversed."""
    if not msg.start_step < msg.end_step:
        raise StepError(
            msg.episode_id, int(msg.start_step), f"annotation [{msg.start_step}, {msg.end_step}) is empty"
        )
    return Segment(int(msg.start_step), int(msg.end_step), msg.instruction)


@dataclass
class SegmentClip:
    """A labelled segment with its own data: what a LabelledSegment message carries.

    ``segment`` is in the source episode's step numbering; ``frames`` holds its ``length + 1``
    observations (o_start..o_end), ``actions`` its ``length`` actions, ``states`` matches frames or is None.
    """

    episode_id: str
    segment: Segment
    model_id: str
    frames: np.ndarray
    actions: np.ndarray
    states: np.ndarray | None = None

    @classmethod
    def from_episode(cls, episode: Episode, segment: Segment, model_id: str) -> SegmentClip:
        """The clip of ``segment`` (views into the episode's arrays)."""
        start, end = segment.start, segment.end
        states = None if episode.states is None else episode.states[start : end + 1]
        return cls(
            episode.episode_id,
            segment,
            model_id,
            episode.frames[start : end + 1],
            episode.actions[start:end],
            states,
        )


def labelled_segment_message(
    clip: SegmentClip, stamp: int, step_stamps: Sequence[int] | None = None, frame_id: str = "play"
) -> Any:
    """A self-contained LabelledSegment: the label plus the clip's end - start + 1 PlayStep messages."""
    segment = clip.segment
    stamps = list(step_stamps) if step_stamps is not None else [stamp] * (segment.length + 1)
    steps = play_step_messages(
        clip.episode_id, clip.frames, clip.actions, clip.states, stamps, segment.start, frame_id
    )
    return _types()[LABELLED_SEGMENT](
        header=header(stamp, frame_id),
        episode_id=clip.episode_id,
        start_step=segment.start,
        end_step=segment.end,
        instruction=segment.instruction,
        label_confidence=segment.confidence,
        segment_log_prob=segment.log_prob,
        model_id=clip.model_id,
        steps=list(steps),
    )


def clip_from_labelled(msg: Any) -> SegmentClip:
    """The SegmentClip of a LabelledSegment; StepError naming the episode and step if it is inconsistent."""
    if not msg.start_step < msg.end_step:
        raise StepError(
            msg.episode_id, int(msg.start_step), f"segment [{msg.start_step}, {msg.end_step}) is empty"
        )
    segment = Segment(
        int(msg.start_step),
        int(msg.end_step),
        msg.instruction,
        float(msg.label_confidence),
        float(msg.segment_log_prob),
    )
    builder = EpisodeBuilder(msg.episode_id, first_step=segment.start)
    for step in msg.steps:
        builder.add(step)
    if builder.next_step != segment.end + 1 or not builder.finished:
        raise StepError(
            msg.episode_id,
            builder.next_step - 1,
            f"segment [{segment.start}, {segment.end}) needs steps {segment.start}..{segment.end} "
            f"ending with episode_end, got {len(msg.steps)} steps",
        )
    episode = builder.build()
    return SegmentClip(msg.episode_id, segment, msg.model_id, episode.frames, episode.actions, episode.states)


class EpisodeBuilder:
    """Collects the PlayStep messages of one episode in order and checks each against the first.

    ``first_step`` is the step number the stream must start at (0 for a play stream, ``start_step``
    for the steps inside a LabelledSegment).
    """

    def __init__(self, episode_id: str, first_step: int = 0) -> None:
        self.episode_id = episode_id
        self.first_step = first_step
        self.frames: list[np.ndarray] = []
        self.states: list[np.ndarray] = []
        self.actions: list[np.ndarray] = []
        self.state_shape: tuple[int, ...] | None = None
        self.finished = False

    @property
    def next_step(self) -> int:
        return self.first_step + len(self.frames)

    def add(self, msg: Any) -> None:
        """Append one PlayStep; StepError on a gap, repeat, bad frame/state/action or step after the end."""
        step = int(msg.step)
        if msg.episode_id != self.episode_id:
            raise StepError(self.episode_id, step, f"message of episode {msg.episode_id!r}")
        if self.finished:
            raise StepError(
                self.episode_id, step, f"step after the episode ended at step {self.next_step - 1}"
            )
        if step != self.next_step:
            kind = "repeated" if step < self.next_step else "missing steps before it"
            raise StepError(self.episode_id, step, f"expected step {self.next_step} ({kind})")
        try:
            frame = frame_from_image(msg.observation)
        except ValueError as error:
            raise StepError(self.episode_id, step, str(error)) from None
        if self.frames and frame.shape != self.frames[0].shape:
            raise StepError(
                self.episode_id, step, f"frame is {frame.shape}, earlier frames are {self.frames[0].shape}"
            )
        self._add_state(step, np.asarray(msg.state, np.float32), tuple(int(n) for n in msg.state_shape))
        action = np.asarray(msg.action, np.float32)
        if msg.episode_end:
            if action.size:
                raise StepError(self.episode_id, step, "the last step (episode_end) must have no action")
            self.finished = True
        else:
            if not action.size:
                raise StepError(self.episode_id, step, "empty action on a step that does not end the episode")
            if self.actions and action.shape != self.actions[0].shape:
                raise StepError(
                    self.episode_id,
                    step,
                    f"action has {action.size} values, earlier ones {self.actions[0].size}",
                )
            self.actions.append(action)
        self.frames.append(frame)

    def _add_state(self, step: int, state: np.ndarray, shape: tuple[int, ...]) -> None:
        expected_size = int(np.prod(shape)) if shape else 0
        if state.size != expected_size:
            raise StepError(self.episode_id, step, f"state has {state.size} values but state_shape {shape}")
        if self.state_shape is None:
            self.state_shape = shape
        elif shape != self.state_shape:
            raise StepError(self.episode_id, step, f"state_shape {shape}, earlier steps {self.state_shape}")
        if shape:
            self.states.append(state.reshape(shape))

    def build(self, segments: Sequence[Segment] = ()) -> Episode:
        """The Episode (steps renumbered from 0); StepError if it did not end or a segment does not fit."""
        if not self.finished:
            raise StepError(self.episode_id, self.next_step - 1, "stream ends before episode_end")
        num_steps = len(self.actions)
        try:
            check_segments(segments, num_steps, f"episode {self.episode_id!r}")
        except ValueError as error:
            raise StepError(self.episode_id, None, str(error)) from None
        action_dim = self.actions[0].size if self.actions else 0
        return Episode(
            episode_id=self.episode_id,
            frames=np.stack(self.frames),
            actions=np.stack(self.actions) if self.actions else np.zeros((0, action_dim), np.float32),
            states=np.stack(self.states) if self.states else None,
            segments=list(segments),
        )
