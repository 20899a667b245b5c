"""rclpy messages <-> core types for the live nodes, with the checks a malformed PlayStep must fail.

(The bag side converts rosbags' message dataclasses in `playseg_ros.convert`; the field layout is the same
playseg_msgs definition.)
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from builtin_interfaces.msg import Time
from playseg_msgs.msg import LabelledSegment, PlayStep

from playseg_core.augmentation_buffer import BufferedSegment
from playseg_core.data_model import Episode, Segment


@dataclass
class StepData:
    """The content of one PlayStep as arrays."""

    episode_id: str
    step: int
    frame: np.ndarray  # (H, W, 3) uint8
    state: np.ndarray | None
    action: np.ndarray | None  # None on the final step (episode_end)
    episode_end: bool


class MalformedStep(ValueError):
    """A PlayStep that cannot be used; the message names the episode, step and field."""


def step_from_msg(msg: PlayStep, frame_shape: tuple[int, int, int] | None = None) -> StepData:
    """Validate and unpack a PlayStep. `frame_shape` (H, W, 3), when given, is enforced."""
    where = f"episode {msg.episode_id!r} step {msg.step}"
    image = msg.observation
    if image.encoding != "rgb8":
        raise MalformedStep(f"{where}: observation.encoding is {image.encoding!r}, expected 'rgb8'")
    h, w = int(image.height), int(image.width)
    if frame_shape is not None and (h, w, 3) != tuple(frame_shape):
        raise MalformedStep(f"{where}: observation is {h}x{w}, expected {frame_shape[0]}x{frame_shape[1]}")
    if image.step != w * 3 or len(image.data) != h * w * 3:
        raise MalformedStep(
            f"{where}: observation.data holds {len(image.data)} bytes (step {image.step}), expected {h * w * 3}"
        )
    frame = np.frombuffer(bytes(image.data), np.uint8).reshape(h, w, 3)
    state = None
    if len(msg.state):
        shape = tuple(int(s) for s in msg.state_shape) or (len(msg.state),)
        if math.prod(shape) != len(msg.state):
            raise MalformedStep(f"{where}: state has {len(msg.state)} values, state_shape {shape}")
        state = np.asarray(msg.state, np.float32).reshape(shape)
    action = None
    if not msg.episode_end:
        action = np.asarray(msg.action, np.float32)
        if action.size == 0:
            raise MalformedStep(f"{where}: action is empty but episode_end is false")
        if not np.all(np.isfinite(action)):
            raise MalformedStep(f"{where}: action contains NaN or inf: {action.tolist()}")
    return StepData(msg.episode_id, int(msg.step), frame, state, action, bool(msg.episode_end))


def play_step_msg(episode: Episode, t: int, stamp: Time | None = None, frame_id: str = "") -> PlayStep:
    """Step t of an episode as a PlayStep (the last step, t = T, carries episode_end and no action)."""
    msg = PlayStep()
    if stamp is not None:
        msg.header.stamp = stamp
    msg.header.frame_id = frame_id
    msg.episode_id = episode.episode_id
    msg.step = t
    frame = np.ascontiguousarray(episode.frames[t])
    image = msg.observation
    image.header = msg.header
    image.height, image.width = int(frame.shape[0]), int(frame.shape[1])
    image.encoding, image.step = "rgb8", int(frame.shape[1]) * 3
    image.data = frame.tobytes()
    if episode.states is not None:
        state = np.asarray(episode.states[t], np.float32)
        msg.state = state.ravel().tolist()
        msg.state_shape = list(state.shape)
    msg.episode_end = t == episode.num_steps
    msg.action = [] if msg.episode_end else np.asarray(episode.actions[t], np.float32).tolist()
    return msg


def labelled_segment_msg(
    segment: Segment, steps: list[PlayStep], model_id: str, stamp: Time | None = None
) -> LabelledSegment:
    """A self-contained LabelledSegment: `steps` are the PlaySteps start..end (end inclusive)."""
    if len(steps) != segment.length + 1:
        raise ValueError(
            f"segment [{segment.start}, {segment.end}) needs {segment.length + 1} steps, got {len(steps)}"
        )
    msg = LabelledSegment()
    if stamp is not None:
        msg.header.stamp = stamp
    msg.episode_id = steps[0].episode_id
    msg.start_step, msg.end_step = segment.start, segment.end
    msg.instruction = segment.instruction
    msg.label_confidence = float(segment.confidence)
    msg.segment_log_prob = float(segment.log_prob)
    msg.model_id = model_id
    msg.steps = steps
    return msg


def buffered_segment_from_msg(msg: LabelledSegment) -> BufferedSegment:
    """Unpack a LabelledSegment (validating every step) into the trainer's buffer record."""
    where = f"LabelledSegment {msg.episode_id!r} [{msg.start_step}, {msg.end_step})"
    if msg.end_step <= msg.start_step:
        raise ValueError(f"{where}: end_step must be after start_step")
    if len(msg.steps) != msg.end_step - msg.start_step + 1:
        raise ValueError(
            f"{where}: holds {len(msg.steps)} steps, expected {msg.end_step - msg.start_step + 1}"
        )
    steps = []
    for offset, step_msg in enumerate(msg.steps):
        if step_msg.step != msg.start_step + offset:
            raise ValueError(
                f"{where}: steps[{offset}].step is {step_msg.step}, expected {msg.start_step + offset}"
            )
        data = step_from_msg(step_msg, steps[0].frame.shape if steps else None)
        if offset < len(msg.steps) - 1 and data.action is None:
            raise ValueError(f"{where}: step {data.step} has no action but is not the segment's last")
        if steps:
            _check_like_first(where, data, steps[0])
        steps.append(data)
    states = None if steps[0].state is None else np.stack([s.state for s in steps])
    return BufferedSegment(
        episode_id=msg.episode_id,
        start=int(msg.start_step),
        end=int(msg.end_step),
        instruction=msg.instruction,
        actions=np.stack([s.action for s in steps[:-1]]),
        states=states,
        frames=np.stack([s.frame for s in steps]),
        confidence=float(msg.label_confidence),
        log_prob=float(msg.segment_log_prob),
        source=msg.model_id,
    )


def _check_like_first(where: str, data: StepData, first: StepData) -> None:
    """Every step of a segment has the state shape and action size of its first step."""
    first_state = None if first.state is None else first.state.shape
    state = None if data.state is None else data.state.shape
    if state != first_state:
        raise ValueError(
            f"{where}: step {data.step} has state shape {state}, step {first.step} {first_state}"
        )
    if data.action is not None and first.action is not None and data.action.shape != first.action.shape:
        raise ValueError(
            f"{where}: step {data.step} has {data.action.size} action values, step {first.step} "
            f"{first.action.size}"
        )
