"""One filled instance of every playseg_msgs message, shared by the message tests and their peer process."""

from __future__ import annotations

import numpy as np
from playseg_msgs.msg import Annotation, LabelledSegment, PlayStep, TrainerStatus
from sensor_msgs.msg import Image


def play_step(step: int = 3, episode_end: bool = False) -> PlayStep:
    rng = np.random.default_rng(step)
    msg = PlayStep()
    msg.header.stamp.sec = 1700000000 + step
    msg.header.stamp.nanosec = 250_000_000
    msg.header.frame_id = "babyai"
    msg.episode_id = "ep-000042"
    msg.step = step
    image = Image()
    image.header = msg.header
    image.height, image.width, image.encoding = 4, 5, "rgb8"
    image.step = 5 * 3
    image.data = rng.integers(0, 256, size=4 * 5 * 3, dtype=np.uint8).tobytes()
    msg.observation = image
    msg.state = rng.random(6, dtype=np.float32).tolist()
    msg.state_shape = [2, 3]
    msg.action = [] if episode_end else [float(step % 7)]
    msg.episode_end = episode_end
    return msg


def annotation() -> Annotation:
    msg = Annotation()
    msg.header.stamp.sec = 12
    msg.episode_id = "ep-000042"
    msg.start_step, msg.end_step = 3, 9
    msg.instruction = "go to the red ball"
    return msg


def labelled_segment() -> LabelledSegment:
    msg = LabelledSegment()
    msg.header.stamp.sec = 13
    msg.episode_id = "ep-000042"
    msg.start_step, msg.end_step = 3, 5
    msg.instruction = "go to a grey key"
    msg.label_confidence = 0.875
    msg.segment_log_prob = -1.5
    msg.model_id = "ps-test"
    msg.steps = [play_step(3), play_step(4), play_step(5, episode_end=True)]
    return msg


def trainer_status() -> TrainerStatus:
    msg = TrainerStatus()
    msg.header.stamp.sec = 14
    msg.state = "idle"
    msg.buffer_segments = 1234
    msg.buffer_steps = 98765
    msg.policy_version = 3
    msg.checkpoint_path = "/tmp/policy-v3.pt"
    msg.last_eval_success_rate = 0.75
    msg.last_eval_episodes = 512
    msg.last_train_loss = 0.125
    msg.message = "ok"
    return msg


SAMPLES = {
    "PlayStep": play_step,
    "Annotation": annotation,
    "LabelledSegment": labelled_segment,
    "TrainerStatus": trainer_status,
}
