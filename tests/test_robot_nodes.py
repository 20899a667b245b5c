"""Robot-shaped play (two 96x128 cameras, a 7-D state, 7-D continuous actions) through the segmenter and the
trainer (generic `bc` policy) as real processes on real DDS; both nodes through every lifecycle transition
in every state, answering their services."""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
import torch
from lifecycle_msgs.msg import State, Transition
from lifecycle_msgs.srv import ChangeState, GetAvailableTransitions, GetState
from node_procs import Processes, RosPeer, stop, wait_for_log
from playseg_msgs.msg import LabelledSegment, PlayStep, TrainerStatus
from playseg_msgs.srv import EvaluatePolicy, Retrain, SaveBuffer
from test_robot_segmentation import FRONT, INSTRUCTIONS, WRIST, robot_episode, robot_features

from playseg_core.augment.buffer import AugmentationBuffer
from playseg_core.ps.model import PSModel, load_model, save_model
from playseg_core.ps.segmentation import segment_episode
from playseg_core.ps.training import model_config_for, segment_bounds
from playseg_ros import qos
from playseg_ros.messages import RCLPY, episode_step_message
from playseg_ros.play_bags import DataInfo, write_play_bag

Check = Callable[[object], bool]
FEATURES = robot_features({FRONT: (96, 128), WRIST: (96, 128)}, state=True)


def _robot_model(path: Path, episodes: list) -> Path:
    """An untrained PS model over the robot features (it cuts arbitrarily, which is all equality needs)."""
    torch.manual_seed(0)
    bounds = segment_bounds(episodes)
    config = model_config_for(
        FEATURES, None, len(INSTRUCTIONS), max_len=bounds.max_len, episodes=episodes, min_len=bounds.min_len
    )
    save_model(path, PSModel(config, list(INSTRUCTIONS)))
    return path


def _call(peer: RosPeer, srv_type: type, name: str, request: object, timeout: float = 60.0) -> object:
    """One service call through a new client, given half a second after the service shows up: Fast DDS
    drops a server's response ("failed to send response (timeout)") while the client's response reader
    is not matched yet, which a starved CPU can stretch past the server's wait."""
    client = peer.node.create_client(srv_type, name)
    try:
        assert client.wait_for_service(timeout_sec=15), f"{name} not offered"
        peer.spin_until(lambda: False, 0.5)
        future = client.call_async(request)
        assert peer.spin_until(future.done, timeout), f"no answer from {name}"
        return future.result()
    finally:
        peer.node.destroy_client(client)


def test_robot_play_goes_through_the_segmenter_and_a_bc_trainer_over_dds(
    procs: Processes, peer: RosPeer, tmp_path: Path
) -> None:
    annotated = [robot_episode(seed, FEATURES, "action", lengths=(10, 20)) for seed in range(3)]
    play = robot_episode(10, FEATURES, "action", lengths=(10, 20))
    info = DataInfo(FEATURES, None, INSTRUCTIONS)
    base = tmp_path / "annotated"
    write_play_bag(base, annotated, annotated=True, info=info)
    model_path = _robot_model(tmp_path / "ps.pt", annotated)

    segments: list[LabelledSegment] = []
    statuses: list[TrainerStatus] = []
    peer.node.create_subscription(LabelledSegment, "/segments", segments.append, qos.SEGMENTS)
    peer.node.create_subscription(TrainerStatus, "/trainer/status", statuses.append, qos.STATUS)
    steps_pub = peer.node.create_publisher(PlayStep, "/play/steps", qos.PLAY_STEPS)
    segmenter, segmenter_log = procs.node("segmenter", "segmenter", model=str(model_path))
    trainer, trainer_log = procs.node(
        "trainer", "trainer", policy="bc", base_data=str(base), buffer_dir=str(tmp_path / "buffer"),
        checkpoint_dir=str(tmp_path / "checkpoints"), train_steps=30, batch_size=16, status_period_s=0.2,
    )  # fmt: skip
    assert peer.spin_until(lambda: steps_pub.get_subscription_count() >= 1, 60), segmenter_log.read_text()
    wait_for_log(trainer_log, r"annotated segments", 60, trainer)
    # /segments is volatile: the segmenter's writer must have matched the trainer's reader and ours before
    # the first segment, or that reader never sees it; the segmenter logs each change in its matched readers.
    wait_for_log(segmenter_log, r"/segments: [2-9]\d* subscriber\(s\) matched", 60, segmenter)

    for t in range(play.num_steps + 1):
        steps_pub.publish(episode_step_message(play, t, kind=RCLPY))
    # The segmenter's segments reach the trainer too (both subscribe to /segments).
    reaches_end = lambda: any(s.end_step == play.num_steps for s in segments)  # noqa: E731
    assert peer.spin_until(reaches_end, 90), segmenter_log.read_text()[-3000:]
    model, _ = load_model(model_path)
    offline = segment_episode(model, play, min_len=model.cfg.min_len)  # the node uses the model's L_min
    assert [(s.start_step, s.end_step, s.instruction) for s in segments] == [
        (s.start, s.end, s.instruction) for s in offline
    ]
    last = segments[-1].steps[-1]
    assert list(last.camera_names) == [FRONT, WRIST]
    for image, camera in zip([last.observation, *last.extra_observations], (FRONT, WRIST), strict=True):
        frame = np.frombuffer(bytes(image.data), np.uint8).reshape(96, 128, 3)
        np.testing.assert_array_equal(frame, play.images[camera][-1])
    np.testing.assert_array_equal(np.asarray(last.state), play.state[-1])
    np.testing.assert_array_equal(np.asarray(segments[0].steps[0].action), play.actions[0])

    acknowledged = lambda: statuses and statuses[-1].buffer_segments == len(segments)  # noqa: E731
    assert peer.spin_until(acknowledged, 30), trainer_log.read_text()[-3000:]
    answer = _call(peer, Retrain, "/trainer/retrain", Retrain.Request(wait=True), timeout=180)
    assert answer.accepted and answer.policy_version == 1, answer.message
    # No simulator for this data: the trainer reports the bc policy's held-out validation loss, and says so.
    assert answer.eval_metric == "val_loss" and math.isfinite(answer.eval_value) and answer.eval_value > 0
    assert math.isnan(answer.eval_success_rate)
    assert peer.spin_until(lambda: statuses[-1].policy_version == 1, 10)
    assert statuses[-1].last_eval_metric == "val_loss" and statuses[-1].last_eval_value == answer.eval_value
    evaluation = _call(peer, EvaluatePolicy, "/trainer/evaluate", EvaluatePolicy.Request())
    assert evaluation.success and (evaluation.metric, evaluation.value) == ("val_loss", answer.eval_value)
    assert "no simulator" in evaluation.message
    assert stop(trainer) == 0 and stop(segmenter) == 0
    for log in (trainer_log, segmenter_log):
        assert "Traceback" not in log.read_text()

    with AugmentationBuffer(tmp_path / "buffer") as buffer:  # stored with the declared camera, state, action
        assert len(buffer) == len(segments)
        for clip in buffer:
            start, end = clip.segment.start, clip.segment.end
            for camera in (FRONT, WRIST):
                np.testing.assert_array_equal(clip.images[camera], play.images[camera][start : end + 1])
            np.testing.assert_array_equal(clip.state, play.state[start : end + 1])
            np.testing.assert_array_equal(clip.actions, play.actions[start:end])


# -- lifecycle -------------------------------------------------------------------------------------------

VALID = {
    State.PRIMARY_STATE_UNCONFIGURED: {
        Transition.TRANSITION_CONFIGURE, Transition.TRANSITION_UNCONFIGURED_SHUTDOWN,
    },
    State.PRIMARY_STATE_INACTIVE: {
        Transition.TRANSITION_CLEANUP, Transition.TRANSITION_ACTIVATE, Transition.TRANSITION_INACTIVE_SHUTDOWN,
    },
    State.PRIMARY_STATE_ACTIVE: {Transition.TRANSITION_DEACTIVATE, Transition.TRANSITION_ACTIVE_SHUTDOWN},
}  # fmt: skip
ALL_TRANSITIONS = sorted(set().union(*VALID.values()))


class LifecycleProbe:
    """Drives one node through transitions and calls every service it offers, checking each answer."""

    def __init__(self, peer: RosPeer, name: str, services: dict[str, tuple[type, object, Check]]) -> None:
        self.peer, self.name, self.services = peer, name, services

    def state(self) -> int:
        return _call(self.peer, GetState, f"/{self.name}/get_state", GetState.Request()).current_state.id

    def transition(self, transition_id: int) -> bool:
        request = ChangeState.Request(transition=Transition(id=transition_id))
        return _call(self.peer, ChangeState, f"/{self.name}/change_state", request).success

    def refuse_invalid_transitions(self) -> None:
        """Every transition not valid in the current state is refused and changes nothing."""
        state = self.state()
        available = _call(
            self.peer,
            GetAvailableTransitions,
            f"/{self.name}/get_available_transitions",
            GetAvailableTransitions.Request(),
        )
        assert {t.transition.id for t in available.available_transitions} >= VALID[state]
        for transition_id in ALL_TRANSITIONS:
            if transition_id not in VALID[state]:
                assert not self.transition(transition_id), f"{transition_id} accepted in state {state}"
                assert self.state() == state

    def call_every_service(self) -> None:
        """Each of the node's own services gives the expected answer while it is offered."""
        offered = {name for name, _ in self.peer.node.get_service_names_and_types()}
        for name, (srv_type, request, check) in self.services.items():
            if name in offered:
                answer = _call(self.peer, srv_type, name, request)
                assert check(answer), f"{name}: {answer}"

    def walk(self, shutdown_from: int) -> None:
        """unconfigured -> inactive -> active -> inactive -> unconfigured -> ... -> shutdown from the
        given state; at each state: invalid transitions refused, services answered."""
        path = [
            Transition.TRANSITION_CONFIGURE, Transition.TRANSITION_ACTIVATE, Transition.TRANSITION_DEACTIVATE,
            Transition.TRANSITION_CLEANUP,
        ]  # fmt: skip
        for transition_id in path:
            self.refuse_invalid_transitions()
            self.call_every_service()
            assert self.transition(transition_id), f"transition {transition_id} failed"
        to_state = {
            State.PRIMARY_STATE_UNCONFIGURED: [],
            State.PRIMARY_STATE_INACTIVE: [Transition.TRANSITION_CONFIGURE],
            State.PRIMARY_STATE_ACTIVE: [Transition.TRANSITION_CONFIGURE, Transition.TRANSITION_ACTIVATE],
        }[shutdown_from]
        for transition_id in to_state:
            assert self.transition(transition_id)
        shutdown = (VALID[shutdown_from] & {5, 6, 7}).pop()
        assert self.transition(shutdown)
        assert self.state() == State.PRIMARY_STATE_FINALIZED
        self.call_every_service()


@pytest.mark.parametrize("kind", ["segmenter", "trainer"])
def test_every_transition_in_every_state_and_every_service_answer(
    kind: str, procs: Processes, peer: RosPeer, tmp_path: Path
) -> None:
    annotated = [robot_episode(0, FEATURES, "action", lengths=(10, 20))]
    if kind == "segmenter":
        params: dict[str, object] = {"model": str(_robot_model(tmp_path / "ps.pt", annotated))}
        services: dict[str, tuple[type, object, Check]] = {}
    else:
        base = tmp_path / "annotated"
        write_play_bag(base, annotated, annotated=True, info=DataInfo(FEATURES, None, INSTRUCTIONS))
        params = {
            "policy": "bc", "base_data": str(base), "buffer_dir": str(tmp_path / "buffer"),
            "checkpoint_dir": str(tmp_path / "checkpoints"), "train_steps": 5, "batch_size": 8,
        }  # fmt: skip
        services = {  # a new policy version each time; nothing segmented yet, so nothing to export
            "/trainer/retrain": (
                Retrain, Retrain.Request(wait=True), lambda a: a.accepted and a.eval_metric == "val_loss",
            ),
            "/trainer/save_buffer": (
                SaveBuffer, SaveBuffer.Request(path=str(tmp_path / "export")),
                lambda a: not a.success and "no episodes" in a.message,
            ),
            "/trainer/evaluate": (
                EvaluatePolicy, EvaluatePolicy.Request(), lambda a: a.success and a.metric == "val_loss",
            ),
        }  # fmt: skip
    for shutdown_from in (State.PRIMARY_STATE_UNCONFIGURED, State.PRIMARY_STATE_ACTIVE):
        node, log = procs.node(kind, f"{kind}-{shutdown_from}", autostart=False, **params)
        probe = LifecycleProbe(peer, kind, services)
        probe.walk(shutdown_from)
        assert node.poll() is None, log.read_text()[-3000:]  # finalized, still answering, until stopped
        assert stop(node) == 0, log.read_text()[-3000:]
        text = log.read_text()
        assert "Traceback" not in text and "failed:" not in text, text[-3000:]
