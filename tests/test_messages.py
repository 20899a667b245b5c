"""playseg_msgs on the real stack: DDS between processes, CDR interoperability with rosbags."""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import rclpy
from msg_samples import SAMPLES
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from rclpy.serialization import deserialize_message, serialize_message

from playseg_ros.typestore import playseg_typestore


def _fields(msg) -> dict:
    """Comparable view of an rclpy or rosbags message: nested dicts, arrays as lists."""
    if hasattr(msg, "get_fields_and_field_types"):
        names = list(msg.get_fields_and_field_types())
    else:
        names = [n for n in msg.__dataclass_fields__ if n != "__msgtype__"]
    out = {}
    for name in names:
        value = getattr(msg, name)
        if hasattr(value, "get_fields_and_field_types") or hasattr(value, "__dataclass_fields__"):
            out[name] = _fields(value)
        elif isinstance(value, (list, tuple)) and value and not isinstance(value[0], (int, float)):
            out[name] = [_fields(v) for v in value]
        elif (
            isinstance(value, (bytes, bytearray, np.ndarray, list, tuple)) or type(value).__name__ == "array"
        ):
            out[name] = np.asarray(list(value) if not isinstance(value, np.ndarray) else value).tolist()
        else:
            out[name] = value
    return out


@pytest.mark.parametrize("name", sorted(SAMPLES))
def test_cdr_roundtrip_with_rosbags_typestore(name: str) -> None:
    store = playseg_typestore()
    original = SAMPLES[name]()
    raw = serialize_message(original)
    decoded = store.deserialize_cdr(raw, f"playseg_msgs/msg/{name}")
    assert _fields(decoded) == _fields(original)
    # and back: rosbags' bytes are what rclpy reads
    again = deserialize_message(
        bytes(store.serialize_cdr(decoded, f"playseg_msgs/msg/{name}")), type(original)
    )
    assert _fields(again) == _fields(original)


@pytest.mark.dds
def test_every_message_crosses_processes_over_dds() -> None:
    peer = subprocess.Popen(
        [sys.executable, str(Path(__file__).with_name("ros_publisher_peer.py"))],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    rclpy.init()
    try:
        node = rclpy.create_node("playseg_test_subscriber")
        qos = QoSProfile(
            depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL
        )
        received: dict = {}
        for name, make in SAMPLES.items():
            node.create_subscription(
                type(make()), f"/test_{name}", lambda m, n=name: received.setdefault(n, m), qos
            )
        deadline = time.monotonic() + 30
        while len(received) < len(SAMPLES) and time.monotonic() < deadline and peer.poll() is None:
            rclpy.spin_once(node, timeout_sec=0.1)
        node.destroy_node()
    finally:
        rclpy.shutdown()
        peer.terminate()
        _, err = peer.communicate(timeout=10)
    assert sorted(received) == sorted(SAMPLES), f"missing {set(SAMPLES) - set(received)}; peer stderr: {err}"
    for name, make in SAMPLES.items():
        assert _fields(received[name]) == _fields(make())


@pytest.mark.slow
def test_core_does_not_import_rclpy() -> None:
    code = "import sys, playseg_core, pkgutil, importlib\n"
    code += "for m in pkgutil.walk_packages(playseg_core.__path__, 'playseg_core.'):\n"
    code += "    importlib.import_module(m.name)\n"
    code += "bad = [m for m in sys.modules if m.split('.')[0] in ('rclpy', 'playseg_ros')]\n"
    code += "assert not bad, bad\n"
    subprocess.run([sys.executable, "-c", code], check=True)


def _two_camera_step(kind):
    from playseg_ros.messages import play_step_message

    rng = np.random.default_rng(0)
    frames = {
        "observation.images.front": rng.integers(0, 256, (6, 8, 3), dtype=np.uint8),
        "observation.images.wrist": rng.integers(0, 256, (4, 4, 3), dtype=np.uint8),
    }
    return frames, play_step_message("ep", 0, frames, None, np.ones(2, np.float32), 0, kind=kind)


@pytest.mark.parametrize("kind_name", ["ROSBAGS", "RCLPY"])
def test_a_playstep_carries_every_camera_by_name(kind_name: str) -> None:
    from playseg_ros import messages
    from playseg_ros.messages import StepError, step_from_message

    kind = getattr(messages, kind_name)
    frames, msg = _two_camera_step(kind)
    assert list(msg.camera_names) == list(frames) and len(msg.extra_observations) == 1
    data = step_from_message(msg)
    assert list(data.frames) == list(frames)
    for name, frame in frames.items():
        np.testing.assert_array_equal(data.frames[name], frame)
    with pytest.raises(
        StepError, match=r"camera observation.images.wrist: extra_observations\[0\] is 4x4, expected 5x5"
    ):
        step_from_message(msg, {"observation.images.wrist": (5, 5, 3)})
    _, msg = _two_camera_step(kind)
    msg.camera_names = ["observation.images.front"]
    with pytest.raises(StepError, match="episode 'ep' step 0: camera_names has 1 names for 2 images"):
        step_from_message(msg)
    msg.camera_names = ["observation.images.front", "observation.images.front"]
    with pytest.raises(StepError, match="names must be non-empty and distinct"):
        step_from_message(msg)
    msg.camera_names = []
    with pytest.raises(StepError, match="1 extra_observations but no camera_names"):
        step_from_message(msg)


def test_a_trainer_status_of_the_earlier_definition_is_re_encoded_in_todays() -> None:
    """A bag recorded before TrainerStatus said which evaluation it reports still plays: its messages
    decode as today's, the new figure NaN and its metric empty."""
    import math

    from playseg_ros.typestore import as_current_cdr, earlier_typestores, typestore_for

    name = "playseg_msgs/msg/TrainerStatus"
    old = earlier_typestores()[-1]
    digest = old.hash_rihs01(name)
    assert typestore_for(name, digest) is old and digest != playseg_typestore().hash_rihs01(name)
    time_type, header_type = old.types["builtin_interfaces/msg/Time"], old.types["std_msgs/msg/Header"]
    msg = old.types[name](
        header=header_type(stamp=time_type(sec=1, nanosec=2), frame_id="t"), state="idle", buffer_segments=3,
        buffer_steps=40, policy_version=2, checkpoint_path="p.pt", last_eval_success_rate=0.5,
        last_eval_episodes=8, last_train_loss=0.25, message="m",
    )  # fmt: skip
    data = as_current_cdr(bytes(old.serialize_cdr(msg, name)), name, digest)
    now = playseg_typestore().deserialize_cdr(data, name)
    assert (now.state, now.buffer_segments, now.policy_version, now.last_eval_episodes) == ("idle", 3, 2, 8)
    assert (
        now.last_eval_success_rate == 0.5 and now.last_eval_metric == "" and math.isnan(now.last_eval_value)
    )


def test_a_labelled_segment_of_the_earlier_definition_is_re_encoded_in_todays() -> None:
    """A bag recorded before LabelledSegment had a reference form still reads and plays: its segments
    decode as today's embedded form (steps kept, no recording_bag, zero stamps)."""
    from msg_samples import play_step

    from playseg_ros.typestore import as_current_cdr, earlier_typestores, typestore_for

    name = "playseg_msgs/msg/LabelledSegment"
    old = earlier_typestores()[0]  # today's PlayStep inside the earlier LabelledSegment
    digest = old.hash_rihs01(name)
    assert typestore_for(name, digest) is old and digest != playseg_typestore().hash_rihs01(name)
    step = old.deserialize_cdr(bytes(serialize_message(play_step(4))), "playseg_msgs/msg/PlayStep")
    time_type, header_type = old.types["builtin_interfaces/msg/Time"], old.types["std_msgs/msg/Header"]
    msg = old.types[name](
        header=header_type(stamp=time_type(sec=1, nanosec=2), frame_id="t"), episode_id="ep", start_step=4,
        end_step=5, instruction="go to the red ball", label_confidence=0.5, segment_log_prob=-1.0,
        model_id="m", steps=[step],
    )  # fmt: skip
    now = playseg_typestore().deserialize_cdr(
        as_current_cdr(bytes(old.serialize_cdr(msg, name)), name, digest), name
    )
    assert (now.episode_id, now.start_step, now.end_step, now.model_id) == ("ep", 4, 5, "m")
    assert [s.step for s in now.steps] == [4] and bytes(now.steps[0].observation.data) == bytes(
        step.observation.data
    )
    assert now.recording_bag == "" and now.steps_topic == ""
    assert (now.first_step_stamp.sec, now.last_step_stamp.nanosec) == (0, 0)
