"""segmenter: PlayStep in -> LabelledSegment out, Play Segmentation running online per episode.

Each episode gets its own `StreamingSegmenter` (playseg_core.ps.streaming); a segment is published the moment
the online decoder decides it, carrying its PlaySteps so consumers need no other stream (``segment_form``
``embedded``), or naming where the recorder keeps them (``reference``: the recorder's bag, the steps
topic and the stamps of its first and last step; a few hundred bytes whatever the cameras). Malformed steps
(wrong image size or encoding, NaN action, a gap or repeat in step numbers) are logged with their reason
and end that episode's segmentation (a gap cannot be segmented across); the node keeps running. An
episode whose steps stop arriving without `episode_end` is dropped after `episode_timeout_s`.

Lifecycle: configure loads the model and creates the segment publisher, the silent-episode timer and the
wait timer; activate subscribes to steps (once ``wait_for_subscribers`` readers take the segments);
deactivate segments the steps already delivered, unsubscribes (open episodes are kept) and waits until the
segments are acknowledged; cleanup drops open episodes and the model and destroys the publisher and the
timers (shutdown and error processing release the same).
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass, field
from typing import Any

import torch
from playseg_msgs.msg import LabelledSegment, PlayStep
from rclpy.event_handler import PublisherEventCallbacks, QoSPublisherMatchedInfo
from rclpy.lifecycle import LifecycleState, TransitionCallbackReturn

from playseg_core.augment.buffer import MODEL_DIGEST_CHARS, MODEL_DIGEST_SEP
from playseg_core.checkpoint import file_digest
from playseg_core.data.features import DEFAULT_CAMERA
from playseg_core.ps.labelling import KEEP_RULES, KeepRule, is_calibrated, uncalibrated_warning
from playseg_core.ps.model import load_model
from playseg_core.ps.streaming import StreamingSegmenter
from playseg_core.training.device import resolve_device
from playseg_ros import qos
from playseg_ros.messages import (
    RCLPY,
    StepError,
    check_step_number,
    labelled_segment_of_steps,
    labelled_segment_reference,
    stamp_ns,
    step_from_message,
)
from playseg_ros.nodes.common import (
    STOP_DELIVERY_TIMEOUT_S,
    ReleasingLifecycleNode,
    StartGaps,
    declare,
    require,
    run_node,
    take_queued,
    wait_delivered,
)

DUPLICATE_CHECK_S = 2.0
"""How often the segmenter looks for another node of its name on the graph (a local cache query)."""


@dataclass
class _OpenEpisode:
    episode_id: str
    segmenter: StreamingSegmenter
    # from the last decided boundary on: the PlaySteps (embedded form), or their headers (reference form:
    # the frames stay in the recording, not in this node's memory)
    steps: list[Any] = field(default_factory=list)
    first_step: int = 0  # step number of steps[0]
    last_seen: float = field(default_factory=time.monotonic)

    @property
    def next_step(self) -> int:
        return self.first_step + len(self.steps)


class SegmenterNode(ReleasingLifecycleNode):
    def __init__(self) -> None:
        super().__init__("segmenter")
        self.model_path = declare(self, "model", "", "PS checkpoint (playseg train)")
        self.model_id = declare(
            self,
            "model_id",
            "",
            "id put in LabelledSegment.model_id ('' = checkpoint file name), followed by @sha256:<16 hex of the checkpoint>",
        )
        self.steps_topic = declare(self, "steps_topic", "/play/steps", "PlayStep input topic")
        self.segments_topic = declare(self, "segments_topic", "/segments", "LabelledSegment output topic")
        self.keep = declare(
            self,
            "keep",
            "all",
            "which segments to publish: all, label (label confidence >= the checkpoint's threshold "
            "calibrated on true cuts), own_cuts (label x cut probability >= its threshold calibrated on its "
            "own cuts of the val episodes: docs/segmentation.md 'Calibration')",
        )
        self.min_confidence = declare(
            self, "min_confidence", 0.0, "publish only segments with label confidence >= this (and kept)"
        )
        self.min_len = declare(self, "min_len", 0, "minimum segment length in steps (0 = the model's L_min)")
        self.episode_timeout_s = declare(
            self, "episode_timeout_s", 60.0, "drop an episode silent for this long"
        )
        self.threads = declare(
            self, "torch_threads", 1, "torch CPU threads (more threads than cores is slow)"
        )
        self.device = declare(
            self, "device", "auto", "where the model runs: auto (CUDA when torch sees one), cpu, cuda, cuda:N"
        )
        self.segment_form = declare(
            self,
            "segment_form",
            "embedded",
            "embedded: each LabelledSegment carries its PlaySteps; reference: it names recording_bag, the "
            "steps topic and its first and last step stamps instead (the trainer reads the steps there)",
        )
        self.recording_bag = declare(
            self, "recording_bag", "", "reference form: the recorder's bag directory (its 'output')"
        )
        self.wait_for_subscribers = declare(
            self,
            "wait_for_subscribers",
            0,
            "subscribe to steps only once segments_topic has this many subscribers (segments are volatile: "
            "a recorder or trainer matched late would miss the first ones; playseg up sets it from the graph)",
        )
        self.model = None
        self.keep_rule = KeepRule("all")  # from the checkpoint, in on_configure
        self.camera = DEFAULT_CAMERA  # the feature the PlaySteps' image is: the model's camera
        self.episodes: dict[str, _OpenEpisode] = {}
        self.finished: set[str] = set()
        self._ended_quietly: set[str] = set()  # ended by episode_end, no step after it seen yet
        self.published = 0
        self._sub = None
        self._recording = ("", "")  # reference form: (bag, fully qualified steps topic), from activate
        self._pub = None  # created in on_configure, destroyed in on_cleanup, as the timer
        self._timer = None
        self._graph_timer = None  # the duplicate-name check (a graph query), from configure to cleanup
        self._wait_timer = None  # while active: subscribes to steps once the segments have their readers
        self._start_gaps = StartGaps(self)
        self._duplicate_warned = False
        self._frame_shapes: dict[str, tuple[int, ...]] = {}  # by camera name, from the model

    def on_configure(self, state: LifecycleState) -> TransitionCallbackReturn:
        try:
            require(bool(self.model_path), self, "model must be set")
            require(self.min_len >= 0, self, "min_len must be >= 0")
            require(self.episode_timeout_s > 0, self, "episode_timeout_s must be > 0")
            require(self.threads >= 1, self, "torch_threads must be >= 1")
            require(self.wait_for_subscribers >= 0, self, "wait_for_subscribers must be >= 0")
            require(
                self.segment_form in ("embedded", "reference"), self, "segment_form: embedded | reference"
            )
            require(
                self.segment_form == "embedded" or bool(self.recording_bag),
                self,
                "segment_form reference needs recording_bag (the recorder's output)",
            )
            # absolute: the trainer resolves it from its own working directory
            self.recording_bag = os.path.abspath(self.recording_bag) if self.recording_bag else ""
            torch.set_num_threads(self.threads)
            require(self.keep in KEEP_RULES, self, f"keep: {' | '.join(KEEP_RULES)}")
            device = resolve_device(self.device)
            self.model, meta = load_model(self.model_path, kinds=("ps",))
            self.model.to(device)
            self.keep_rule = KeepRule.of_checkpoint(
                self.keep, meta, f"{self.get_name()}: model {self.model_path}"
            )
            if not is_calibrated(meta):
                self.get_logger().warning(uncalibrated_warning(f"model {self.model_path}"))
            self.min_len = self.min_len or self.model.cfg.min_len
            features = self.model.cfg.features
            cameras = features.cameras
            # A PlayStep without camera names carries one camera: the model's first.
            self.camera = cameras[0] if cameras else DEFAULT_CAMERA
            self._frame_shapes = {name: features[name].shape for name in cameras}
            if cameras:
                self._frame_shapes[""] = features[cameras[0]].shape
            # /segments is volatile: a reader that matches after a segment left never gets it, so each
            # change in the matched readers is logged (operators and tests can wait for their consumers).
            self._pub = self.create_publisher(
                LabelledSegment,
                self.segments_topic,
                qos.SEGMENTS,
                event_callbacks=PublisherEventCallbacks(matched=self._on_segments_matched),
            )
            self._timer = self.create_timer(min(5.0, self.episode_timeout_s / 2), self._drop_silent_episodes)
            self._graph_timer = self.create_timer(DUPLICATE_CHECK_S, self._check_duplicate_name)
            self._wait_timer = self.create_timer(0.1, self._subscribe_when_heard, autostart=False)
        except Exception as exc:  # any configuration problem: report it, stay unconfigured (retryable)
            self.get_logger().error(str(exc) if isinstance(exc, ValueError) else f"configure failed: {exc!r}")
            self.release()
            return TransitionCallbackReturn.FAILURE
        # the checkpoint's digest in every segment: the trainer stores a segment once per model, however
        # many segmenters (or copies of the checkpoint) publish it
        # (split: a reconfigured node's model_id carries the earlier digest already)
        name = self.model_id.split(MODEL_DIGEST_SEP)[0] or self.model_path.rsplit("/", 1)[-1]
        self.model_id = f"{name}{MODEL_DIGEST_SEP}{file_digest(self.model_path)[:MODEL_DIGEST_CHARS]}"
        self._duplicate_warned = False
        form = f"reference to {self.recording_bag}" if self.reference else "embedded"
        self.get_logger().info(
            f"model {self.model_path} (L_max {self.model.max_len}, on {self.model.device}); {self.steps_topic} -> {self.segments_topic} "
            f"({form} segments; kept: {self.keep_rule.describe()})"
        )
        return TransitionCallbackReturn.SUCCESS

    def _on_segments_matched(self, info: QoSPublisherMatchedInfo) -> None:
        self.get_logger().info(f"{self.segments_topic}: {info.current_count} subscriber(s) matched")

    @property
    def reference(self) -> bool:
        return self.segment_form == "reference"

    def on_activate(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._wait_timer.reset()
        self._subscribe_when_heard()
        return super().on_activate(state)

    def _subscribe_when_heard(self) -> None:
        """Subscribe to steps once `wait_for_subscribers` readers take the segments: upstream waits for
        this subscription, so the whole chain starts only when its last reader is there."""
        if self._sub is not None or self._pub.get_subscription_count() < self.wait_for_subscribers:
            return
        self._wait_timer.cancel()
        self._sub = self.create_subscription(PlayStep, self.steps_topic, self._on_step, qos.PLAY_STEPS)
        self._recording = (self.recording_bag, self._sub.topic_name)  # the name the recorder records

    def on_deactivate(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._wait_timer.cancel()
        if self._sub is not None:
            # the steps already delivered are segmented and their segments sent, not dropped: a graph
            # stopped upstream first (playseg up) gets the last episode's segments
            take_queued(self._sub)
            self.destroy_subscription(self._sub)
            self._sub = None
        wait_delivered(self, [self._pub], STOP_DELIVERY_TIMEOUT_S)
        return super().on_deactivate(state)

    def release(self) -> None:
        """Undo configure and activate, whatever got done of them; safe to call again."""
        if self._sub is not None:
            self.destroy_subscription(self._sub)
            self._sub = None
        if self._timer is not None:
            self.destroy_timer(self._timer)
            self._timer = None
        for name in ("_graph_timer", "_wait_timer"):
            if getattr(self, name) is not None:
                self.destroy_timer(getattr(self, name))
                setattr(self, name, None)
        if self._pub is not None:
            self.destroy_publisher(self._pub)
            self._pub = None
        if self.episodes:
            self.get_logger().warning(
                f"dropping {len(self.episodes)} unfinished episodes: {sorted(self.episodes)}"
            )
        self.episodes.clear()
        self.model = None

    def _on_step(self, msg: PlayStep, info: dict) -> None:
        self._start_gaps.check(self.steps_topic, info)
        if msg.episode_id in self.finished and msg.step != 0:
            if msg.episode_id in self._ended_quietly:  # a dropped episode had its log line already
                self._ended_quietly.discard(msg.episode_id)
                self.get_logger().warning(
                    f"{self.steps_topic}: episode {msg.episode_id!r} goes on after its episode_end (step "
                    f"{msg.step}): its later steps are dropped (a new episode starts at step 0)"
                )
            return
        try:
            self._segment_step(msg)
        except Exception as exc:  # a bad step or a failure on one episode must not take the node down
            if isinstance(exc, StepError):
                self.get_logger().warning(f"{self.steps_topic}: malformed PlayStep, episode dropped: {exc}")
            else:
                self.get_logger().error(
                    f"episode {msg.episode_id!r} step {msg.step}: segmentation failed, dropped: {exc!r}"
                )
            self.episodes.pop(msg.episode_id, None)
            self.finished.add(msg.episode_id)

    def _segment_step(self, msg: PlayStep) -> None:
        data = step_from_message(msg, self._frame_shapes)
        episode = self.episodes.get(data.episode_id)
        if episode is None:
            # Step 0 of an id seen before starts that episode anew (a replayed bag): documented rule.
            self.finished.discard(data.episode_id)
            self._ended_quietly.discard(data.episode_id)
            check_step_number(data.episode_id, data.step, 0)
            episode = self.episodes[data.episode_id] = _OpenEpisode(
                data.episode_id, StreamingSegmenter(self.model, self.min_len)
            )
        else:
            check_step_number(data.episode_id, data.step, episode.next_step)
        episode.steps.append(msg.header if self.reference else msg)
        episode.last_seen = time.monotonic()
        decided = episode.segmenter.push(data.observation(self.camera), data.action)
        if data.episode_end:
            decided += episode.segmenter.finish()
            del self.episodes[data.episode_id]
            self.finished.add(data.episode_id)
            self._ended_quietly.add(data.episode_id)
        for segment in decided:
            self._publish(episode, segment)
        if data.episode_end:  # every segment of the episode is published
            self.get_logger().info(f"episode {data.episode_id!r} ended after {data.step + 1} steps")
        if decided:
            drop = decided[-1].end - episode.first_step
            episode.steps = episode.steps[drop:]
            episode.first_step += drop

    def _publish(self, episode: _OpenEpisode, segment) -> None:
        if segment.confidence < self.min_confidence or not self.keep_rule.keeps(segment):
            return
        steps = episode.steps[segment.start - episode.first_step : segment.end - episode.first_step + 1]
        stamp = self.get_clock().now().nanoseconds
        if self.reference:
            headers = steps
            msg = labelled_segment_reference(
                episode.episode_id, segment, self.model_id, stamp, self._recording,
                (stamp_ns(headers[0]), stamp_ns(headers[-1])), headers[0].frame_id, RCLPY,
            )  # fmt: skip
        else:
            msg = labelled_segment_of_steps(
                episode.episode_id, segment, steps, self.model_id, stamp, steps[0].header.frame_id, RCLPY
            )
        self._pub.publish(msg)
        self.published += 1

    def _check_duplicate_name(self) -> None:
        """Warn (once) when another node with this one's fully qualified name is on the graph: two
        segmenters started alike publish every segment twice. Checked periodically, as discovery of a
        node started at the same time (or later) takes a moment."""
        if self._duplicate_warned:
            return
        me = (self.get_name(), self.get_namespace())
        same = sum(1 for entry in self.get_node_names_and_namespaces() if tuple(entry) == me)
        if same > 1:
            self._duplicate_warned = True
            self.get_logger().warning(
                f"{same} nodes named {self.get_fully_qualified_name()} on the graph: every segment is "
                "published once by each (give each segmenter its own name: --ros-args -r __node:=NAME); "
                "a trainer stores each segment of one model once"
            )

    def _drop_silent_episodes(self) -> None:
        now = time.monotonic()
        for episode_id, episode in list(self.episodes.items()):
            if now - episode.last_seen > self.episode_timeout_s:
                self.get_logger().warning(
                    f"episode {episode_id!r}: no step for {self.episode_timeout_s} s and no episode_end: dropped "
                    f"after step {episode.next_step - 1}"
                )
                del self.episodes[episode_id]
                self.finished.add(episode_id)


def main(args: list[str] | None = None) -> int:
    return run_node(SegmenterNode, args)


if __name__ == "__main__":
    raise SystemExit(main())
