"""trainer: LabelledSegment in -> persistent augmentation buffer -> retrained policy, TrainerStatus out.

Lifecycle: configure opens the buffer, loads the annotated base data and creates the status publisher,
its timer and the services; activate starts listening; deactivate stops listening; cleanup closes the
buffer and destroys the publisher, the timer and the services (shutdown and error processing release the
same: a failed configure can be retried). Every received segment is fsync'ed to the buffer before it
counts (TrainerStatus.buffer_segments is the acknowledged count), so a crash loses nothing that was
acknowledged. Retraining runs in a background thread every `retrain_every` segments and on the
`~/retrain` service; each run writes `policy-vNNNN.pt` and evaluates it on fixed seeded episodes of the
policy's simulator (the `policy` parameter names it: ``<domain>.<policy>``, see playseg_core.augment.policies).
A policy without a simulator (the generic ``bc``) reports its held-out validation figure instead;
TrainerStatus.last_eval_metric and the `~/evaluate` answer say which one they carry.

A reference-form segment (no steps; the recorder's bag, topic and step stamps instead) is resolved by
reading its steps from that bag (playseg_ros/recorded_steps.py; the recording may still be in progress).
Steps not there yet keep the segment pending, with one warning; it is retried every
`resolve_period_s` and given up, with an error line, only after `resolve_timeout_s`.
"""

from __future__ import annotations

import math
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from playseg_msgs.msg import LabelledSegment, TrainerStatus
from playseg_msgs.srv import EvaluatePolicy, Retrain, SaveBuffer
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.lifecycle import LifecycleState, TransitionCallbackReturn

from playseg_core.augment.policies import load_policy_learner
from playseg_core.augment.retraining import (
    AugmentationTrainer,
    TrainerConfig,
    annotated_clips,
    export_buffer_dataset,
)
from playseg_core.errors import PlaysegError
from playseg_core.training.device import resolve_device
from playseg_ros import qos
from playseg_ros.messages import clip_from_labelled
from playseg_ros.nodes.common import (
    ReleasingLifecycleNode,
    StartGaps,
    declare,
    require,
    run_node,
    take_queued,
)
from playseg_ros.play_bags import DataInfo, load_annotated
from playseg_ros.recorded_steps import RecordedSteps, StepsNotRecorded, StepsReference, reference_of

NOT_CONFIGURED = "trainer is not configured"
PENDING_WARN_S = 10.0
"""A reference-form segment whose steps a running recording still lacks after this long is warned about."""


@dataclass
class _Pending:
    """A reference-form segment waiting for its steps to be recorded."""

    msg: LabelledSegment
    since: float  # time.monotonic() when it arrived
    warned: bool = False


class TrainerNode(ReleasingLifecycleNode):
    def __init__(self) -> None:
        super().__init__("trainer")
        self.p = {
            "buffer_dir": declare(self, "buffer_dir", "", "directory of the persistent augmentation buffer"),
            "checkpoint_dir": declare(self, "checkpoint_dir", "", "where versioned policy checkpoints go"),
            "base_data": declare(
                self,
                "base_data",
                "",
                "annotated data the policy always trains on: a play bag (its /play/annotations) or a playseg "
                "dataset (its 'train' split); '' = none",
            ),
            "segments_topic": declare(self, "segments_topic", "/segments", "LabelledSegment input topic"),
            "status_topic": declare(self, "status_topic", "/trainer/status", "TrainerStatus output topic"),
            "retrain_every": declare(
                self, "retrain_every", 0, "retrain after N new segments (0 = on request)"
            ),
            "min_confidence": declare(
                self, "min_confidence", 0.0, "train only on segments at this confidence+"
            ),
            "policy": declare(
                self, "policy", "babyai.film", "the policy to train: <domain>.<policy>, or a generic one (bc)"
            ),
            "train_steps": declare(self, "train_steps", 2000, "optimiser steps per retraining"),
            "batch_size": declare(self, "batch_size", 256, "imitation batch size"),
            "policy_channels": declare(self, "policy_channels", 64, "width of the policy network"),
            "device": declare(
                self,
                "device",
                "auto",
                "where the policy trains: auto (CUDA when torch sees one), cpu, cuda, cuda:N",
            ),
            "seed": declare(self, "seed", 0, "training seed"),
            "eval_episodes": declare(self, "eval_episodes", 512, "fixed seeded evaluation episodes"),
            "eval_max_steps": declare(self, "eval_max_steps", 25, "success must come within this many steps"),
            "status_period_s": declare(self, "status_period_s", 2.0, "status republish period"),
            "resolve_period_s": declare(
                self,
                "resolve_period_s",
                1.0,
                "retry reading a reference-form segment's steps from its recording this often",
            ),
            "resolve_timeout_s": declare(
                self,
                "resolve_timeout_s",
                300.0,
                "give up a reference-form segment whose steps are not in its recording after this long "
                "(0 = never)",
            ),
        }
        self.trainer: AugmentationTrainer | None = None
        self.base_info = DataInfo()
        self.state = "idle"
        self.message = ""
        self.last_eval = math.nan
        self.last_eval_episodes = 0
        self.last_eval_metric, self.last_eval_value = "", math.nan
        self.last_loss = math.nan
        self._training = threading.Lock()
        self._sub = None
        self._start_gaps = StartGaps(self)
        # Created in on_configure, destroyed in on_cleanup. The status publisher is also used from the
        # retraining thread: `_status_lock` keeps it from being destroyed under a publish.
        self._status_lock = threading.Lock()
        self._status_pub = None
        self._status_timer = None
        self._resolve_timer = None
        self._own_services = []
        self._recordings: dict[tuple[str, str], RecordedSteps] = {}  # by (bag, topic), indexed as they grow
        # reference-form segments whose steps are not recorded yet, by buffer key
        self._pending: dict[tuple[str, int, int, str], _Pending] = {}

    # -- lifecycle -------------------------------------------------------------------------------------
    def on_configure(self, state: LifecycleState) -> TransitionCallbackReturn:
        p = self.p
        try:
            require(bool(p["buffer_dir"]), self, "buffer_dir must be set")
            require(bool(p["checkpoint_dir"]), self, "checkpoint_dir must be set")
            require(p["retrain_every"] >= 0, self, "retrain_every must be >= 0")
            require(p["eval_episodes"] > 0 and p["eval_max_steps"] > 0, self, "eval_* must be > 0")
            require(p["resolve_period_s"] > 0, self, "resolve_period_s must be > 0")
            require(p["resolve_timeout_s"] >= 0, self, "resolve_timeout_s must be >= 0")
            require(0 < p["status_period_s"] < float("inf"), self, "status_period_s must be finite and > 0")
            for key in ("buffer_dir", "checkpoint_dir"):  # made here, so a failure names its parameter
                try:
                    Path(p[key]).mkdir(parents=True, exist_ok=True)
                except OSError as exc:
                    require(False, self, f"{key} {p[key]!r}: {exc.strerror or exc}")
            annotated = load_annotated(p["base_data"]) if p["base_data"] else None
            learner = load_policy_learner(
                p["policy"],
                {
                    "steps": p["train_steps"],
                    "batch_size": p["batch_size"],
                    "seed": p["seed"],
                    "channels": p["policy_channels"],
                    "eval_max_steps": p["eval_max_steps"],
                    "device": str(
                        resolve_device(p["device"])
                    ),  # no CUDA where asked: configure fails, one line
                },
                features=annotated.info.features if annotated is not None else None,  # a generic policy's
            )
            base = []
            if annotated is not None:
                self.base_info = annotated.info
                if annotated.info.features is not None:
                    learner.features.check_compatible(
                        annotated.info.features, sorted(learner.features.by_name), f"policy {p['policy']}"
                    )
                base = annotated_clips(annotated.episodes)
            config = TrainerConfig(
                buffer_dir=p["buffer_dir"],
                checkpoint_dir=p["checkpoint_dir"],
                retrain_every=p["retrain_every"],
                min_confidence=p["min_confidence"],
                eval_episodes=p["eval_episodes"],
            )
            self.trainer = AugmentationTrainer(config, learner, base)
            self._create_entities()
        except Exception as exc:  # any configuration problem: report it, stay unconfigured (retryable)
            # an OSError's repr leaves out the file it is about; its str names it
            what = str(exc) if isinstance(exc, (OSError, ValueError)) else repr(exc)
            self.get_logger().error(f"configure failed: {what}")
            self.release()
            return TransitionCallbackReturn.FAILURE
        if self.trainer.buffer.recovered_bytes:
            self.get_logger().warning(f"cut a torn record of {self.trainer.buffer.recovered_bytes} bytes")
        self.get_logger().info(
            f"buffer {p['buffer_dir']}: {len(self.trainer.buffer)} segments; {len(base)} annotated segments; "
            f"policy v{self.trainer.policy_version}"
        )
        self.publish_status()
        return TransitionCallbackReturn.SUCCESS

    def _create_entities(self) -> None:
        with self._status_lock:
            self._status_pub = self.create_publisher(TrainerStatus, self.p["status_topic"], qos.STATUS)
        self._status_timer = self.create_timer(self.p["status_period_s"], self.publish_status)
        # runs only while segments are pending: no wake-ups (nor a timer callback in flight at shutdown)
        self._resolve_timer = self.create_timer(
            self.p["resolve_period_s"], self._retry_pending, autostart=False
        )
        # Services may run for minutes (retrain with wait=true): their own group keeps segments flowing.
        slow = MutuallyExclusiveCallbackGroup()
        self._own_services = [
            self.create_service(Retrain, "~/retrain", self._on_retrain, callback_group=slow),
            self.create_service(SaveBuffer, "~/save_buffer", self._on_save_buffer, callback_group=slow),
            self.create_service(EvaluatePolicy, "~/evaluate", self._on_evaluate, callback_group=slow),
        ]

    def on_activate(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._sub = self.create_subscription(
            LabelledSegment, self.p["segments_topic"], self._on_segment, qos.SEGMENTS
        )
        return super().on_activate(state)

    def on_deactivate(self, state: LifecycleState) -> TransitionCallbackReturn:
        if self._sub is not None:
            take_queued(self._sub)  # delivered segments are stored, not dropped with the subscription
            self.destroy_subscription(self._sub)
            self._sub = None
        return super().on_deactivate(state)

    def release(self) -> None:
        """Undo configure and activate, whatever got done of them; safe to call again."""
        if self._sub is not None:
            self.destroy_subscription(self._sub)
            self._sub = None
        for service in self._own_services:
            self.destroy_service(service)
        self._own_services = []
        for timer in (self._status_timer, self._resolve_timer):
            if timer is not None:
                self.destroy_timer(timer)
        self._status_timer = self._resolve_timer = None
        if self._pending:
            self.get_logger().warning(
                f"dropping {len(self._pending)} reference-form segments whose steps were never read: "
                + ", ".join(f"{e!r} [{a}, {b})" for e, a, b, _ in self._pending)
            )
        self._pending.clear()
        self._recordings.clear()
        with self._training:  # let a running retraining finish writing its checkpoint
            if self.trainer is not None:
                self.trainer.close()
                self.trainer = None
        with self._status_lock:
            if self._status_pub is not None:
                self.destroy_publisher(self._status_pub)
                self._status_pub = None
        self.base_info = DataInfo()
        self.last_eval, self.last_eval_episodes, self.last_loss = math.nan, 0, math.nan
        self.last_eval_metric, self.last_eval_value = "", math.nan

    # -- data ------------------------------------------------------------------------------------------
    def _on_segment(self, msg: LabelledSegment, info: dict) -> None:
        self._start_gaps.check(self.p["segments_topic"], info)
        ref = reference_of(msg)
        if ref is None:
            self._store(msg)
            return
        key = (msg.episode_id, int(msg.start_step), int(msg.end_step), msg.model_id)
        if key in self._pending:
            return  # the same segment again (a second segmenter of the same model): it waits already
        try:
            steps = self._recorded(ref).steps(ref)
        except StepsNotRecorded as exc:
            # Steps a running recorder has not flushed yet are normal (it closes a chunk every second or
            # so): warned about only when they are still missing after PENDING_WARN_S.
            self._pending[key] = _Pending(msg, time.monotonic())
            if self._resolve_timer.is_canceled():
                self._resolve_timer.reset()
            if not exc.recording:
                self._warn_pending(self._pending[key], exc)
            return
        self._store(msg, steps)

    def _warn_pending(self, pending: _Pending, exc: StepsNotRecorded) -> None:
        pending.warned = True
        self.get_logger().warning(
            f"LabelledSegment on {self.p['segments_topic']}: {exc}; kept pending, retried every "
            f"{self.p['resolve_period_s']:g} s"
        )

    def _recorded(self, ref: StepsReference) -> RecordedSteps:
        recording = (ref.bag, ref.topic)
        if recording not in self._recordings:
            self._recordings[recording] = RecordedSteps(*recording)
        return self._recordings[recording]

    def _retry_pending(self) -> None:
        """Resolve the pending reference-form segments whose steps have been recorded since."""
        timeout = self.p["resolve_timeout_s"]
        for key, pending in list(self._pending.items()):
            ref = reference_of(pending.msg)
            try:
                steps = self._recorded(ref).steps(ref)
            except StepsNotRecorded as exc:
                waited = time.monotonic() - pending.since
                if timeout and waited > timeout:
                    del self._pending[key]
                    self.get_logger().error(
                        f"dropped LabelledSegment on {self.p['segments_topic']} after resolve_timeout_s "
                        f"{timeout:g}: {exc}"
                    )
                elif not pending.warned and (waited > PENDING_WARN_S or not exc.recording):
                    self._warn_pending(pending, exc)
                continue
            del self._pending[key]
            if pending.warned:
                self.get_logger().info(f"{ref}: read from the recording, stored")
            self._store(pending.msg, steps)
        if not self._pending:
            self._resolve_timer.cancel()

    def _store(self, msg: LabelledSegment, steps: list[Any] | None = None) -> None:
        """Add a segment (its steps: embedded, or read from its recording) to the buffer."""
        try:
            due = self.trainer.add(clip_from_labelled(msg, self.base_info.camera, steps))
        except ValueError as exc:
            self.get_logger().error(f"dropped LabelledSegment on {self.p['segments_topic']}: {exc}")
            return
        self.publish_status()
        if due:
            self._start_retraining()

    def _start_retraining(self) -> bool:
        if not self._training.acquire(blocking=False):
            return False  # one already runs; the next trigger picks up the new segments
        threading.Thread(target=self._retrain_locked, daemon=True).start()
        return True

    def _retrain_locked(self) -> None:
        trainer = self.trainer
        if trainer is None:  # cleaned up while this request waited for the lock
            self._training.release()
            return
        try:
            self.state = "training"
            self.publish_status()
            version = trainer.retrain()
            self.last_eval, self.last_eval_episodes = version.success_rate, version.eval_episodes
            self.last_eval_metric, self.last_eval_value = version.eval_metric, version.eval_value
            self.last_loss = version.train_loss
            self.message = (
                f"policy v{version.version}: {version.eval_metric or 'eval'} {version.eval_value:.3f}"
            )
            self.get_logger().info(self.message)
            self.state = "idle"
        except Exception as exc:  # a failed retraining must not kill the node or lose the buffer
            self.state, self.message = "error", f"retraining failed: {exc}"
            self.get_logger().error(self.message)
        finally:
            self._training.release()
            self.publish_status()

    # -- services --------------------------------------------------------------------------------------
    def _on_retrain(self, request: Retrain.Request, response: Retrain.Response) -> Retrain.Response:
        try:
            if self.trainer is None:
                response.accepted, response.message = False, NOT_CONFIGURED
                return response
            if request.wait:
                self._training.acquire()  # waits for a running retraining, then runs a fresh one
                trainer = self.trainer
                self._retrain_locked()
                if trainer is None:
                    response.accepted, response.message = False, NOT_CONFIGURED
                    return response
                response.accepted = self.state != "error"
                response.eval_success_rate = self.last_eval
                response.eval_metric, response.eval_value = self.last_eval_metric, self.last_eval_value
            else:
                trainer = self.trainer
                response.accepted = self._start_retraining()
                response.eval_success_rate = response.eval_value = math.nan
            response.policy_version = trainer.policy_version + (0 if request.wait else 1)
            response.message = self.message if request.wait else ("started" if response.accepted else "busy")
        except Exception as exc:  # a service must answer, never take the node down
            self.get_logger().error(f"~/retrain failed: {exc!r}")
            response.accepted, response.message = False, f"retrain failed: {exc}"
        return response

    def _on_save_buffer(
        self, request: SaveBuffer.Request, response: SaveBuffer.Response
    ) -> SaveBuffer.Response:
        trainer = self.trainer
        if trainer is None:
            response.success, response.message = False, NOT_CONFIGURED
            return response
        try:
            info = self.base_info
            response.segments = export_buffer_dataset(
                trainer.buffer, request.path, info.instructions, info.features, info.domain
            )
            response.success, response.path = True, request.path
        except Exception as exc:
            response.success, response.message = False, str(exc)
        return response

    def _on_evaluate(
        self, request: EvaluatePolicy.Request, response: EvaluatePolicy.Response
    ) -> EvaluatePolicy.Response:
        trainer = self.trainer
        if trainer is None:
            response.success, response.message = False, NOT_CONFIGURED
            return response
        try:
            latest = trainer.latest  # one version throughout, though a retraining may replace it meanwhile
            if latest is None:
                raise PlaysegError("no policy trained yet")
            model = trainer.learner.load(Path(latest.checkpoint))[0]
            result = trainer.evaluate(model, episodes=request.episodes or None)
            response.policy_version = latest.version
            if result is not None:
                response.success, response.success_rate = True, result.success_rate
                response.metric, response.value = "success_rate", result.success_rate
                response.episodes = result.num_episodes
            else:  # no simulator: the held-out figure measured when this version was trained
                response.success, response.success_rate = True, math.nan
                response.metric, response.value = latest.eval_metric, latest.eval_value
                response.message = (
                    f"policy {self.p['policy']} has no simulator: {latest.eval_metric or 'no figure'} "
                    f"of v{latest.version} on its held-out annotated segments"
                )
        except ValueError as exc:
            response.success, response.message = False, str(exc)
        except Exception as exc:  # a service must answer, never take the node down
            self.get_logger().error(f"~/evaluate failed: {exc!r}")
            response.success, response.message = False, f"evaluation failed: {exc}"
        return response

    def publish_status(self) -> None:
        """Publish the TrainerStatus (timer, every change; a no-op while unconfigured)."""
        with self._status_lock:
            if self._status_pub is None:
                return
            msg = TrainerStatus()
            msg.header.stamp = self.get_clock().now().to_msg()
            msg.state = self.state
            trainer = self.trainer
            if trainer is not None:
                msg.buffer_segments = len(trainer.buffer)
                msg.buffer_steps = trainer.buffer.num_steps
                msg.policy_version = trainer.policy_version
                if trainer.latest:
                    msg.checkpoint_path = trainer.latest.checkpoint
                    if not self.last_eval_metric:  # a version trained before this node started
                        self.last_eval = trainer.latest.success_rate
                        self.last_eval_episodes = trainer.latest.eval_episodes
                        self.last_eval_metric = trainer.latest.eval_metric
                        self.last_eval_value = trainer.latest.eval_value
            msg.last_eval_success_rate = float(self.last_eval)
            msg.last_eval_metric = self.last_eval_metric
            msg.last_eval_value = float(self.last_eval_value)
            msg.last_eval_episodes = self.last_eval_episodes
            msg.last_train_loss = float(self.last_loss)
            msg.message = self.message
            self._status_pub.publish(msg)


def main(args: list[str] | None = None) -> int:
    return run_node(TrainerNode, args, threads=2)  # services run beside the segment subscription


if __name__ == "__main__":
    raise SystemExit(main())
