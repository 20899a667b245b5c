"""`make demo`, the robot half: a robot's bag in standard messages, segmented live and exported for LeRobot.

1. Bring up topic_adapter (the bag's mapping file: camera, joint states and velocity commands at their own
   rates -> PlaySteps), segmenter and recorder as separate ROS 2 processes.
2. The bag player replays the long unannotated tabletop bag (bags/tabletop/tabletop-2, 30 tasks) at twice
   its recorded speed with its /clock; the segmenter publishes a LabelledSegment as soon as its online
   decoder decides one.
3. Score the recorded segments against the bag's ground truth (its sidecar, read through
   mapping_truth.yaml), exact and within 2 steps.
4. `playseg convert --format lerobot --segment MODEL` over both tabletop bags: a LeRobot v3 dataset whose
   annotated episode keeps its human labels and whose unannotated one carries the model's segments as
   per-frame instructions; check that they are the live segments.
"""

from __future__ import annotations

import json
import shutil
import sys
import time
from dataclasses import dataclass
from pathlib import Path

from playseg_core.errors import PlaysegError

PLAY_BAG = "tabletop-2"
ANNOTATED_BAG = "tabletop-0"
STREAM_TIMEOUT_S = 120.0
REPLAY_RATE = 2.0
"""Twice the recorded speed, so that 30 segments of play fit the demo's minutes. Not as fast as possible:
/cmd_vel has no header, so its time is the adapter's clock (the replay's /clock), and unthrottled the clock
runs ahead of the messages still queued in the adapter."""
RECORDER_SETTLE_S = 1.0
IDLE_TIMEOUT_S = 4.0  # the adapter ends the episode after this long without a message (the bag is over)


def _log(message: str) -> None:
    print(f"[demo {time.strftime('%H:%M:%S')}] {message}", flush=True)


class RobotHalfError(PlaysegError):
    """The robot half could not run to its end (a node or a conversion failed); the message names it."""


def robot_half_inputs(bags_dir: Path) -> list[Path]:
    """The sample files the robot half reads (checked before the demo starts)."""
    tabletop = bags_dir / "tabletop"
    return [
        tabletop / PLAY_BAG / "metadata.yaml",
        tabletop / ANNOTATED_BAG / "metadata.yaml",
        tabletop / "mapping.yaml",
        tabletop / "mapping_truth.yaml",
    ]


@dataclass
class RobotHalfResult:
    summary: dict
    table: str


def _truth_episode(play_bag: Path, mapping_truth: Path, out: Path):
    """The played bag as `playseg convert` reads it, with the ground-truth segments of its sidecar."""
    from playseg_core.data.dataset import PlayDataset
    from playseg_ros.convert import convert, load_mapping

    summary = convert([play_bag], out, load_mapping(mapping_truth), 1, True, False)
    if summary.failed:
        raise RobotHalfError(f"{play_bag}: {summary.failed[0].error}")
    return PlayDataset.open(out).episode(0)


def _stream_live(play_bag: Path, mapping: Path, model: Path, run_dir: Path, expected_steps: int) -> Path:
    """Play the bag into topic_adapter -> segmenter (recorder writes both streams); -> the recorded bag."""
    import rclpy
    from playseg_msgs.msg import LabelledSegment, PlayStep
    from rclpy.executors import SingleThreadedExecutor

    from playseg_ros import qos
    from playseg_ros.convert import load_mapping
    from playseg_ros.launch import Graph, GraphSpec, NodeSpec, player_graph

    topics = sorted({feature.topic for feature in load_mapping(mapping).topic_features})
    recorded = run_dir / "robot_bag"
    graph = Graph(
        GraphSpec(
            [
                NodeSpec("segmenter", "segmenter", {"model": str(model)}),
                NodeSpec(
                    "recorder", "recorder", {"output": str(recorded), "topics": ["/play/steps", "/segments"]}
                ),
                NodeSpec(
                    "topic_adapter",
                    "topic_adapter",
                    # The replay's /clock stamps the header-less /cmd_vel with its recorded time.
                    {
                        "mapping": str(mapping),
                        "episode_id": play_bag.name,
                        "idle_timeout_s": IDLE_TIMEOUT_S,
                        "use_sim_time": True,
                        "wait_for_subscribers": 3,  # segmenter, recorder and this process
                    },
                ),
            ]
        ),
        log_dir=run_dir / "logs",
    )
    player = player_graph(
        play_bag, run_dir / "logs", rate=REPLAY_RATE, clock=True, topics=topics, wait_topics=topics,
        wait_for_subscribers=1,
    )  # fmt: skip
    # Its own context: the caller's process may have a ROS node of its own (a test, the demo's first half).
    context = rclpy.Context()
    rclpy.init(context=context)
    node = rclpy.create_node("playseg_demo_robot", context=context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    steps, ends = [0], [0]

    def on_step(msg) -> None:
        steps[0] += 1

    def on_segment(msg) -> None:
        ends[0] = max(ends[0], msg.end_step)

    node.create_subscription(PlayStep, "/play/steps", on_step, qos.PLAY_STEPS)
    node.create_subscription(LabelledSegment, "/segments", on_segment, qos.SEGMENTS)

    def spin_until(condition, timeout_s: float) -> bool:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline and not condition():
            for name, proc in {**graph.processes, **player.processes}.items():
                # the player exits when done: only a failure counts (a damaged bag: exit code 1)
                if proc.poll() is not None and (name != "bag_player" or proc.returncode != 0):
                    raise RobotHalfError(
                        f"node {name} exited with code {proc.returncode}: see {graph.log_dir / name}.log"
                    )
            executor.spin_once(timeout_sec=0.1)
        return condition()

    graph.start()
    try:
        # PlaySteps are volatile: play once the segmenter, the recorder and this node listen to the adapter.
        if not spin_until(lambda: node.count_subscribers("/play/steps") >= 3, 60.0):
            raise RobotHalfError(
                "segmenter and recorder did not subscribe to /play/steps (see build/demo/run/logs)"
            )
        _log(f"bag_player: publishing {play_bag} ({', '.join(topics)}) into topic_adapter ...")
        started = time.monotonic()
        player.start()
        # Done when the segment ending at the episode's last step has arrived (a segmentation tiles it).
        if not spin_until(lambda: ends[0] >= expected_steps, STREAM_TIMEOUT_S):
            raise RobotHalfError(
                f"after {STREAM_TIMEOUT_S:.0f} s the segments reach step {ends[0]} of {expected_steps} "
                f"({steps[0]} PlaySteps; logs in {graph.log_dir})"
            )
        _log(
            f"topic_adapter published {steps[0]} PlaySteps, the segments reach step {ends[0]}, "
            f"in {time.monotonic() - started:.1f} s"
        )
        # The recorder gets the last segment when this node does, but a node stopped before its callback
        # ran loses it: a moment for the recorder to take it before the SIGINT.
        spin_until(lambda: False, RECORDER_SETTLE_S)
    finally:
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown(context=context)
        player.stop()
        graph.stop()
    return recorded


def _lerobot_summary(root: Path) -> dict:
    """Frames, episodes, tasks and per-frame instruction rows of a LeRobot v3 export (read with pyarrow)."""
    import pyarrow.parquet as pq

    info = json.loads((root / "meta" / "info.json").read_text())
    frames = pq.read_table(sorted((root / "data").rglob("*.parquet"))[0])
    tasks = pq.read_table(root / "meta" / "tasks.parquet")
    language = (
        frames.column("language_persistent").to_pylist()
        if "language_persistent" in frames.column_names
        else []
    )
    subtasks = {
        row["content"] for rows in language for row in rows if row["style"] == "subtask" and row["content"]
    }
    return {
        "codebase_version": info["codebase_version"],
        "episodes": info["total_episodes"],
        "frames": info["total_frames"],
        "tasks": tasks.num_rows,
        "instructions": len(subtasks),
        "videos": sorted(str(p.relative_to(root)) for p in (root / "videos").rglob("*.mp4")),
    }


def run_robot_half(
    bags_dir: Path, run_dir: Path, model: Path, play_bag_name: str = PLAY_BAG
) -> RobotHalfResult:
    """The robot half of the demo (module docstring); ``model`` is a tabletop PS checkpoint, ``play_bag_name``
    the unannotated bag of bags/tabletop it replays."""
    from playseg_core.checkpoint import read_checkpoint
    from playseg_core.data.dataset import PlayDataset
    from playseg_core.ps.labelling import threshold_json
    from playseg_core.ps.metrics import evaluate, format_metrics_table
    from playseg_ros.convert import SegmentationSpec, convert, load_mapping
    from playseg_ros.convert.run import playseg_copy
    from playseg_ros.convert.segmenting import keep_rule
    from playseg_ros.play_bags import read_segment_bag

    tabletop = bags_dir / "tabletop"
    play_bag, mapping, mapping_truth = (
        tabletop / play_bag_name,
        tabletop / "mapping.yaml",
        tabletop / "mapping_truth.yaml",
    )
    for path in robot_half_inputs(bags_dir):
        if not path.is_file():
            raise FileNotFoundError(f"sample robot bag file {path} is missing (regenerate with `make bags`)")
    robot_dir = run_dir / "robot"
    if robot_dir.exists():
        shutil.rmtree(robot_dir)
    robot_dir.mkdir(parents=True)
    truth = _truth_episode(play_bag, mapping_truth, robot_dir / "truth")
    recorded = _stream_live(play_bag, mapping, model, robot_dir, truth.num_steps)

    live = [clip.segment for clip in read_segment_bag(recorded)]
    metrics = evaluate(
        {truth.episode_id: live}, {truth.episode_id: truth.segments}, {truth.episode_id: truth.num_steps}
    )
    table = format_metrics_table(metrics)

    _log(
        f"playseg convert --format lerobot --segment {model}: {ANNOTATED_BAG} (annotated) and {play_bag.name} ..."
    )
    lerobot_dir = robot_dir / "lerobot"
    segmentation = SegmentationSpec.of(model)
    exported = convert(
        [tabletop / ANNOTATED_BAG, play_bag], lerobot_dir, load_mapping(mapping), 1, True, False,
        output_format="lerobot", segmentation=segmentation,
    )  # fmt: skip
    if exported.failed:
        raise RobotHalfError(f"convert: {exported.failed[0].error}")
    copy = PlayDataset.open(playseg_copy(lerobot_dir))
    by_id = {record.episode_id: index for index, record in enumerate(copy.records)}
    stored = copy.segments(by_id[truth.episode_id], truth=True) if truth.episode_id in by_id else []
    # The segmenter publishes every segment; convert stores those its keep rule keeps (the label threshold).
    rule = keep_rule(segmentation)
    kept = [s for s in live if rule.keeps(s)]
    same = [(s.start, s.end, s.instruction) for s in stored] == [
        (s.start, s.end, s.instruction) for s in kept
    ]
    summary = {
        "bag": str(play_bag),
        "steps": truth.num_steps,
        "segments": len(live),
        "true_segments": len(truth.segments),
        "precision": metrics["boundary_precision_tol0"],
        "recall": metrics["boundary_recall_tol0"],
        "f1_tol2": metrics["boundary_f1_tol2"],
        "label_accuracy": metrics["label_accuracy"],
        "label_threshold": threshold_json(rule.threshold),
        # the same model on its training play's held-out test split (`make models` keeps them in its meta)
        "model_test": read_checkpoint(model, ("ps",)).meta.get("test"),
        "stored_segments": len(stored),
        "live_equals_convert": same,
        "lerobot": {"path": str(lerobot_dir), **_lerobot_summary(lerobot_dir)},
    }
    (robot_dir / "summary.json").write_text(json.dumps(summary, indent=2))
    if not same:
        live_rows = [(s.start, s.end, s.instruction) for s in kept]
        stored_rows = [(s.start, s.end, s.instruction) for s in stored]
        first = next(
            (i for i, (a, b) in enumerate(zip(live_rows, stored_rows, strict=False)) if a != b),
            min(len(live_rows), len(stored_rows)),
        )
        print(
            f"warning: the live segments ({len(live_rows)}) differ from convert --segment's "
            f"({len(stored_rows)}) from segment {first}: live {live_rows[first : first + 2]}, "
            f"convert {stored_rows[first : first + 2]}",
            file=sys.stderr,
        )
    return RobotHalfResult(summary, table)


__all__ = ["RobotHalfError", "RobotHalfResult", "robot_half_inputs", "run_robot_half"]
