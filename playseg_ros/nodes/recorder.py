"""recorder: records topics through serialized (raw) subscriptions into a rosbag2-compatible MCAP bag.

Lifecycle: configure opens the bag (`<output>.partial/` until it is closed) and creates the discovery and
flush timers (stopped); activate starts them and subscribes to every configured topic as soon as its type
is known on the graph; deactivate stops them, unsubscribes and flushes; cleanup finishes the bag
(metadata.yaml, rename to `<output>`) and destroys the timers. Shutdown from active or inactive does what
deactivate and cleanup do. Files split by size or duration; chunks are zstd
compressed and flushed every `flush_period_s`, so a crash loses at most the open chunk and
`playseg bag recover <output>` restores the rest (each flush that wrote something logs, at debug level,
how many messages are on disk: `--ros-args --log-level recorder:=debug`).

A write error (a full disk) while recording or finishing the bag is logged, the bag is left in
`<output>.partial/` with everything flushed so far (for `playseg bag recover`) and the process exits 1.

QoS: KEEP_ALL history, `reliability` as configured. A topic whose publishers all offer TRANSIENT_LOCAL
(e.g. /play/annotations) is subscribed TRANSIENT_LOCAL, so what they published before the recorder
subscribed is recorded too.
"""

from __future__ import annotations

import math
from pathlib import Path

from rclpy.lifecycle import LifecycleNode, LifecycleState, TransitionCallbackReturn
from rclpy.qos import DurabilityPolicy
from rclpy.subscription import Subscription

from playseg_core.errors import PlaysegError
from playseg_ros import qos
from playseg_ros.bag import BagError, BagWriter, QosProfile, partial_path, topic_info
from playseg_ros.nodes.common import StartGaps, declare, require, run_node, take_queued
from playseg_ros.ros_types import message_class


def _offered_profile(info) -> QosProfile:
    """An rclpy TopicEndpointInfo's QoS in rosbag2's metadata vocabulary."""
    q = info.qos_profile
    return QosProfile(
        history=q.history.name.lower(),
        depth=int(q.depth),
        reliability=q.reliability.name.lower(),
        durability=q.durability.name.lower(),
        liveliness=q.liveliness.name.lower(),
    )


class RecorderNode(LifecycleNode):
    def __init__(self) -> None:
        super().__init__("recorder")
        self.output = declare(self, "output", "", "bag directory to create (must not exist)")
        self.topics = declare(self, "topics", ["/play/steps"], "topics to record")
        self.reliability = declare(
            self, "reliability", "reliable", "subscription reliability: reliable | best_effort"
        )
        self.max_file_mb = declare(
            self, "max_file_mb", 0.0, "start a new .mcap file past this size (0 = never)"
        )
        self.max_file_s = declare(
            self, "max_file_s", 0.0, "start a new .mcap file past this duration (0 = never)"
        )
        self.compression = declare(self, "compression", "zstd", "chunk compression: zstd | none")
        self.flush_period_s = declare(
            self, "flush_period_s", 1.0, "close the open chunk this often (bounds crash loss)"
        )
        self.writer: BagWriter | None = None
        self.exit_code = 0  # 1 once the bag could not be written: run_node then ends the process with it
        self.received: dict[str, int] = {}
        self._flushed_count = 0
        self._subs: dict[str, Subscription | None] = {}
        self._own_timers = []  # created (stopped) in on_configure, run while active, destroyed in on_cleanup
        self._start_gaps = StartGaps(self)

    def on_configure(self, state: LifecycleState) -> TransitionCallbackReturn:
        try:
            require(bool(self.output) and bool(Path(self.output).name), self, "output must name a directory")
            # an empty list in a parameter file arrives as None
            require(bool(self.topics) and all(self.topics), self, "topics must list at least one topic")
            # recorded as the graph names them: "play/steps" in this node's namespace is "/play/steps"
            self.topics = [self._graph_name(topic) for topic in self.topics]
            require(
                self.reliability in ("reliable", "best_effort"), self, "reliability: reliable | best_effort"
            )
            require(self.compression in ("zstd", "none"), self, "compression: zstd | none")
            sizes = (self.max_file_mb, self.max_file_s)
            require(
                all(math.isfinite(v) and v >= 0 for v in sizes),
                self,
                "max_file_mb and max_file_s must be finite and >= 0",
            )
            require(
                math.isfinite(self.flush_period_s) and self.flush_period_s > 0,
                self,
                "flush_period_s must be finite and > 0",
            )
            self._own_timers = [
                self.create_timer(0.1, self._subscribe_discovered, autostart=False),
                self.create_timer(self.flush_period_s, self._flush, autostart=False),
            ]
            self.writer = BagWriter(
                self.output,
                max_file_bytes=int(self.max_file_mb * 1e6),
                max_file_duration_ns=int(self.max_file_s * 1e9),
                compression=self.compression,
            )
        except (ValueError, OSError) as exc:
            self.get_logger().error(str(exc))
            self._destroy_timers()  # stay unconfigured, ready for another configure
            return TransitionCallbackReturn.FAILURE
        self.get_logger().info(f"recording {', '.join(self.topics)} to {self.output}")
        return TransitionCallbackReturn.SUCCESS

    def _graph_name(self, topic: str) -> str:
        try:
            return self.resolve_topic_name(topic)
        except Exception as exc:  # rclpy's name validation errors are not ValueErrors
            raise PlaysegError(f"{self.get_name()}: invalid parameter: topics: {topic!r}: {exc}") from None

    def on_activate(self, state: LifecycleState) -> TransitionCallbackReturn:
        for timer in self._own_timers:
            timer.reset()  # (re)start
        self._subscribe_discovered()
        return super().on_activate(state)

    def _subscribe_discovered(self) -> None:
        """Subscribe to each configured topic once a publisher reveals its type."""
        missing = [t for t in self.topics if t not in self._subs]
        if not missing or self.writer is None:  # nothing to add, or writing failed: on the way out
            return
        types = dict(self.get_topic_names_and_types())
        for topic in missing:
            if topic not in types:
                continue
            type_name = types[topic][0]
            try:
                msg_class = message_class(type_name)
                publishers = self.get_publishers_info_by_topic(topic)
                offered = [_offered_profile(i) for i in publishers]
                self.writer.add_topic(topic_info(topic, type_name, qos=offered or [QosProfile()]))
            except ValueError as exc:
                self.get_logger().error(f"cannot record {topic}: {exc}")
                self._subs[topic] = None
                continue
            profile = qos.recorder_qos(self.reliability)
            latched = publishers and all(
                i.qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL for i in publishers
            )
            if latched:
                profile.durability = DurabilityPolicy.TRANSIENT_LOCAL
            self.received[topic] = 0
            self._subs[topic] = self.create_subscription(
                msg_class, topic, lambda data, info, t=topic: self._on_message(t, data, info), profile,
                raw=True,
            )  # fmt: skip
            durability = " transient-local" if latched else ""
            self.get_logger().info(f"subscribed to {topic} ({type_name}){durability}")

    def _on_message(self, topic: str, data: bytes, info: dict) -> None:
        self._start_gaps.check(topic, info)
        if self.writer is None:  # writing failed earlier; the node is on its way out
            return
        try:
            self.writer.write(topic, data, self.get_clock().now().nanoseconds)
        except (OSError, BagError) as exc:
            self._give_up("recording", exc)
            return
        self.received[topic] += 1

    def _give_up(self, what: str, exc: Exception) -> None:
        """Stop writing after a write error, keeping what is on disk recoverable, and exit non-zero."""
        self.get_logger().error(
            f"{what} {self.output} failed: {exc}; everything flushed before is in "
            f"{partial_path(Path(self.output))}: `playseg bag recover {self.output}` restores it"
        )
        if self.writer is not None:
            self.writer.abandon()
            self.writer = None
        self.exit_code = 1

    def _flush(self) -> None:
        """Close the open chunk; everything received so far then survives a crash."""
        if self.writer is None:
            return
        try:
            self.writer.flush()
        except (OSError, BagError) as exc:
            self._give_up("flushing", exc)
            return
        total = sum(self.received.values())
        if total != self._flushed_count:
            self._flushed_count = total
            self.get_logger().debug(f"flushed: {total} messages on disk")

    def on_deactivate(self, state: LifecycleState) -> TransitionCallbackReturn:
        for timer in self._own_timers:
            timer.cancel()
        writing = self.writer is not None
        for topic, sub in self._subs.items():
            if sub is not None:
                # what DDS delivered (and acknowledged) but the executor has not handed over yet
                drained = take_queued(sub) if self.writer is not None else 0
                if drained:
                    self.get_logger().info(f"{topic}: recorded {drained} messages still queued at stop")
                self.destroy_subscription(sub)
        self._subs.clear()
        self._flush()
        if writing and self.writer is None:  # a write failed during this transition (logged)
            return TransitionCallbackReturn.ERROR
        return super().on_deactivate(state)

    def on_cleanup(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._destroy_timers()
        if self.writer is not None:
            try:
                self.writer.close()
            except Exception as exc:  # noqa: BLE001 -- rclpy would swallow it: log it, keep the bag
                self._give_up("finishing", exc)
                return TransitionCallbackReturn.ERROR
            self.get_logger().info(f"closed {self.output}: {self.received}")
            self.writer = None
        return TransitionCallbackReturn.SUCCESS

    def on_shutdown(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Shutdown from active or inactive finishes the bag as deactivate and cleanup do."""
        result = TransitionCallbackReturn.SUCCESS
        if state.label == "active":
            result = self.on_deactivate(state)
        if state.label in ("active", "inactive"):
            cleaned = self.on_cleanup(state)
            if result == TransitionCallbackReturn.SUCCESS:
                result = cleaned
        return result

    def on_error(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Error processing ends in unconfigured: release everything so configure can start afresh."""
        for sub in self._subs.values():
            if sub is not None:
                self.destroy_subscription(sub)
        self._subs.clear()
        self.on_cleanup(state)  # a failure is logged and sets exit_code
        return TransitionCallbackReturn.SUCCESS

    def _destroy_timers(self) -> None:
        for timer in self._own_timers:
            self.destroy_timer(timer)
        self._own_timers = []


def main(args: list[str] | None = None) -> int:
    return run_node(RecorderNode, args)


if __name__ == "__main__":
    raise SystemExit(main())
