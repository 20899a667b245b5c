"""topic_adapter: a robot's standard topics in, PlaySteps out, through a `playseg convert` mapping.

It subscribes to the mapping's topics (Image/CompressedImage cameras, JointState, Twist or any numeric
fields, TimedAnnotation labels, an episode marker) and runs the same step builder as `playseg convert`
(playseg_ros/convert/live.py over convert/stepping.py): a step is published once every feature has a
sample later than the step's time plus its tolerance, or dropped and reported (warning) when a feature
has none within its tolerance; never invented. PlaySteps carry every camera by name (camera_names), the
state and the action, so the segmenter needs no other input. The input falling silent for
``idle_timeout_s`` ends the stream (as a bag's end: the last episode is closed); human labels become
step-numbered ``Annotation``s when their episode ends. One topic falling silent while the others go on
(a camera died) is reported once it lags ``max_lag_s`` behind them; from then on its steps are decided
without waiting for it, so the other topics' buffers stay bounded.

Message times: ``header.stamp`` (mapping ``clock: header``), else the node's clock when the message is
received (right on a robot). Replaying a bag: bag_player ``clock:=true`` (``ros2 bag play --clock`` publishes
/clock at a fixed rate: up to one period early) at recorded speed and this node with ``use_sim_time:=true``; a message without a header then takes the
/clock value in effect when the player published it (live.py ReplayStamps), its recorded time, so the
steps are those `playseg convert` makes of the bag. A message published before the first /clock has no
time (the replay's clock is not set): refused with a warning. The discovery/idle timer runs on the steady
clock, so the stream ends ``idle_timeout_s`` of real time after the replay's last message.

Lifecycle: configure reads the mapping and creates the publishers and the discovery/idle timer;
activate subscribes to each mapping topic once a publisher reveals its type (or at once with
``topic_types``); deactivate takes what the subscriptions hold already, unsubscribes, ends the open
stream and waits until its steps are acknowledged; cleanup (and shutdown, error
processing) destroys publishers, subscriptions and the timer.
"""

from __future__ import annotations

import time
from typing import Any

from playseg_msgs.msg import Annotation, PlayStep
from rclpy.clock import Clock, ClockType
from rclpy.lifecycle import LifecycleState, TransitionCallbackReturn
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rclpy.serialization import deserialize_message
from rosgraph_msgs.msg import Clock as ClockMessage

from playseg_core.errors import PlaysegError
from playseg_ros import qos
from playseg_ros.convert.errors import MappingError
from playseg_ros.convert.live import DEFAULT_MAX_LAG_S, LiveMapping, LiveOutput, ReplayStamps
from playseg_ros.convert.mapping import load_mapping
from playseg_ros.convert.source import message_time
from playseg_ros.messages import RCLPY, annotation_message, play_step_message
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
from playseg_ros.ros_types import message_class


class TopicAdapterNode(ReleasingLifecycleNode):
    def __init__(self) -> None:
        super().__init__("topic_adapter")
        self.mapping_path = declare(self, "mapping", "", "playseg convert mapping file (docs/convert.md)")
        self.episode_id = declare(
            self, "episode_id", "live", "episode ids are <episode_id>:<k>, as a bag's are <bag name>:<k>"
        )
        self.topic_types = declare(
            self, "topic_types", [""], "TOPIC=pkg/msg/Type per mapping topic (empty: learnt from publishers)"
        )
        self.steps_topic = declare(self, "steps_topic", "/play/steps", "PlayStep output")
        self.annotations_topic = declare(
            self, "annotations_topic", "/play/annotations", "Annotation output ('' = off)"
        )
        self.reliability = declare(
            self, "reliability", "reliable", "subscriptions: reliable | best_effort (a camera driver's)"
        )
        self.idle_timeout_s = declare(
            self, "idle_timeout_s", 5.0, "no message for this long ends the stream (its last episode)"
        )
        self.wait_for_subscribers = declare(
            self,
            "wait_for_subscribers",
            0,
            "subscribe to the mapped topics only once steps_topic has this many subscribers (PlaySteps "
            "are volatile: a segmenter or recorder matched late would miss the first steps)",
        )
        self.max_lag_s = declare(
            self,
            "max_lag_s",
            DEFAULT_MAX_LAG_S,
            "a mapped topic this far (message time) behind the newest sample of the others is silent: "
            "reported, its steps decided without it (dropped where it has no sample within tolerance, as "
            "convert drops them) and older samples dropped, bounding memory; keep it above the largest "
            "lag between topics of the input",
        )
        self.live: LiveMapping | None = None
        self._types: dict[str, str] = {}
        self._subs: dict[str, Any] = {}
        self._steps_pub = None
        self._annotations_pub = None
        self._timer = None
        self._last_message = 0.0
        self._stream_open = False
        self.published = 0
        self._episodes_done = 0  # episodes of earlier configurations: their ids are never published again
        self._clock_sub = None
        self._replay: ReplayStamps | None = None  # use_sim_time: times of messages without a header
        self._refused_seen = 0
        self._start_gaps = StartGaps(self)

    def on_configure(self, state: LifecycleState) -> TransitionCallbackReturn:
        try:
            require(bool(self.mapping_path), self, "mapping must be set")
            require(bool(self.episode_id), self, "episode_id must not be empty")
            require(self.idle_timeout_s > 0, self, "idle_timeout_s must be > 0")
            require(self.max_lag_s > 0, self, "max_lag_s must be > 0")
            require(
                self.reliability in ("reliable", "best_effort"), self, "reliability: reliable | best_effort"
            )
            try:
                mapping = load_mapping(self.mapping_path)
            except MappingError as error:
                raise PlaysegError(f"{self.get_name()}: {error}") from None
            given = {}
            for item in (t for t in self.topic_types if t):
                topic, sep, type_name = item.partition("=")
                require(bool(sep and topic and type_name), self, f"topic_types entry {item!r}: TOPIC=TYPE")
                given[topic] = type_name
            unknown = sorted(set(given) - set(mapping.topics))
            require(not unknown, self, f"topic_types names topics the mapping does not read: {unknown}")
            self.live = LiveMapping(
                mapping, self.episode_id, self.get_name(), self.max_lag_s, first_episode=self._episodes_done
            )
            self._types = given
            self._steps_pub = self.create_publisher(PlayStep, self.steps_topic, qos.PLAY_STEPS)
            if self.annotations_topic:
                self._annotations_pub = self.create_publisher(
                    Annotation, self.annotations_topic, qos.ANNOTATIONS
                )
            # steady: with use_sim_time a ROS-time timer stands still until the first /clock (no discovery,
            # a player waiting for subscribers never starts) and after the last one (the stream never ends)
            steady = Clock(clock_type=ClockType.STEADY_TIME)
            self._timer = self.create_timer(0.1, self._tick, autostart=False, clock=steady)
        except Exception as exc:  # any configuration problem: report it, stay unconfigured (retryable)
            self.get_logger().error(str(exc) if isinstance(exc, ValueError) else f"configure failed: {exc!r}")
            self.release()
            return TransitionCallbackReturn.FAILURE
        self.get_logger().info(
            f"mapping {self.mapping_path}: {', '.join(self.live.topics)} -> {self.steps_topic}"
        )
        return TransitionCallbackReturn.SUCCESS

    def on_activate(self, state: LifecycleState) -> TransitionCallbackReturn:
        if self.get_parameter("use_sim_time").value:
            self._replay = ReplayStamps()
            self._refused_seen = 0
            # its own /clock reader (the time source keeps only the newest): every value, with its source
            # timestamp; best effort as the time source's, so it matches any /clock publisher
            profile = QoSProfile(depth=1000, reliability=ReliabilityPolicy.BEST_EFFORT)
            self._clock_sub = self.create_subscription(
                ClockMessage, "/clock", self._on_clock, profile, raw=True
            )
        self._timer.reset()
        self._subscribe_discovered()
        return super().on_activate(state)

    def on_deactivate(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._timer.cancel()
        # what the readers hold already becomes steps before the stream ends (a graph stopped upstream
        # first: the player has exited, its last messages are here), and the last steps reach the
        # segmenter and the recorder before this process goes
        self._take_queued()
        self._unsubscribe()
        self._end_stream()
        wait_delivered(self, [self._steps_pub, self._annotations_pub], STOP_DELIVERY_TIMEOUT_S)
        return super().on_deactivate(state)

    def release(self) -> None:
        """Undo configure and activate, whatever got done of them; safe to call again."""
        self._unsubscribe()
        if self._timer is not None:
            self.destroy_timer(self._timer)
            self._timer = None
        for name in ("_steps_pub", "_annotations_pub"):
            publisher = getattr(self, name)
            if publisher is not None:
                self.destroy_publisher(publisher)
                setattr(self, name, None)
        if self.live is not None:
            self._episodes_done = self.live.episodes_done
        self.live = None

    def _unsubscribe(self) -> None:
        for sub in self._subs.values():
            if sub is not None:
                self.destroy_subscription(sub)
        self._subs.clear()
        if self._clock_sub is not None:
            self.destroy_subscription(self._clock_sub)
            self._clock_sub = None

    def _tick(self) -> None:
        self._subscribe_discovered()
        if self._stream_open and time.monotonic() - self._last_message > self.idle_timeout_s:
            # A process starved of CPU can run this timer before messages already queued in its readers:
            # take those first, so a stream ends only when nothing of it is left.
            if not self._take_queued():
                self._end_stream()

    def _take_queued(self) -> bool:
        """Handle the messages waiting in the subscriptions' readers; whether any was a data message
        (/clock alone keeps no stream open: a simulator publishes it all the time)."""
        if self._clock_sub is not None:
            take_queued(self._clock_sub)
        return sum(take_queued(sub) for sub in list(self._subs.values()) if sub is not None) > 0

    def _subscribe_discovered(self) -> None:
        """Subscribe to each mapping topic once its type is known (given, or a publisher reveals it)."""
        if self.live is None:
            return
        missing = [t for t in self.live.topics if t not in self._subs]
        if not missing:
            return
        if self._steps_pub is None or self._steps_pub.get_subscription_count() < self.wait_for_subscribers:
            return
        discovered = dict(self.get_topic_names_and_types())
        profile = qos.recorder_qos(self.reliability)
        for topic in missing:
            type_name = self._types.get(topic) or (discovered.get(topic) or [None])[0]
            if type_name is None:
                continue
            try:
                msg_class = message_class(type_name)
            except ValueError as error:
                self.get_logger().error(f"{topic}: {error}; not subscribed")
                self._subs[topic] = None
                continue
            self._types[topic] = type_name
            # raw: deserialized here, so the receive time is taken before any work
            self._subs[topic] = self.create_subscription(
                msg_class, topic,
                lambda data, info, t=topic, c=msg_class: self._on_message(t, c, data, info), profile,
                raw=True,
            )  # fmt: skip
            self.get_logger().info(f"subscribed to {topic} ({type_name})")

    def _on_clock(self, data: bytes, info: dict) -> None:
        if self._replay is None:
            return
        msg = deserialize_message(data, ClockMessage)
        self._add_released(self._replay.clock(info["source_timestamp"], _ns(msg.clock)))

    def _on_message(self, topic: str, msg_class: type, data: bytes, info: dict) -> None:
        received = self.get_clock().now().nanoseconds
        self._start_gaps.check(topic, info)
        self._last_message = time.monotonic()
        self._stream_open = True
        try:
            msg = deserialize_message(data, msg_class)
        except Exception as exc:  # one bad message must not take the node down: reported, dropped
            self.get_logger().error(f"{topic}: message dropped: {exc!r}")
            return
        own_time = message_time(msg, 0, self.live.mapping.clock == "header")  # 0: none (receive time)
        if self._replay is not None and not own_time and info.get("source_timestamp"):
            self._add_released(self._replay.stamp(info["source_timestamp"], (topic, msg)))
            return
        if not own_time and not received:  # use_sim_time, no /clock yet: the time would be 0
            self._refused(topic)
            return
        self._add(topic, msg, received)

    def _add_released(self, released: list[tuple[int, tuple[str, Any]]]) -> None:
        for stamp, (topic, msg) in released:
            self._add(topic, msg, stamp)
        if self._replay is not None and self._replay.refused > self._refused_seen:
            self._refused_seen = self._replay.refused
            self._refused(self._replay.last_refused[0])

    def _refused(self, topic: str) -> None:
        self.get_logger().warning(
            f"{topic}: message without header.stamp published before the first /clock (use_sim_time: no "
            "time yet): dropped",
            throttle_duration_sec=5.0,
        )

    def _add(self, topic: str, msg: Any, received_ns: int) -> None:
        try:
            output = self.live.add(topic, self._types[topic], msg, received_ns)
        except Exception as exc:  # one bad message must not take the node down: reported, dropped
            self.get_logger().error(f"{topic}: message dropped: {exc!r}")
            return
        self._publish(output)

    def _end_stream(self) -> None:
        if self.live is None or not self._stream_open:
            return
        if self._replay is not None:
            self._add_released(self._replay.flush())
        self._stream_open = False
        self._publish(self.live.end_stream(), ended=True)

    def _publish(self, out: LiveOutput, ended: bool = False) -> None:
        for note in out.notes:
            self.get_logger().warning(note)
        for step in out.steps:
            msg = play_step_message(
                step.episode_id, step.step, step.frames, step.state, step.action, step.time_ns,
                kind=RCLPY,
            )  # fmt: skip
            self._steps_pub.publish(msg)
            self.published += 1
        if self._annotations_pub is not None:
            for episode_id, segment in out.annotations:
                stamp = self.get_clock().now().nanoseconds
                self._annotations_pub.publish(annotation_message(episode_id, segment, stamp, kind=RCLPY))
        if ended:
            self.get_logger().info(f"stream ended: {self.published} steps published so far")


def _ns(stamp: Any) -> int:
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def main(args: list[str] | None = None) -> int:
    return run_node(TopicAdapterNode, args)


if __name__ == "__main__":
    raise SystemExit(main())
