"""A fleet live: N robots streaming standard messages at their own rates into the segmentation server.

Each robot is its own process publishing, in real time, the play of benchmarks/generic_robot.py's arm:
a 96x96 rgb8 camera at 30 Hz (sensor_msgs/Image), JointState at 100 Hz (7 joints) and a header-less
Twist command at 30 Hz (half a frame ahead of the camera, as its own clock), on /robotI/... topics,
into its own topic_adapter (one PlayStep per camera frame; joints 'nearest', the command 'previous').
Server side: one segmenter per robot (default) or one shared segmenter reading every robot's steps
(`--shared`: the adapters publish to one topic, episodes told apart by their ids), and one recorder of
every step and segment. All nodes are real processes on real DDS (localhost, this machine's cores).

Reported per N: steps lost (camera frames published - PlaySteps received by this process, itself one
more RELIABLE reader of every step topic), segments live against the same model offline on those steps,
and the latency from the last input message of the step that decided a segment (`Commit.decided_at` of
the node's own streaming decoder run offline on those steps; a step's last input is the first message of
each topic later than the step's time plus that feature's tolerance, which the adapter waits for) to the
LabelledSegment's arrival here, p50 / p99 / max, split into the adapter's part (last input -> PlayStep
here) and the segmenter's (that PlayStep -> segment here); segments decided by an episode's end are
counted apart (the stream's end is the adapter's idle timeout). Send times are taken just before each
publish. Also the CPU each kind of process used over the streaming window (percent of one core).

    ROS_DOMAIN_ID=151 .venv/bin/python benchmarks/bench_fleet.py [--robots 1,2,5,10] [--seconds 20] [--shared] [--reference]

The model: PS trained by `playseg train` (at most --train-minutes) on five 30 s bags of the same kind of
play with every skill labelled, saved to --model and reused by later runs.

Prints figures; not a test.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import yaml
from generic_robot import JOINT_HZ, JOINT_NAMES, Camera, Play, write_robot_bag

FPS, SIZE = 30, 96
CAMERA = "observation.images.front"
LATENCY_BUDGET_MS = 50.0
TAIL_S = 0.2
"""Joints and commands go on this long after the last frame, as a robot's do: its step has its inputs."""


def mapping(robot: str) -> dict:
    return {
        "fps": FPS,
        "primary": CAMERA,
        "tolerance_ms": 20,
        "features": {
            CAMERA: {"topic": f"/{robot}/camera/image_raw"},
            "observation.state": {"topic": f"/{robot}/joint_states", "field": "position"},
            "action": {
                "topic": f"/{robot}/cmd_vel",
                "fields": ["linear.x", "angular.z"],
                "align": "previous",
                "tolerance_ms": 50,
            },
        },
    }


# --- the robot: a process publishing its sensors in real time ----------------------------------------


def run_robot(robot: str, seconds: float, start_at: float, times_out: Path) -> None:
    """Publish ``robot``'s camera, joints and commands from wall time ``start_at`` for ``seconds``; write
    each camera frame's stamp -> its publish time (ns) to ``times_out``."""
    import rclpy
    from geometry_msgs.msg import Twist
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import Image, JointState

    rclpy.init()
    node = rclpy.create_node(f"{robot}_driver")
    profile = QoSProfile(depth=50, reliability=ReliabilityPolicy.RELIABLE)
    camera = node.create_publisher(Image, f"/{robot}/camera/image_raw", profile)
    joints = node.create_publisher(JointState, f"/{robot}/joint_states", profile)
    command = node.create_publisher(Twist, f"/{robot}/cmd_vel", profile)
    deadline = time.monotonic() + 120
    while any(p.get_subscription_count() < 1 for p in (camera, joints, command)):
        if time.monotonic() > deadline:
            raise SystemExit(f"{robot}: no topic_adapter subscribed within 120 s")
        time.sleep(0.05)
    play, view = Play(int(robot.removeprefix("robot")) + 1, seconds), Camera(SIZE, SIZE)
    published: dict[int, int] = {}  # camera stamp -> wall time sent, ns
    sent: dict[str, list[tuple[int, int]]] = {"joints": [], "command": []}  # (message time, wall time sent)
    time.sleep(max(0.0, start_at - time.time()))
    began, cpu_began = time.monotonic(), time.process_time()
    frames = joint_ticks = commands = 0
    while True:
        now = time.monotonic() - began
        if now >= seconds + TAIL_S:
            break
        # the teleop's commands at k / FPS, the camera's frames half a period later (own clocks); the
        # camera stops at `seconds`, the joints and commands a little later (the last frame's neighbours)
        due = {"joint": joint_ticks / JOINT_HZ, "command": commands / FPS}
        if (frames + 0.5) / FPS < seconds:
            due["frame"] = (frames + 0.5) / FPS
        if now < min(due.values()):
            time.sleep(min(due.values()) - now)
            continue
        stamp = node.get_clock().now().to_msg()
        if due["joint"] <= now:
            msg = JointState()
            msg.header.stamp = stamp
            msg.name = list(JOINT_NAMES)
            msg.position = play.joints(now).tolist()
            sent["joints"].append((stamp.sec * 1_000_000_000 + stamp.nanosec, time.time_ns()))
            joints.publish(msg)
            joint_ticks += 1
        if due["command"] <= now:
            twist = Twist()
            linear, angular = twist.linear, twist.angular
            linear.x, linear.y, linear.z, angular.x, angular.z = play.command(now)
            sent["command"].append((node.get_clock().now().nanoseconds, time.time_ns()))  # stamped on arrival
            command.publish(twist)
            commands += 1
        if due.get("frame", now + 1) <= now:
            image = Image()
            image.header.stamp, image.header.frame_id = stamp, "camera"
            image.height, image.width, image.encoding, image.step = SIZE, SIZE, "rgb8", SIZE * 3
            image.data = view.image(*play.pose(now)).tobytes()
            published[stamp.sec * 1_000_000_000 + stamp.nanosec] = time.time_ns()
            camera.publish(image)
            frames += 1
    cpu = time.process_time() - cpu_began
    frames_sent = {str(k): v for k, v in published.items()}
    times_out.write_text(json.dumps({"cpu_s": cpu, "published": frames_sent, "sent": sent}))
    time.sleep(1.0)  # reliable delivery of the last messages before the publishers go
    node.destroy_node()
    rclpy.try_shutdown()


# --- the server side and the measurement -------------------------------------------------------------


@dataclass
class Listener:
    """This process's subscriptions to every steps and segments topic, stamped on arrival."""

    steps_topics: list[str]
    segments_topics: list[str]
    step_arrival: dict[tuple[str, int], tuple[int, int]] = field(default_factory=dict)  # -> (recv, stamp)
    step_messages: dict[str, list] = field(default_factory=dict)  # episode -> its PlaySteps, in order
    segments: list[tuple[tuple[str, int, int], int]] = field(default_factory=list)

    def start(self) -> None:
        import rclpy
        from playseg_msgs.msg import LabelledSegment, PlayStep
        from rclpy.executors import SingleThreadedExecutor

        from playseg_ros import qos

        self.context = rclpy.Context()
        rclpy.init(context=self.context)
        self.node = rclpy.create_node("bench_fleet", context=self.context)
        for topic in self.steps_topics:
            self.node.create_subscription(PlayStep, topic, self._on_step, qos.PLAY_STEPS)
        self.segment_subs = [
            self.node.create_subscription(LabelledSegment, topic, self._on_segment, qos.SEGMENTS)
            for topic in self.segments_topics
        ]
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.running = True
        self.thread = threading.Thread(target=self._spin, daemon=True)
        self.thread.start()

    def _spin(self) -> None:
        while self.running:
            self.executor.spin_once(timeout_sec=0.05)

    def _on_step(self, msg, info) -> None:
        stamp = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
        self.step_arrival[(msg.episode_id, msg.step)] = (time.time_ns(), stamp)
        self.step_messages.setdefault(msg.episode_id, []).append(msg)

    def _on_segment(self, msg, info) -> None:
        self.segments.append(((msg.episode_id, msg.start_step, msg.end_step), time.time_ns()))

    def close(self) -> None:
        self.running = False
        self.thread.join()
        self.node.destroy_node()
        self.context.try_shutdown()


STATE = "observation.state"


def cpu_seconds(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def make_model(work: Path, bags: int, seconds: float, minutes: float) -> Path:
    """A PS model that `playseg train` learns from ``bags`` recorded bags of ``seconds`` of play each
    (other seeds than the fleet's robots), every skill labelled."""
    from playseg_ros.cli import main as cli

    for number in range(bags):
        bag = work / "probe_bags" / f"bag{number}"
        write_robot_bag(bag, Play(1000 + number, seconds), camera=Camera(SIZE, SIZE), seed=number)
    (work / "probe.yaml").write_text(
        yaml.safe_dump(mapping("robot0") | {"annotations": {"file": "labels.yaml"}})
    )
    if cli(
        [
            "convert",
            str(work / "probe_bags"),
            "--out",
            str(work / "probe"),
            "--mapping",
            str(work / "probe.yaml"),
            "--quiet",
        ]
    ):
        raise SystemExit("could not convert the probe bags")
    path = work / "fleet-ps.pt"
    if cli(["train", "--data", str(work / "probe"), "--out", str(path), "--max-minutes", str(minutes)]):
        raise SystemExit("could not train on the probe bags")
    return path


def last_inputs(report: dict) -> dict[int, int]:
    """Camera stamp of each step -> wall time its last input message was sent. The adapter's rule
    (docs/convert.md): a step's own inputs are there once each topic has a message later than the step's
    time plus that feature's tolerance; it is published once the next step's are there too (the PlayStep
    carries the action up to the next step and whether it is the last). Steps whose inputs run past the
    stream's end are left out (they wait for the end)."""
    frames = sorted((int(stamp), sent) for stamp, sent in report["published"].items())
    streams = {
        "frame": (frames, mapping("")["tolerance_ms"]),
        "joints": (report["sent"]["joints"], mapping("")["tolerance_ms"]),
        "command": (report["sent"]["command"], mapping("")["features"]["action"]["tolerance_ms"]),
    }
    times = {name: np.array([t for t, _ in messages]) for name, (messages, _) in streams.items()}
    own: list[int | None] = []
    for stamp, _ in frames:
        latest: int | None = 0
        for name, (messages, tolerance_ms) in streams.items():
            index = int(np.searchsorted(times[name], stamp + tolerance_ms * 1_000_000, side="right"))
            if index == len(messages):
                latest = None
                break
            latest = max(latest, messages[index][1])
        own.append(latest)
    return {
        stamp: max(mine, following)
        for (stamp, _), mine, following in zip(frames, own, own[1:], strict=False)
        if mine is not None and following is not None
    }


def decisions(model, episodes: list) -> dict:
    """Per segment (episode, start, end): the step after which the node's streaming decoder (with the
    node's L_min, the model's) could publish it."""
    from playseg_core.ps.streaming import StreamingSegmenter

    decided: dict[tuple[str, int, int], int] = {}
    for episode in episodes:
        streaming = StreamingSegmenter(model, model.cfg.min_len)
        for t in range(episode.num_steps + 1):
            observation = {name: frames[t] for name, frames in episode.images.items()}
            if episode.state is not None:
                observation[STATE] = episode.state[t]
            streaming.push(observation, episode.actions[t] if t < episode.num_steps else None)
        streaming.finish()
        for commit in streaming.decoder.commits:
            decided[(episode.episode_id, commit.start, commit.end)] = commit.decided_at
    return decided


def run_fleet(robots: int, seconds: float, shared: bool, reference: bool, model: Path, work: Path) -> dict:
    from playseg_ros.launch import Graph, GraphSpec, NodeSpec
    from playseg_ros.messages import EpisodeBuilder

    names = [f"robot{i}" for i in range(robots)]
    nodes: list[NodeSpec] = []
    steps_topics = ["/fleet/play/steps"] if shared else [f"/{r}/play/steps" for r in names]
    segments_topics = ["/fleet/segments"] if shared else [f"/{r}/segments" for r in names]
    for i, robot in enumerate(names):
        path = work / f"{robot}.yaml"
        path.write_text(yaml.safe_dump(mapping(robot)))
        steps = steps_topics[0 if shared else i]
        nodes.append(NodeSpec(f"{robot}_adapter", "topic_adapter", {
            "mapping": str(path), "episode_id": robot, "steps_topic": steps,
            "wait_for_subscribers": 3, "idle_timeout_s": 2.0,
        }))  # fmt: skip
    recorded = work / "recorded"
    form = {"segment_form": "reference", "recording_bag": str(recorded)} if reference else {}
    for i, steps in enumerate(steps_topics):
        nodes.append(NodeSpec(f"segmenter{i}", "segmenter", {
            "model": str(model), "steps_topic": steps, "segments_topic": segments_topics[i],
            "wait_for_subscribers": 2, **form,
        }))  # fmt: skip
    nodes.append(
        NodeSpec("recorder", "recorder", {"output": str(recorded), "topics": steps_topics + segments_topics})
    )
    listener = Listener(steps_topics, segments_topics)
    listener.start()
    graph = Graph(GraphSpec(nodes, shutdown_timeout_s=60), log_dir=work)
    graph.start()
    start_at = time.time() + 8.0 + robots  # every robot's adapter subscribed by then
    drivers = {
        robot: subprocess.Popen(
            [sys.executable, __file__, "robot", robot, str(seconds), str(start_at), str(work / f"{robot}.times.json")],
            stdout=open(work / f"{robot}.driver.log", "wb"), stderr=subprocess.STDOUT,
        )
        for robot in names
    }  # fmt: skip
    time.sleep(max(0.0, start_at - time.time()))
    pids = {name: proc.pid for name, proc in graph.processes.items()}
    cpu_before = {name: cpu_seconds(pid) for name, pid in pids.items()}
    time.sleep(max(0.0, start_at + seconds - time.time()))  # the streaming window, for every process
    window = seconds
    cpu_after = {name: cpu_seconds(pid) for name, pid in pids.items() if Path(f"/proc/{pid}").exists()}
    for robot, proc in drivers.items():
        if proc.wait(timeout=180) != 0:
            raise SystemExit(f"{robot} driver failed:\n{(work / f'{robot}.driver.log').read_text()[-2000:]}")
    graph.stop()  # upstream first: the adapters end their streams, the segmenters publish the last segments
    time.sleep(0.5)
    listener.close()

    import torch

    from playseg_core.ps.model import load_model

    torch.set_num_threads(1)
    ps, _ = load_model(model, kinds=("ps",))
    episodes = []
    for episode_id, messages in sorted(listener.step_messages.items()):
        builder = EpisodeBuilder(episode_id, camera=CAMERA)
        for msg in messages:
            builder.add(msg)
        episodes.append(builder.build([], truncated=not builder.finished))
    offline = decisions(ps, episodes)
    reports = {r: json.loads((work / f"{r}.times.json").read_text()) for r in names}
    published = {r: report["published"] for r, report in reports.items()}
    frames = sum(len(p) for p in published.values())
    received = {stamp for _, stamp in listener.step_arrival.values()}
    missing = []  # (robot, index of the frame in its stream, frames in its stream)
    for robot, stamps in published.items():
        order = sorted(int(stamp) for stamp in stamps)
        missing += [(robot, i, len(order)) for i, stamp in enumerate(order) if stamp not in received]
    steps = sum(e.num_steps + 1 for e in episodes)
    last_step = {e.episode_id: e.num_steps for e in episodes}
    last_input = {robot: last_inputs(report) for robot, report in reports.items()}
    total, adapter, segmenter, at_end = [], [], [], 0
    for key, arrival in listener.segments:
        decided = (key[0], offline.get(key, -1))
        if decided[1] == last_step.get(key[0]):  # decided by the episode's end: the adapter's idle timeout
            at_end += 1
            continue
        if decided not in listener.step_arrival:
            continue
        step_arrival, stamp = listener.step_arrival[decided]
        ready = last_input[key[0].split(":")[0]].get(stamp)
        if ready is None:
            continue
        total.append((arrival - ready) / 1e6)
        adapter.append((step_arrival - ready) / 1e6)
        segmenter.append((arrival - step_arrival) / 1e6)
    step_latency = [  # every step but each episode's last (which waits for the stream's end)
        (received - last_input[episode.split(":")[0]][stamp]) / 1e6
        for (episode, step), (received, stamp) in listener.step_arrival.items()
        if step < last_step.get(episode, -1) and stamp in last_input[episode.split(":")[0]]
    ]
    kinds: dict[str, float] = {"driver": sum(100 * r["cpu_s"] / window for r in reports.values())}
    for name, after in cpu_after.items():
        kind = (
            "driver"
            if name.endswith("_driver")
            else "adapter"
            if name.endswith("_adapter")
            else name.rstrip("0123456789")
        )
        kinds[kind] = kinds.get(kind, 0.0) + 100 * (after - cpu_before[name]) / window
    return {
        "robots": robots, "frames": frames, "steps": steps, "lost": frames - steps,
        "segments_live": len(listener.segments), "at_end": at_end, "step_ms": step_latency,
        "segments_offline": len(offline), "latency_ms": total, "adapter_ms": adapter,
        "segmenter_ms": segmenter, "cpu": kinds, "window_s": window, "missing": missing,
    }  # fmt: skip


def percentiles(values: list[float], with_max: bool = True) -> str:
    if not values:
        return "n/a"
    text = f"{np.percentile(values, 50):.1f} / {np.percentile(values, 99):.1f}"
    return f"{text} / {max(values):.1f}" if with_max else text


def main() -> None:
    if len(sys.argv) > 1 and sys.argv[1] == "robot":
        run_robot(sys.argv[2], float(sys.argv[3]), float(sys.argv[4]), Path(sys.argv[5]))
        return
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--robots", default="1,2,5,10", help="fleet sizes to run, comma-separated")
    parser.add_argument("--seconds", type=float, default=20.0, help="how long each robot streams")
    parser.add_argument("--shared", action="store_true", help="one segmenter for every robot")
    parser.add_argument(
        "--reference",
        action="store_true",
        help="reference-form segments (no steps inside; the recorder has them)",
    )
    parser.add_argument(
        "--model",
        default="build/bench_fleet/generic-ps.pt",
        help="the PS checkpoint (trained here if missing)",
    )
    parser.add_argument("--train-minutes", type=float, default=3.0, help="the training's --max-minutes")
    args = parser.parse_args()
    os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    os.environ.setdefault("ROS_DOMAIN_ID", str(100 + os.getpid() % 100))
    form = "reference" if args.reference else "embedded"
    print(f"{'shared segmenter' if args.shared else 'one segmenter per robot'}, {form} segments; {args.seconds:.0f} s per robot; "
          f"{os.cpu_count()} CPUs")  # fmt: skip
    with tempfile.TemporaryDirectory() as tmp:
        model = Path(args.model)
        if not model.exists():  # trained once, then reused
            model.parent.mkdir(parents=True, exist_ok=True)
            shutil.copy(make_model(Path(tmp), 5, 30.0, args.train_minutes), model)
        for robots in (int(n) for n in args.robots.split(",")):
            work = Path(tmp) / f"n{robots}"
            work.mkdir()
            r = run_fleet(robots, args.seconds, args.shared, args.reference, model, work)
            cpu = r["cpu"]
            p99 = np.percentile(r["latency_ms"], 99) if r["latency_ms"] else float("inf")
            verdict = "keeps up" if r["lost"] == 0 and p99 <= LATENCY_BUDGET_MS else "does not keep up"
            print(
                f"N={robots}: {r['frames']} frames, {r['lost']} lost; segments {r['segments_live']} live / "
                f"{r['segments_offline']} offline ({r['at_end']} decided by the episodes' end); {verdict} "
                f"(0 lost, p99 <= {LATENCY_BUDGET_MS:.0f} ms)\n"
                f"  last input -> segment, {len(r['latency_ms'])} decided while streaming (ms p50/p99/max): "
                f"{percentiles(r['latency_ms'])}; adapter part {percentiles(r['adapter_ms'], False)}, "
                f"segmenter part {percentiles(r['segmenter_ms'], False)}\n"
                f"  last input -> PlayStep, every step (ms p50/p99/max): {percentiles(r['step_ms'])}\n"
                f"  CPU, % of one core: drivers {cpu.get('driver', 0):.0f}, adapters {cpu.get('adapter', 0):.0f}, "
                f"segmenters {cpu.get('segmenter', 0):.0f}, recorder {cpu.get('recorder', 0):.0f}",
                flush=True,
            )
            if r["missing"]:
                shown = ", ".join(f"{robot} frame {i + 1} of {n}" for robot, i, n in r["missing"][:6])
                print(f"  lost: {shown}{' ...' if len(r['missing']) > 6 else ''}")


if __name__ == "__main__":
    main()
