"""Core types <-> playseg_msgs messages, for both kinds of message object.

Bags use rosbags' typestore dataclasses (`ROSBAGS`, no rclpy); the live nodes use the rclpy classes
(`RCLPY`, imported on first use). The builders take the kind to build; the readers use attribute access
only, so they accept either kind, and every field check lives here once.

An episode ``(o_0, a_0, ..., o_T)`` is T+1 PlayStep messages with ``step = 0..T``; step t carries the
camera frames of o_t as ``sensor_msgs/Image`` (rgb8): the first camera's in ``observation`` (0x0 when
the episode has no camera), any further ones in ``extra_observations``, and each frame's feature name
(``observation.images.<camera>``) in ``camera_names``. A message without names (written before
PlayStep carried them, or by a publisher that leaves them out) has one camera, whose name readers take
from the stream's declared features, else `DEFAULT_CAMERA`. It also carries the state flattened with its
shape and the action a_t (empty on the last step, which has ``episode_end = true``). A LabelledSegment
carries the steps start..end of its segment; the last one's action, if any, is the first action after the segment and is
not part of it. Reading raises `StepError` naming the episode, step and field, so callers can add where
the message came from.
"""

from __future__ import annotations

import array
import importlib
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from functools import cache
from typing import Any

import numpy as np

from playseg_core.data.episode import Episode, Segment, SegmentClip, check_segments
from playseg_core.data.features import DEFAULT_CAMERA, STATE
from playseg_core.errors import PlaysegError
from playseg_ros.typestore import playseg_typestore

PLAY_STEP = "playseg_msgs/msg/PlayStep"
ANNOTATION = "playseg_msgs/msg/Annotation"
LABELLED_SEGMENT = "playseg_msgs/msg/LabelledSegment"
RGB8 = "rgb8"


# --- message kinds --------------------------------------------------------------------------------------


@dataclass(frozen=True)
class MessageKind:
    """How to build one kind of message object: its class for a type name and its array fields."""

    name: str
    message_class: Callable[[str], type]
    array: Callable[[np.ndarray, np.dtype], Any]  # a flat array field from values of the field's dtype

    def make(self, type_name: str, **fields: Any) -> Any:
        return self.message_class(type_name)(**fields)


def _typestore_class(type_name: str) -> type:
    return playseg_typestore().types[type_name]


@cache
def _rclpy_class(type_name: str) -> type:
    package, kind, name = type_name.split("/")
    return getattr(importlib.import_module(f"{package}.{kind}"), name)


def _rclpy_array(values: np.ndarray, dtype: np.dtype) -> array.array:
    # rclpy keeps numeric sequences as array.array; built from bytes there is no per-element check.
    return array.array(np.dtype(dtype).char, np.ascontiguousarray(values, dtype).tobytes())


ROSBAGS = MessageKind(
    "rosbags", _typestore_class, lambda values, dtype: np.ascontiguousarray(values, dtype).reshape(-1)
)
RCLPY = MessageKind("rclpy", _rclpy_class, _rclpy_array)


# --- building messages ----------------------------------------------------------------------------------


def time_message(stamp_ns: int, kind: MessageKind = ROSBAGS) -> Any:
    """A builtin_interfaces/Time of nanoseconds since the epoch."""
    sec, nanosec = divmod(int(stamp_ns), 1_000_000_000)
    return kind.make("builtin_interfaces/msg/Time", sec=sec, nanosec=nanosec)


def header(stamp_ns: int, frame_id: str, kind: MessageKind = ROSBAGS) -> Any:
    """A std_msgs/Header with the stamp in nanoseconds since the epoch."""
    return kind.make("std_msgs/msg/Header", stamp=time_message(stamp_ns, kind), frame_id=frame_id)


def time_ns(time: Any) -> int:
    """Nanoseconds since the epoch of a builtin_interfaces/Time."""
    return int(time.sec) * 1_000_000_000 + int(time.nanosec)


def stamp_ns(msg_header: Any) -> int:
    return time_ns(msg_header.stamp)


def image_message(frame: np.ndarray | None, msg_header: Any, kind: MessageKind = ROSBAGS) -> Any:
    """An rgb8 sensor_msgs/Image of an (H, W, 3) uint8 frame (None: an empty 0x0 image, no camera)."""
    frame = np.zeros((0, 0, 3), np.uint8) if frame is None else frame
    height, width, _ = frame.shape
    return kind.make(
        "sensor_msgs/msg/Image",
        header=msg_header,
        height=height,
        width=width,
        encoding=RGB8,
        is_bigendian=0,
        step=width * 3,
        data=kind.array(frame, np.uint8),
    )


def play_step_message(
    episode_id: str,
    step: int,
    frames: Mapping[str, np.ndarray],
    state: np.ndarray | None,
    action: np.ndarray | None,
    stamp: int,
    frame_id: str = "play",
    kind: MessageKind = ROSBAGS,
) -> Any:
    """PlayStep for observation ``step``: ``frames`` maps each camera's feature name to its (H, W, 3)
    frame (none: no camera); ``action`` None marks the episode's last step."""
    msg_header = header(stamp, frame_id, kind)
    no_values = np.zeros(0)
    names = list(frames)
    images = [image_message(frames[name], msg_header, kind) for name in names]
    return kind.make(
        PLAY_STEP,
        header=msg_header,
        episode_id=episode_id,
        step=step,
        observation=images[0] if images else image_message(None, msg_header, kind),
        state=kind.array(no_values if state is None else state, np.float32),
        state_shape=kind.array(no_values if state is None else np.shape(state), np.uint32),
        action=kind.array(no_values if action is None else action, np.float32),
        episode_end=action is None,
        camera_names=names,
        extra_observations=images[1:],
    )


def play_step_messages(
    episode_id: str,
    images: dict[str, np.ndarray],
    actions: np.ndarray,
    state: np.ndarray | None,
    stamps: Sequence[int],
    first_step: int = 0,
    frame_id: str = "play",
    kind: MessageKind = ROSBAGS,
) -> Iterator[Any]:
    """PlayStep messages of ``len(actions) + 1`` observations numbered from ``first_step``.

    The last message has no action and ``episode_end = true``. ``stamps[i]`` is the stamp of observation i.
    """
    last = len(actions)
    for i in range(last + 1):
        yield play_step_message(
            episode_id,
            first_step + i,
            {name: frames[i] for name, frames in images.items()},
            None if state is None else state[i],
            None if i == last else actions[i],
            stamps[i],
            frame_id,
            kind,
        )


def episode_messages(
    episode: Episode, stamps: Sequence[int], frame_id: str = "play", kind: MessageKind = ROSBAGS
) -> Iterator[Any]:
    """The T+1 PlayStep messages of an episode."""
    return play_step_messages(
        episode.episode_id, episode.images, episode.actions, episode.state, stamps, 0, frame_id, kind
    )


def episode_step_message(
    episode: Episode, t: int, stamp: int = 0, frame_id: str = "play", kind: MessageKind = ROSBAGS
) -> Any:
    """Step t of an episode as a PlayStep (the last step, t = T, carries episode_end and no action)."""
    frames = {name: images[t] for name, images in episode.images.items()}
    state = None if episode.state is None else episode.state[t]
    action = None if t == episode.num_steps else episode.actions[t]
    return play_step_message(episode.episode_id, t, frames, state, action, stamp, frame_id, kind)


def annotation_message(
    episode_id: str, segment: Segment, stamp: int, frame_id: str = "play", kind: MessageKind = ROSBAGS
) -> Any:
    return kind.make(
        ANNOTATION,
        header=header(stamp, frame_id, kind),
        episode_id=episode_id,
        start_step=segment.start,
        end_step=segment.end,
        instruction=segment.instruction,
    )


def labelled_segment_message(
    clip: SegmentClip,
    stamp: int,
    step_stamps: Sequence[int] | None = None,
    frame_id: str = "play",
    kind: MessageKind = ROSBAGS,
) -> Any:
    """A self-contained LabelledSegment of a clip: its end - start + 1 PlaySteps, the last one without
    action and with episode_end (the clip ends there)."""
    segment = clip.segment
    stamps = list(step_stamps) if step_stamps is not None else [stamp] * (segment.length + 1)
    steps = play_step_messages(
        clip.episode_id, clip.images, clip.actions, clip.state, stamps, segment.start, frame_id, kind
    )
    return labelled_segment_of_steps(
        clip.episode_id, segment, list(steps), clip.source, stamp, frame_id, kind
    )


def labelled_segment_of_steps(
    episode_id: str,
    segment: Segment,
    steps: list[Any],
    model_id: str,
    stamp: int,
    frame_id: str = "play",
    kind: MessageKind = ROSBAGS,
) -> Any:
    """A LabelledSegment carrying ``steps``, the PlayStep messages start..end (end inclusive)."""
    if len(steps) != segment.length + 1:
        raise PlaysegError(
            f"segment [{segment.start}, {segment.end}) needs {segment.length + 1} steps, got {len(steps)}"
        )
    return _labelled_segment(episode_id, segment, model_id, stamp, frame_id, kind, steps=steps)


def labelled_segment_reference(
    episode_id: str,
    segment: Segment,
    model_id: str,
    stamp: int,
    recording: tuple[str, str],
    step_stamps: tuple[int, int],
    frame_id: str = "play",
    kind: MessageKind = ROSBAGS,
) -> Any:
    """A reference-form LabelledSegment: no steps; ``recording`` (bag directory, PlayStep topic) holds
    them, ``step_stamps`` are the header stamps of steps start and end."""
    bag, topic = recording
    if not bag or not topic:
        raise PlaysegError(f"a reference needs a bag and a topic, got {recording}")
    return _labelled_segment(
        episode_id, segment, model_id, stamp, frame_id, kind, recording_bag=bag, steps_topic=topic,
        first_step_stamp=time_message(step_stamps[0], kind), last_step_stamp=time_message(step_stamps[1], kind),
    )  # fmt: skip


def _labelled_segment(
    episode_id: str,
    segment: Segment,
    model_id: str,
    stamp: int,
    frame_id: str,
    kind: MessageKind,
    **form: Any,
) -> Any:
    return kind.make(
        LABELLED_SEGMENT,
        header=header(stamp, frame_id, kind),
        episode_id=episode_id,
        start_step=segment.start,
        end_step=segment.end,
        instruction=segment.instruction,
        label_confidence=float(segment.confidence),
        segment_log_prob=float(segment.log_prob),
        model_id=model_id,
        **{  # every field, as rosbags' classes need them all: the other form's empty
            "steps": [], "recording_bag": "", "steps_topic": "", "first_step_stamp": time_message(0, kind),
            "last_step_stamp": time_message(0, kind), **form,
        },
    )  # fmt: skip


# --- reading messages (either kind) ---------------------------------------------------------------------


class StepError(PlaysegError):
    """A message that cannot be used; names the episode, step and field."""

    def __init__(self, episode: str, step: int | None, detail: str) -> None:
        self.episode, self.step, self.detail = episode, step, detail
        where = f"episode {episode!r}" + (f" step {step}" if step is not None else "")
        super().__init__(f"{where}: {detail}")


@dataclass
class StepData:
    """The content of one PlayStep as arrays."""

    episode_id: str
    step: int
    frames: dict[str, np.ndarray]  # camera feature name -> (H, W, 3) uint8; "" for an unnamed single camera
    state: np.ndarray | None  # float32, shaped by state_shape
    action: np.ndarray | None  # float32 (action_dim,); None on the final step (episode_end)
    episode_end: bool

    def named_frames(self, camera: str = DEFAULT_CAMERA) -> dict[str, np.ndarray]:
        """The frames by feature name, an unnamed single camera's as feature ``camera``."""
        return {name or camera: frame for name, frame in self.frames.items()}

    def observation(self, camera: str = DEFAULT_CAMERA) -> dict[str, np.ndarray]:
        """The observation by feature name (an unnamed single camera's frame as feature ``camera``)."""
        observation = self.named_frames(camera)
        if self.state is not None:
            observation[STATE] = self.state
        return observation


def _values(field: Any, dtype: type) -> np.ndarray:
    """A numeric sequence field (numpy array, array.array, bytes or list) as a flat numpy array."""
    if isinstance(field, (bytes, bytearray, memoryview)):
        return np.frombuffer(field, dtype)
    return np.asarray(field, dtype).reshape(-1)


def frame_from_image(
    image: Any, frame_shape: tuple[int, ...] | None = None, field: str = "observation"
) -> np.ndarray | None:
    """The (H, W, 3) uint8 frame of an rgb8 Image, None for an empty one; ValueError naming the field
    for anything else.

    ``frame_shape`` (H, W, 3), when given, is enforced (earlier frames, or what a model takes).
    """
    if int(image.height) == 0 and int(image.width) == 0 and not len(image.data):
        if frame_shape is not None:
            raise PlaysegError(f"{field} is empty, expected {frame_shape[0]}x{frame_shape[1]}")
        return None
    if image.encoding != RGB8:
        raise PlaysegError(f"{field}.encoding is {image.encoding!r}, expected {RGB8!r}")
    height, width, row = int(image.height), int(image.width), int(image.step)
    if row != width * 3:
        raise PlaysegError(f"{field}.step is {row} bytes, expected {width * 3} for width {width}")
    data = _values(image.data, np.uint8)
    if data.size != height * row:
        raise PlaysegError(
            f"{field}.data holds {data.size} bytes, expected {height} x {row} = {height * row}"
        )
    if frame_shape is not None and (height, width, 3) != tuple(frame_shape):
        raise PlaysegError(f"{field} is {height}x{width}, expected {frame_shape[0]}x{frame_shape[1]}")
    return data.reshape(height, width, 3)


def _frames(msg: Any, frame_shapes: Mapping[str, tuple[int, ...]] | None) -> dict[str, np.ndarray]:
    """The step's frames by camera name ("" for an unnamed single camera); ``frame_shapes`` (by name,
    "" for the unnamed one) enforced where given."""
    names = [str(name) for name in getattr(msg, "camera_names", ())]
    images = [msg.observation, *getattr(msg, "extra_observations", ())]
    if not names:
        if len(images) > 1:
            raise PlaysegError(f"{len(images) - 1} extra_observations but no camera_names")
        names = [""]
    elif len(names) != len(images):
        raise PlaysegError(f"camera_names has {len(names)} names for {len(images)} images")
    elif "" in names or len(set(names)) != len(names):
        raise PlaysegError(f"camera_names {names}: names must be non-empty and distinct")
    shapes = frame_shapes or {}
    frames = {}
    for index, (name, image) in enumerate(zip(names, images, strict=True)):
        field = "observation" if index == 0 else f"extra_observations[{index - 1}]"
        try:
            frame = frame_from_image(image, shapes.get(name), field)
        except ValueError as error:
            if len(names) > 1:  # say which camera
                raise PlaysegError(f"camera {name}: {error}") from None
            raise
        if frame is not None:
            frames[name] = frame
    return frames


def _state(msg: Any) -> np.ndarray | None:
    state = _values(msg.state, np.float32)
    shape = tuple(int(n) for n in msg.state_shape)
    if not shape:
        if not state.size:
            return None
        shape = (state.size,)  # a flat state published without its shape
    if int(np.prod(shape)) != state.size:
        raise PlaysegError(f"state has {state.size} values, state_shape {shape}")
    return state.reshape(shape)


def _action(msg: Any) -> np.ndarray | None:
    action = _values(msg.action, np.float32)
    if msg.episode_end:
        if action.size:
            raise PlaysegError("action is not empty on the episode_end step (the last observation has none)")
        return None
    if not action.size:
        raise PlaysegError("action is empty but episode_end is false")
    if not np.all(np.isfinite(action)):
        raise PlaysegError(f"action contains NaN or inf: {action.tolist()}")
    return action


def step_from_message(msg: Any, frame_shapes: Mapping[str, tuple[int, ...]] | None = None) -> StepData:
    """Validate and unpack one PlayStep on its own; StepError naming the episode, step and field.

    ``frame_shapes`` maps camera names ("" for an unnamed single camera) to the (H, W, 3) they must have.
    """
    step = int(msg.step)
    try:
        frames = _frames(msg, frame_shapes)
        state, action = _state(msg), _action(msg)
    except ValueError as error:
        raise StepError(msg.episode_id, step, str(error)) from None
    return StepData(msg.episode_id, step, frames, state, action, bool(msg.episode_end))


def check_step_number(episode_id: str, step: int, expected: int) -> None:
    """StepError unless ``step`` is the ``expected`` next step of the episode."""
    if step != expected:
        kind = "repeat" if step < expected else "gap"
        raise StepError(episode_id, step, f"step {kind}, expected step {expected}")


def segment_from_annotation(msg: Any) -> Segment:
    """The Segment of an Annotation; StepError when its range is empty or reversed."""
    if not msg.start_step < msg.end_step:
        raise StepError(
            msg.episode_id, int(msg.start_step), f"annotation [{msg.start_step}, {msg.end_step}) is empty"
        )
    return Segment(int(msg.start_step), int(msg.end_step), msg.instruction)


def is_reference(msg: Any) -> bool:
    """Whether a LabelledSegment is of the reference form (its steps are in a recording)."""
    return bool(getattr(msg, "recording_bag", ""))  # earlier definitions have only the embedded form


def clip_from_labelled(
    msg: Any, camera: str = DEFAULT_CAMERA, steps: Sequence[Any] | None = None
) -> SegmentClip:
    """The SegmentClip of a LabelledSegment (every step validated; an unnamed single camera's image as
    feature ``camera``); StepError naming episode and step. ``steps``: the PlaySteps of a reference-form
    segment, read from its recording (recorded_steps.py); None: the ones it embeds."""
    episode_id, start, end = msg.episode_id, int(msg.start_step), int(msg.end_step)
    if steps is None and is_reference(msg):
        raise StepError(
            episode_id,
            start,
            f"a reference-form segment: its steps are in bag {msg.recording_bag} on {msg.steps_topic}, "
            "not in the message",
        )
    steps = msg.steps if steps is None else steps
    if not start < end:
        raise StepError(episode_id, start, f"segment [{start}, {end}) is empty")
    if len(steps) != end - start + 1:
        raise StepError(
            episode_id,
            start,
            f"segment [{start}, {end}) needs steps {start}..{end}, got {len(steps)} steps",
        )
    segment = Segment(start, end, msg.instruction, float(msg.label_confidence), float(msg.segment_log_prob))
    builder = EpisodeBuilder(episode_id, first_step=start, camera=camera)
    for step in steps:
        builder.add(step)
    return SegmentClip(
        episode_id=episode_id,
        segment=segment,
        actions=np.stack(builder.actions[: segment.length]),
        images=builder.images(),
        state=np.stack(builder.states) if builder.states else None,
        source=msg.model_id,
    )


class EpisodeBuilder:
    """Collects the PlayStep messages of one episode in order and checks each against the first.

    ``first_step`` is the step number the stream must start at (0 for a play stream, ``start_step``
    for the steps inside a LabelledSegment); an unnamed single camera's image becomes feature ``camera``.
    """

    def __init__(self, episode_id: str, first_step: int = 0, camera: str = DEFAULT_CAMERA) -> None:
        self.episode_id = episode_id
        self.first_step = first_step
        self.camera = camera
        self.num_observations = 0
        self.frame_shapes: dict[str, tuple[int, ...]] | None = None  # by camera name, from the first step
        self.frames: dict[str, list[np.ndarray]] = {}
        self.states: list[np.ndarray] = []
        self.actions: list[np.ndarray] = []
        self.state_shape: tuple[int, ...] | None = None
        self.stamps: list[int] = []  # each observation's header stamp, ns
        self.finished = False

    @property
    def next_step(self) -> int:
        return self.first_step + self.num_observations

    def images(self) -> dict[str, np.ndarray]:
        return {name or self.camera: np.stack(frames) for name, frames in self.frames.items()}

    def add(self, msg: Any) -> StepData:
        """Append one PlayStep; StepError on a gap, repeat, bad field, change of shape or step after the end."""
        step = int(msg.step)
        if msg.episode_id != self.episode_id:
            raise StepError(self.episode_id, step, f"message of episode {msg.episode_id!r}")
        if self.finished:
            raise StepError(
                self.episode_id, step, f"step after the episode ended at step {self.next_step - 1}"
            )
        check_step_number(self.episode_id, step, self.next_step)
        data = step_from_message(msg, self.frame_shapes)
        frame_shapes = {name: frame.shape for name, frame in data.frames.items()}
        if self.num_observations and frame_shapes != self.frame_shapes:
            raise StepError(
                self.episode_id, step, f"images {frame_shapes}, earlier steps {self.frame_shapes}"
            )
        state_shape = None if data.state is None else data.state.shape
        if self.num_observations and state_shape != self.state_shape:
            raise StepError(
                self.episode_id, step, f"state_shape {state_shape}, earlier steps {self.state_shape}"
            )
        if data.action is not None and self.actions and data.action.size != self.actions[0].size:
            raise StepError(
                self.episode_id,
                step,
                f"action has {data.action.size} values, earlier steps {self.actions[0].size}",
            )
        self.state_shape, self.frame_shapes = state_shape, frame_shapes
        self.num_observations += 1
        self.stamps.append(stamp_ns(msg.header))
        for name, frame in data.frames.items():
            self.frames.setdefault(name, []).append(frame)
        if data.state is not None:
            self.states.append(data.state)
        if data.action is not None:
            self.actions.append(data.action)
        self.finished = data.episode_end
        return data

    def build(self, segments: Sequence[Segment] = (), truncated: bool = False) -> Episode:
        """The Episode (steps renumbered from 0); StepError if it did not end or a segment does not fit.

        ``truncated``: the stream stopped before ``episode_end`` (a recovered recording); the episode ends
        at the last observation received (its action, which led nowhere, is dropped).
        """
        if not self.finished and not truncated:
            raise StepError(self.episode_id, self.next_step - 1, "stream ends before episode_end")
        if not self.finished:
            self.actions = self.actions[: self.num_observations - 1]
        num_steps = len(self.actions)
        try:
            check_segments(segments, num_steps, f"episode {self.episode_id!r}")
        except ValueError as error:
            raise StepError(self.episode_id, None, str(error)) from None
        action_dim = self.actions[0].size if self.actions else 0
        return Episode(
            episode_id=self.episode_id,
            actions=np.stack(self.actions) if self.actions else np.zeros((0, action_dim), np.float32),
            images=self.images(),
            state=np.stack(self.states) if self.states else None,
            segments=list(segments),
        )
