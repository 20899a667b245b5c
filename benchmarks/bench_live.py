"""The live pipeline under load: a play bag replayed as fast as possible into the segmenter node.

A bag_player node (rate 0 by default: as fast as subscribers take it, RELIABLE KEEP_ALL) plays the bag's
/play/steps into a segmenter node. This process subscribes to /play/steps and /segments itself and reports:
- lost messages: PlaySteps in the bag vs received here; episodes whose final segment (ending at the
  episode's last step) arrived; LabelledSegments received vs offline `segment_episode` on the same model;
- sustained throughput: PlaySteps / (last segment received - first step received);
- latency per segment: from the arrival here of the PlayStep that decided it to the arrival of the segment.
  The deciding step is `Commit.decided_at` of an offline `StreamingSegmenter` (the node's own decoder) run
  on the same model (for the segments that `finish()` emits: the episode's last step). Arrival times are
  the middleware's receive stamps (MessageInfo.received_timestamp), not the callbacks' times.
Prints figures; not a test.

    ROS_DOMAIN_ID=150 .venv/bin/python benchmarks/bench_live.py [--bag bags/play] [--model PS.pt] [--rate 0]

Without --model: the newest build/demo/cache/ps-*.pt, else a randomly initialised default-size PS model.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import rclpy
import torch
from playseg_msgs.msg import LabelledSegment, PlayStep
from rclpy.subscription import MessageInfo

from playseg_core.checkpoint import CheckpointError
from playseg_core.data.episode import Episode
from playseg_core.data.features import STATE
from playseg_core.domains.babyai.spec import INSTRUCTIONS
from playseg_core.ps.model import PSModel, load_model, save_model
from playseg_core.ps.segmentation import segment_episode
from playseg_core.ps.streaming import StreamingSegmenter
from playseg_core.ps.training import model_config_for
from playseg_ros import qos
from playseg_ros.launch import Graph, GraphSpec, NodeSpec
from playseg_ros.play_bags import STEPS_TOPIC, read_play_bag, read_play_bag_info

SEGMENTS_TOPIC = "/segments"
DEMO_CACHE = Path("build/demo/cache")

SegmentKey = tuple[str, int, int]  # (episode_id, start step, end step)


@dataclass
class Offline:
    """What the same model decides offline: segments per episode and the step that decided each."""

    last_step: dict[str, int] = field(default_factory=dict)
    segments: list[SegmentKey] = field(default_factory=list)  # segment_episode, in bag order
    decided_at: dict[SegmentKey, int] = field(default_factory=dict)  # StreamingSegmenter commits


def choose_model(requested: str | None, bag: str, work: Path) -> tuple[PSModel, str, str]:
    """-> (model, checkpoint path, how it was chosen)."""
    if requested:
        model, _ = load_model(requested, kinds=("ps",))
        return model, requested, "--model"
    cached = sorted(DEMO_CACHE.glob("ps-*.pt"), key=lambda p: p.stat().st_mtime)
    why = "no build/demo/cache/ps-*.pt"
    if cached:
        try:
            model, _ = load_model(cached[-1], kinds=("ps",))
            return model, str(cached[-1]), "newest demo cache checkpoint"
        except CheckpointError as error:  # a cache written by an older model version
            why = f"{cached[-1]} does not load with the current model code ({type(error).__name__})"
    info = read_play_bag_info(bag)
    if info.features is None:
        raise SystemExit(f"{bag}: the bag declares no features; pass --model")
    instructions = list(info.instructions or INSTRUCTIONS)
    torch.manual_seed(0)
    path = work / "ps-random.pt"
    save_model(
        path,
        PSModel(
            model_config_for(info.features, info.domain, len(instructions), read_actions=False), instructions
        ),
    )
    model, _ = load_model(path, kinds=("ps",))
    return model, str(path), f"randomly initialised; {why}"


def observations(episode: Episode) -> list[dict[str, np.ndarray]]:
    """o_0 .. o_T of ``episode`` by feature, as a PlayStep carries them (cameras and the state)."""
    rows = dict(episode.images)
    if episode.state is not None:
        rows[STATE] = episode.state
    return [{name: array[t] for name, array in rows.items()} for t in range(episode.num_steps + 1)]


def offline_run(model: PSModel, episodes: list[Episode]) -> Offline:
    offline = Offline()
    for episode in episodes:
        offline.last_step[episode.episode_id] = episode.num_steps
        offline.segments += [(episode.episode_id, s.start, s.end) for s in segment_episode(model, episode)]
        streaming = StreamingSegmenter(model)
        for t, observation in enumerate(observations(episode)):
            streaming.push(observation, episode.actions[t] if t < episode.num_steps else None)
        streaming.finish()
        for commit in streaming.decoder.commits:
            offline.decided_at[(episode.episode_id, commit.start, commit.end)] = commit.decided_at
    return offline


class Listener:
    """This process's subscriptions to /play/steps and /segments, stamped with DDS receive times."""

    def __init__(self) -> None:
        rclpy.init()
        self.node = rclpy.create_node("bench_live")
        self.step_time: dict[tuple[str, int], int] = {}  # (episode, step) -> receive time, ns
        # In arrival order: (key, receive time, header stamp = the segmenter's publish time), ns.
        self.segments: list[tuple[SegmentKey, int, int]] = []
        self.steps_sub = self.node.create_subscription(PlayStep, STEPS_TOPIC, self._on_step, qos.PLAY_STEPS)
        self.segments_sub = self.node.create_subscription(
            LabelledSegment, SEGMENTS_TOPIC, self._on_segment, qos.SEGMENTS
        )

    def _on_step(self, msg: PlayStep, info: MessageInfo) -> None:
        self.step_time[(msg.episode_id, msg.step)] = info["received_timestamp"]

    def _on_segment(self, msg: LabelledSegment, info: MessageInfo) -> None:
        key = (msg.episode_id, msg.start_step, msg.end_step)
        stamp = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
        self.segments.append((key, info["received_timestamp"], stamp))

    def spin_until(
        self, condition: Callable[[], bool], timeout_s: float, alive: subprocess.Popen | None = None
    ) -> bool:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline and not condition():
            if alive is not None and alive.poll() is not None:
                break
            rclpy.spin_once(self.node, timeout_sec=0.05)
        return condition()

    def close(self) -> None:
        self.node.destroy_node()
        rclpy.try_shutdown()


def start_node(kind: str, work: Path, **parameters: object) -> Graph:
    """One node process logging to work/<kind>.log (the `playseg up` machinery)."""
    graph = Graph(GraphSpec([NodeSpec(kind, kind, parameters)], shutdown_timeout_s=15), log_dir=work)
    graph.start()
    return graph


def live_run(args: argparse.Namespace, model_path: str, offline: Offline, work: Path) -> Listener:
    listener = Listener()
    segmenter = start_node("segmenter", work, model=str(model_path))
    player = None
    try:
        ready = lambda: (  # noqa: E731  the segmenter listens to steps and publishes segments to us
            listener.node.count_subscribers(STEPS_TOPIC) >= 2
            and listener.segments_sub.get_publisher_count() >= 1
        )
        if not listener.spin_until(ready, 60, segmenter.processes["segmenter"]):
            raise SystemExit(f"segmenter did not come up:\n{(work / 'segmenter.log').read_text()}")
        player = start_node(
            "bag_player",
            work,
            bag=str(args.bag),
            rate=float(args.rate),
            topics=[STEPS_TOPIC],
            wait_for_subscribers=2,  # the segmenter and this process
        )
        ended = lambda: {key[0] for key, _, _ in listener.segments if key[2] == offline.last_step[key[0]]}  # noqa: E731
        total_steps = sum(n + 1 for n in offline.last_step.values())
        done = lambda: len(ended()) == len(offline.last_step) and len(listener.step_time) >= total_steps  # noqa: E731
        if not listener.spin_until(done, args.timeout, segmenter.processes["segmenter"]):
            print(f"incomplete after {args.timeout} s; segmenter log tail:", file=sys.stderr)
            print((work / "segmenter.log").read_text()[-2000:], file=sys.stderr)
        listener.spin_until(lambda: False, 0.5)  # stragglers (there should be none)
    finally:
        for graph in (player, segmenter):
            if graph is not None:
                graph.stop()
    return listener


def report(args: argparse.Namespace, model_info: str, offline: Offline, listener: Listener) -> None:
    total_steps = sum(n + 1 for n in offline.last_step.values())
    received_steps = len(listener.step_time)
    live_keys = [key for key, _, _ in listener.segments]
    finals = {key[0] for key in live_keys if key[2] == offline.last_step[key[0]]}
    same = sorted(live_keys) == sorted(offline.segments)

    latencies_ms, delivery_ms, unmatched = [], [], 0
    for key, received, stamp in listener.segments:
        delivery_ms.append((received - stamp) / 1e6)
        decided_step = (key[0], offline.decided_at.get(key, -1))
        if decided_step not in listener.step_time:
            unmatched += 1
            continue
        latencies_ms.append((received - listener.step_time[decided_step]) / 1e6)
    delays = [offline.decided_at[key] - key[2] for key in offline.segments if key in offline.decided_at]
    span_s = (max(t for _, t, _ in listener.segments) - min(listener.step_time.values())) / 1e9
    throughput = received_steps / span_s
    arrival_s = (max(listener.step_time.values()) - min(listener.step_time.values())) / 1e9

    def pct(values: list[float], q: float) -> float:
        return float(np.percentile(values, q)) if values else float("nan")

    rows = [
        (
            "PlaySteps in bag / received",
            f"{total_steps} / {received_steps}",
            f"lost {total_steps - received_steps}",
        ),
        ("episodes with final segment", f"{len(finals)} / {len(offline.last_step)}", ""),
        (
            "LabelledSegments live / offline",
            f"{len(live_keys)} / {len(offline.segments)}",
            f"boundaries equal: {'yes' if same else 'NO'}",
        ),
        (
            "throughput (steps/s)",
            f"{throughput:.0f}",
            f"{received_steps} steps in {span_s:.2f} s (all steps arrived here within {arrival_s:.2f} s)",
        ),
        (
            "latency step -> segment (ms)",
            f"p50 {pct(latencies_ms, 50):.1f}  p99 {pct(latencies_ms, 99):.1f}  max {max(latencies_ms, default=float('nan')):.1f}",
            f"{len(latencies_ms)} segments" + (f", {unmatched} unmatched" if unmatched else ""),
        ),
        (
            "  of which delivery (ms)",
            f"p50 {pct(delivery_ms, 50):.1f}  p99 {pct(delivery_ms, 99):.1f}",
            "segment header stamp (publish) -> received here",
        ),
        (
            "decision delay (steps)",
            f"p50 {pct(delays, 50):.0f}  p99 {pct(delays, 99):.0f}",
            "decided_at - end",
        ),
    ]
    print(f"bag {args.bag}: {len(offline.last_step)} episodes, {total_steps} PlaySteps; rate {args.rate}")
    print(f"model {model_info}")
    width = max(len(r[0]) for r in rows)
    value_width = max(len(r[1]) for r in rows)
    for name, value, note in rows:
        print(f"{name:<{width}}  {value:<{value_width}}  {note}".rstrip())
    ok = total_steps == received_steps and len(finals) == len(offline.last_step) and same
    print(
        f"summary: {'OK' if ok else 'FAIL'} lost {total_steps - received_steps} steps, "
        f"{len(finals)}/{len(offline.last_step)} final segments, {len(live_keys)}/{len(offline.segments)} "
        f"segments; {throughput:.0f} steps/s; latency p50 {pct(latencies_ms, 50):.1f} ms "
        f"p99 {pct(latencies_ms, 99):.1f} ms max {max(latencies_ms, default=float('nan')):.1f} ms; "
        f"decision delay p50 {pct(delays, 50):.0f} p99 {pct(delays, 99):.0f} steps"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--bag", default="bags/play", help="play bag to replay")
    parser.add_argument("--model", help="PS checkpoint (default: newest demo cache one, else random)")
    parser.add_argument("--rate", type=float, default=0.0, help="bag_player rate (0 = as fast as possible)")
    parser.add_argument("--timeout", type=float, default=300.0, help="seconds to wait for the last segment")
    args = parser.parse_args()
    os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    os.environ.setdefault("ROS_DOMAIN_ID", str(100 + os.getpid() % 100))
    with tempfile.TemporaryDirectory() as tmp:
        model, model_path, how = choose_model(args.model, args.bag, Path(tmp))
        torch.set_num_threads(1)  # as the segmenter node (torch_threads 1)
        started = time.perf_counter()
        offline = offline_run(model, read_play_bag(args.bag))
        print(
            f"offline reference (segment_episode + StreamingSegmenter): {time.perf_counter() - started:.1f} s"
        )
        listener = live_run(args, model_path, offline, Path(tmp))
        try:
            report(args, f"{model_path} ({how}, L_max {model.max_len})", offline, listener)
        finally:
            listener.close()


if __name__ == "__main__":
    main()
