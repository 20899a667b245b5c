"""bag_player: publishes a bag's messages at recorded speed, a multiple of it, or as fast as possible
(there is no `ros2 bag play` in the package registry).

`rate` 1.0 = recorded speed, 2.0 = twice as fast, 0 = as fast as possible. Steps and segments are
reliable KEEP_ALL on both sides, so nothing is dropped: a subscriber slower than the player queues the
backlog in its reader (benchmarks/bench_live.py measures the resulting latency).
`wait_for_subscribers` delays the start until each of `wait_topics` (default: the PlayStep topics) has that
many subscribers, or `TOPIC=N` entries their own N (volatile topics have no history for late joiners);
`playseg up` sets them from the graph when a config leaves both out (playseg_ros/wiring.py). Annotation topics are published transient-local.
`clock` publishes the recording's time on /clock before each message, like `ros2 bag play --clock` (which
publishes it at a fixed rate instead): a node with `use_sim_time` then reads the recording's time from
its clock, which is what gives a message without a header (a `geometry_msgs/Twist` command) its
recorded time in a replay; the player waits for /clock subscribers too.

A bag that cannot be read to its end (a damaged or truncated file) ends the node with exit code 1 after
what could be read was published (and delivered), so `playseg up` reports it instead of a silent
partial playback; a bag that cannot even be opened is a bad parameter (exit code 2).
"""

from __future__ import annotations

import threading
import time

import rclpy
from builtin_interfaces.msg import Time
from rclpy.node import Node
from rosgraph_msgs.msg import Clock

from playseg_ros import qos
from playseg_ros.bag import BagReader
from playseg_ros.nodes.common import declare, require, run_node, wait_delivered
from playseg_ros.ros_types import message_class
from playseg_ros.typestore import as_current_cdr, playseg_typestore, typestore_for


class BagPlayerNode(Node):
    def __init__(self) -> None:
        super().__init__("bag_player")
        self.bag = declare(self, "bag", "", "bag directory to play")
        self.rate = declare(self, "rate", 1.0, "speed multiple of the recording; 0 = as fast as possible")
        topics = declare(self, "topics", [""], "topics to play (empty = all)")
        self.wait_for_subscribers = declare(
            self, "wait_for_subscribers", 0, "start once each of wait_topics has this many subscribers"
        )
        wait_topics = declare(
            self,
            "wait_topics",
            [""],
            "topics to wait on (empty = the PlayStep topics); TOPIC=N waits for N subscribers on that one "
            "(playseg up sets these from the graph: every subscription its nodes make to what is played)",
        )
        self.exit_when_done = declare(
            self, "exit_when_done", True, "shut down once subscribers acknowledged the last message"
        )
        self.delivery_timeout_s = declare(
            self, "delivery_timeout_s", 300.0, "at the end, wait this long at most for acknowledgements"
        )
        publish_clock = declare(
            self, "clock", False, "publish the recording's time on /clock before each message (use_sim_time)"
        )
        require(bool(self.bag), self, "bag must be set")
        require(self.rate >= 0, self, "rate must be >= 0")
        require(
            0 <= self.delivery_timeout_s < float("inf"), self, "delivery_timeout_s must be finite and >= 0"
        )
        topics = topics or []  # an empty list in a parameter file arrives as None
        wait_topics = wait_topics or []
        self.reader = BagReader(self.bag)
        wanted = [t for t in topics if t]
        unknown = sorted(set(wanted) - set(self.reader.topics))
        require(not unknown, self, f"topics {unknown} are not in bag {self.bag}")
        self.topic_types = {t: ty for t, ty in self.reader.topics.items() if not wanted or t in wanted}
        self.clock_publisher = self.create_publisher(Clock, "/clock", 10) if publish_clock else None
        self.publishers_by_topic = {}
        for topic, type_name in self.topic_types.items():
            profile = (
                qos.ANNOTATIONS if type_name.endswith(("/Annotation", "/TimedAnnotation")) else qos.PLAY_STEPS
            )
            self.publishers_by_topic[topic] = self.create_publisher(message_class(type_name), topic, profile)
        # playseg_msgs recorded in an earlier definition are re-encoded in today's as they are played.
        self.earlier_definition: dict[str, tuple[str, str]] = {}
        for topic, type_name in self.topic_types.items():
            digest = self.reader.topic_hash(topic)
            if type_name.startswith("playseg_msgs/"):
                store = typestore_for(type_name, digest)
                require(
                    store is not None, self, f"{topic} in {self.bag}: unknown {type_name} (hash {digest})"
                )
                if store is not playseg_typestore():
                    self.earlier_definition[topic] = (type_name, digest)
        self.wait_counts = self._wait_counts([t for t in wait_topics if t], publish_clock)
        self.published = 0
        self.exit_code = 0  # 1 when the bag could not be played to its end (run_node exits with it)
        self._closing = False
        self.done = threading.Event()
        # Played once the node spins: a short bag played from here could end (and shut the context down)
        # before run_node has made its executor.
        self._start_timer = self.create_timer(0.0, self._start_playback)

    def _start_playback(self) -> None:
        self.destroy_timer(self._start_timer)
        threading.Thread(target=self._play, daemon=True).start()

    def _play(self) -> None:
        try:
            self._wait_for_subscribers()
            first_log, started = None, time.monotonic()
            for message in self.reader.messages(list(self.topic_types)):
                if not rclpy.ok():
                    return
                if self.rate > 0:
                    first_log = message.log_time_ns if first_log is None else first_log
                    due = started + (message.log_time_ns - first_log) / 1e9 / self.rate
                    time.sleep(max(0.0, due - time.monotonic()))
                if self.clock_publisher is not None:
                    seconds, nanoseconds = divmod(message.log_time_ns, 1_000_000_000)
                    self.clock_publisher.publish(Clock(clock=Time(sec=seconds, nanosec=nanoseconds)))
                data = message.data
                if message.topic in self.earlier_definition:
                    data = as_current_cdr(data, *self.earlier_definition[message.topic])
                self.publishers_by_topic[message.topic].publish(data)
                self.published += 1
            self.get_logger().info(f"played {self.published} messages from {self.bag}")
        except Exception as exc:  # noqa: BLE001 -- reported, then the node ends with exit code 1
            if self._closing:  # stopped from outside: the reader was closed under the playback
                return
            self.get_logger().error(f"playback of {self.bag} failed after {self.published} messages: {exc}")
            failed = True
        else:
            failed = False
        finally:
            self.done.set()
        if self.exit_when_done or failed:
            self._wait_until_delivered()  # what was published before the damage still reaches everyone
            self.exit_code = int(failed)
            rclpy.try_shutdown()

    def _wait_until_delivered(self) -> None:
        """Reliable messages not yet acknowledged die with the process: wait until every subscriber's
        reader holds them (a slow subscriber queues them there), at most `delivery_timeout_s`."""
        wait_delivered(self, self.publishers_by_topic.values(), self.delivery_timeout_s)

    def _wait_counts(self, entries: list[str], publish_clock: bool) -> dict[str, int]:
        """Subscribers to wait for, by topic: `TOPIC=N` entries, plain ones (or the PlayStep topics) with
        `wait_for_subscribers`; with `clock`, /clock too (a node on sim time must see the first one: it
        times the first message)."""
        counts: dict[str, int] = {}
        for entry in entries or [
            t for t, ty in self.topic_types.items() if ty == "playseg_msgs/msg/PlayStep"
        ]:
            topic, sep, number = entry.partition("=")
            require(
                not sep or (number.isdigit() and bool(topic)),
                self,
                f"wait_topics entry {entry!r}: TOPIC or TOPIC=N",
            )
            counts[topic] = int(number) if sep else self.wait_for_subscribers
        played = set(self.topic_types) | ({"/clock"} if publish_clock else set())
        unknown = sorted(set(counts) - played)
        require(not unknown, self, f"wait_topics {unknown} are not played")
        if publish_clock and "/clock" not in counts:
            counts["/clock"] = self.wait_for_subscribers
        return {topic: n for topic, n in counts.items() if n > 0}

    def _wait_for_subscribers(self) -> None:
        publishers = {**self.publishers_by_topic, "/clock": self.clock_publisher}
        while rclpy.ok() and any(
            publishers[topic].get_subscription_count() < n for topic, n in self.wait_counts.items()
        ):
            time.sleep(0.05)

    def close(self) -> None:
        self._closing = True
        self.reader.close()


def main(args: list[str] | None = None) -> int:
    return run_node(BagPlayerNode, args)


if __name__ == "__main__":
    raise SystemExit(main())
