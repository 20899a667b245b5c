"""play_source: a BabyAI bot "teleoperator" publishing play as PlayStep at a set rate.

Episodes come from `playseg_core.domains.babyai.play.generate_episode` (seeds seed, seed+1, ...). For a chosen share of
its segments it also publishes an Annotation (the human label a teleoperator would add) and, for
evaluation, every ground-truth segment on `ground_truth_topic`. Annotations are published when their
segment's last step has been published.
"""

from __future__ import annotations

import numpy as np
from playseg_msgs.msg import Annotation, PlayStep
from rclpy.node import Node

from playseg_core.domains.babyai.play import PlayConfig, generate_episode
from playseg_ros import qos
from playseg_ros.messages import RCLPY, annotation_message, episode_step_message
from playseg_ros.nodes.common import declare, require, run_node


class PlaySourceNode(Node):
    def __init__(self) -> None:
        super().__init__("play_source")
        self.rate_hz = declare(self, "rate_hz", 10.0, "PlaySteps per second")
        self.seed = declare(self, "seed", 0, "seed of the first episode (then seed+1, ...)")
        self.num_episodes = declare(self, "num_episodes", 0, "stop after this many episodes (0 = forever)")
        self.annotate_share = declare(
            self, "annotate_share", 0.1, "share of segments published as Annotation"
        )
        num_objects = declare(self, "num_objects", 7, "objects in the BabyAI room")
        steps_topic = declare(self, "steps_topic", "/play/steps", "PlayStep output topic")
        annotations_topic = declare(self, "annotations_topic", "/play/annotations", "Annotation output topic")
        truth_topic = declare(self, "ground_truth_topic", "/play/ground_truth", "ground truth ('' = off)")
        self.wait_for_subscribers = declare(
            self,
            "wait_for_subscribers",
            0,
            "start publishing once the steps topic has N subscribers (steps are volatile: a subscriber "
            "that joins later misses the steps before it)",
        )
        require(self.rate_hz > 0, self, "rate_hz must be > 0")
        require(0.0 <= self.annotate_share <= 1.0, self, "annotate_share must be in [0, 1]")
        require(self.num_episodes >= 0, self, "num_episodes must be >= 0")
        require(self.wait_for_subscribers >= 0, self, "wait_for_subscribers must be >= 0")
        self.config = PlayConfig(num_objects=num_objects)
        self.rng = np.random.default_rng(self.seed)
        self.steps_pub = self.create_publisher(PlayStep, steps_topic, qos.PLAY_STEPS)
        self.annotation_pub = self.create_publisher(Annotation, annotations_topic, qos.ANNOTATIONS)
        self.truth_pub = (
            self.create_publisher(Annotation, truth_topic, qos.ANNOTATIONS) if truth_topic else None
        )
        self.episodes_done = 0
        self.episode = None
        self.t = 0
        self.started = self.wait_for_subscribers == 0
        self.create_timer(1.0 / self.rate_hz, self.publish_next_step)

    def _next_episode(self) -> None:
        seed = self.seed + self.episodes_done
        self.episode = generate_episode(self.config, seed)
        while self.episode.num_steps == 0:  # the bot failed its first task: no play to publish
            seed += 10_000_000
            self.episode = generate_episode(self.config, seed)
        self.annotated = {s for s in self.episode.segments if self.rng.random() < self.annotate_share}
        self.t = 0

    def publish_next_step(self) -> None:
        if self.num_episodes and self.episodes_done >= self.num_episodes:
            return
        if not self.started:
            if self.steps_pub.get_subscription_count() < self.wait_for_subscribers:
                return
            self.started = True
            self.get_logger().info(f"{self.steps_pub.get_subscription_count()} subscribers: starting")
        if self.episode is None:
            self._next_episode()
        stamp = self.get_clock().now().nanoseconds
        self.steps_pub.publish(episode_step_message(self.episode, self.t, stamp, "babyai", RCLPY))
        for seg in self.episode.segments:
            if seg.end == self.t:
                if seg in self.annotated:
                    self.annotation_pub.publish(self._annotation(seg, stamp))
                if self.truth_pub is not None:
                    self.truth_pub.publish(self._annotation(seg, stamp))
        if self.t == self.episode.num_steps:
            self.episodes_done += 1
            self.episode = None
            if self.num_episodes and self.episodes_done >= self.num_episodes:
                self.get_logger().info(f"published {self.episodes_done} episodes")
        else:
            self.t += 1

    def _annotation(self, seg, stamp: int) -> Annotation:
        return annotation_message(self.episode.episode_id, seg, stamp, "babyai", RCLPY)


def main(args: list[str] | None = None) -> int:
    return run_node(PlaySourceNode, args)


if __name__ == "__main__":
    raise SystemExit(main())
