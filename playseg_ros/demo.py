"""`make demo`: the whole pipeline on the sample bags in bags/, live on a real ROS 2 graph.

1. Train a PS model on bags/annotated (cached under build/demo/cache, keyed by the bag's content).
2. Bring up trainer, recorder and segmenter nodes; the trainer trains policy v1 on the annotated segments
   only ("before augmentation").
3. The bag player publishes the unannotated play of bags/play as fast as the subscribers keep up; the
   segmenter publishes LabelledSegment live; the recorder writes play + segments to an output bag; the
   trainer buffers every segment.
4. The trainer retrains (v2 = annotated + extracted segments) and evaluates on the same seeded episodes.
5. Print precision / recall / label accuracy against the ground truth of bags/play (read back from the
   recorded output bag), policy success before and after, where the outputs are; write a PNG timeline.
"""

from __future__ import annotations

import hashlib
import json
import math
import shutil
import sys
import time
from pathlib import Path

DEMO_DIR = Path("build/demo")
PLAY_TIMEOUT_S = 240.0
SEGMENT_TIMEOUT_S = 300.0


def _log(message: str) -> None:
    print(f"[demo {time.strftime('%H:%M:%S')}] {message}", flush=True)


def _cache_key(bag: Path) -> str:
    """The bag's content and playseg_core's code: a cached model is reused only if both are the same."""
    import playseg_core

    digest = hashlib.sha256()
    code = sorted(Path(playseg_core.__file__).parent.rglob("*.py"))
    for file in [*sorted(bag.glob("*.mcap")), *code]:
        digest.update(file.read_bytes())
    return digest.hexdigest()[:16]


def ensure_ps_model(annotated_bag: Path, cache_dir: Path) -> Path:
    """Train the PS model on the annotated bag unless a model for this exact bag is cached."""
    from playseg_core.ps.calibration import calibrate_ps_model
    from playseg_core.ps.model import save_model
    from playseg_core.ps.training import TrainConfig, model_config_for, segment_bounds, train_ps
    from playseg_ros.play_bags import load_annotated

    model_path = cache_dir / f"ps-{_cache_key(annotated_bag)}.pt"
    if model_path.exists():
        _log(f"reusing cached PS model {model_path}")
        return model_path
    annotated = load_annotated(annotated_bag)
    info, episodes = annotated.info, annotated.episodes
    if info.features is None or not info.instructions:
        raise ValueError(f"{annotated_bag}: the bag declares no features or instructions (make bags)")
    split = max(1, len(episodes) // 5)
    train, val = episodes[split:], episodes[:split]
    _log(
        f"training the PS model on {len(train)} annotated episodes ({sum(len(e.segments) for e in train)} segments), "
        f"validating on {len(val)} ..."
    )
    bounds = segment_bounds(train, info.domain)
    model_cfg = model_config_for(
        info.features,
        info.domain,
        len(info.instructions),
        max_len=bounds.max_len,
        episodes=train,
        min_len=bounds.min_len,
    )
    config = TrainConfig(k_max=bounds.k_max, progress=sys.stderr.isatty())
    result = train_ps(train, val, info.instructions, config, model_cfg)
    calibrated = calibrate_ps_model(result.model, val)
    cache_dir.mkdir(parents=True, exist_ok=True)
    save_model(model_path, result.model, {"trained_on": str(annotated_bag), **calibrated})
    bias = calibrated["end_bias"]
    _log(
        f"PS model trained in {result.seconds:.0f} s -> {model_path}; end bias {bias['bias']:+.2f} "
        f"(val boundary F1 {bias['f1']:.3f}, {bias['f1_without_bias']:.3f} without it)"
    )
    return model_path


class _DemoClient:
    """The demo's own ROS node: watches segments and trainer status, calls the trainer's services."""

    def __init__(self, graph) -> None:
        import rclpy
        from playseg_msgs.msg import LabelledSegment, TrainerStatus
        from playseg_msgs.srv import Retrain

        from playseg_ros import qos

        rclpy.init()
        self.graph = graph
        self.rclpy = rclpy
        self.node = rclpy.create_node("playseg_demo")
        self.segments = 0
        self.last_end: dict[str, int] = {}  # episode id -> end step of its latest segment
        self.status = None
        self.node.create_subscription(LabelledSegment, "/segments", self._on_segment, qos.SEGMENTS)
        self.node.create_subscription(TrainerStatus, "/trainer/status", self._on_status, qos.STATUS)
        self.retrain = self.node.create_client(Retrain, "/trainer/retrain")
        self.Retrain = Retrain

    def _on_segment(self, msg) -> None:
        self.segments += 1
        self.last_end[msg.episode_id] = max(msg.end_step, self.last_end.get(msg.episode_id, 0))

    def _on_status(self, msg) -> None:
        self.status = msg

    def spin_until(self, condition, timeout_s: float) -> bool:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if condition():
                return True
            self._check_nodes()
            self.rclpy.spin_once(self.node, timeout_sec=0.1)
        return condition()

    def _check_nodes(self) -> None:
        """Fail fast, naming the node and its log, when a node of the graph died."""
        for name, proc in self.graph.processes.items():
            if proc.poll() is not None:
                raise RuntimeError(
                    f"node {name} exited with code {proc.returncode}: see {self.graph.log_dir / name}.log"
                )

    def call_retrain(self, timeout_s: float = 600.0):
        if not self.spin_until(lambda: self.retrain.service_is_ready(), 60.0):
            raise RuntimeError(
                "the trainer's retrain service did not come up (see build/demo/logs/trainer.log)"
            )
        future = self.retrain.call_async(self.Retrain.Request(wait=True))
        if not self.spin_until(future.done, timeout_s):
            raise RuntimeError("retraining did not finish in time")
        return future.result()

    def close(self) -> None:
        self.node.destroy_node()
        self.rclpy.try_shutdown()


def run_demo(bags_dir: Path = Path("bags"), out_dir: Path = DEMO_DIR) -> int:
    from playseg_core.augment.policy import describe_success_change
    from playseg_core.ps.metrics import evaluate, format_metrics_table
    from playseg_ros.launch import Graph, GraphSpec, NodeSpec
    from playseg_ros.play_bags import read_play_bag, read_segment_bag

    began = time.monotonic()
    annotated_bag, play_bag = bags_dir / "annotated", bags_dir / "play"
    for bag in (annotated_bag, play_bag):
        if not (bag / "metadata.yaml").is_file():
            print(f"error: sample bag {bag} is missing (regenerate with `make bags`)", file=sys.stderr)
            return 2
    model_path = ensure_ps_model(annotated_bag, out_dir / "cache")

    run_dir = out_dir / "run"
    if run_dir.exists():
        shutil.rmtree(run_dir)
    run_dir.mkdir(parents=True)
    output_bag = run_dir / "output_bag"
    policy_params = {"train_steps": 400, "batch_size": 128, "policy_channels": 32, "eval_episodes": 256}
    services = Graph(
        GraphSpec(
            [
                NodeSpec(
                    "trainer",
                    "trainer",
                    {
                        "buffer_dir": str(run_dir / "buffer"),
                        "checkpoint_dir": str(run_dir / "policies"),
                        "base_data": str(annotated_bag),
                        **policy_params,
                    },
                ),
                NodeSpec(
                    "recorder",
                    "recorder",
                    {"output": str(output_bag), "topics": ["/play/steps", "/play/ground_truth", "/segments"]},
                ),
                NodeSpec("segmenter", "segmenter", {"model": str(model_path)}),
            ]
        ),
        log_dir=run_dir / "logs",
    )
    _log("starting trainer, recorder and segmenter nodes (logs in build/demo/run/logs) ...")
    services.start()
    client = _DemoClient(services)
    try:
        _log("trainer: policy v1 on the annotated segments only (before augmentation) ...")
        before = client.call_retrain()
        _log(f"policy v{before.policy_version}: success {before.eval_success_rate:.3f}")

        truth_episodes = read_play_bag(play_bag, truth=True)
        player = Graph(
            GraphSpec(
                [
                    NodeSpec(
                        "bag_player",
                        "bag_player",
                        {
                            "bag": str(play_bag),
                            "rate": 0.0,
                            "wait_for_subscribers": 2,
                            "exit_when_done": True,
                        },
                    )
                ]
            ),
            log_dir=run_dir / "logs",
        )
        _log(f"bag_player: publishing {len(truth_episodes)} unannotated play episodes from {play_bag} ...")
        player.start()
        started = time.monotonic()
        client.spin_until(lambda: player.processes["bag_player"].poll() is not None, PLAY_TIMEOUT_S)

        # The segmenter may lag behind the player (its reader queues the backlog): done when every episode's
        # last segment, the one ending at its final step, has arrived.
        def complete() -> int:
            return sum(client.last_end.get(e.episode_id) == e.num_steps for e in truth_episodes)

        if not client.spin_until(lambda: complete() == len(truth_episodes), SEGMENT_TIMEOUT_S):
            _log(
                f"warning: after {SEGMENT_TIMEOUT_S:.0f} s, {complete()} of {len(truth_episodes)} episodes are complete"
            )
        player.stop()
        # Retrain only once the trainer acknowledged every segment we saw (its status counts them).
        client.spin_until(
            lambda: client.status is not None and client.status.buffer_segments >= client.segments, 60.0
        )
        _log(
            f"segmenter published {client.segments} LabelledSegments in {time.monotonic() - started:.1f} s; "
            f"trainer buffer: {client.status.buffer_segments if client.status else '?'} segments"
        )

        _log("trainer: policy v2 on annotated + extracted segments (after augmentation) ...")
        after = client.call_retrain()
        _log(f"policy v{after.policy_version}: success {after.eval_success_rate:.3f}")
    finally:
        client.close()
        services.stop()

    clips = read_segment_bag(output_bag)
    predicted: dict[str, list] = {e.episode_id: [] for e in truth_episodes}
    for clip in clips:
        predicted.setdefault(clip.episode_id, []).append(clip.segment)
    truth = {e.episode_id: e.segments for e in truth_episodes}
    num_steps = {e.episode_id: e.num_steps for e in truth_episodes}
    metrics = evaluate(predicted, truth, num_steps)
    print(format_metrics_table(metrics))
    summary = {
        "segments": len(clips),
        "precision": metrics["boundary_precision_tol0"],
        "recall": metrics["boundary_recall_tol0"],
        "label_accuracy": metrics["label_accuracy"],
        "policy_success_before": before.eval_success_rate,
        "policy_success_after": after.eval_success_rate,
        "seconds": time.monotonic() - began,
    }
    (run_dir / "summary.json").write_text(json.dumps(summary, indent=2))
    from playseg_core.ps.timeline import plot_timeline

    timeline = run_dir / "timeline.png"
    plot_timeline(timeline, truth_episodes[:6], predicted)
    print()
    _log(
        f"boundary precision {summary['precision']:.3f}  recall {summary['recall']:.3f}  "
        f"label accuracy {summary['label_accuracy']:.3f}  (exact match, vs ground truth of {play_bag})"
    )
    episodes = policy_params["eval_episodes"]
    change = describe_success_change(before.eval_success_rate, after.eval_success_rate, episodes)
    _log(
        f"policy success before augmentation -> after: {change}, on {episodes} fixed seeded episodes of the "
        "policy's simulator; the effect of augmentation at larger scales: README 'Results and figures'"
    )
    _log(
        f"outputs: recorded bag {output_bag} (play steps + /segments), policies {run_dir / 'policies'}, "
        f"buffer {run_dir / 'buffer'}, timeline {timeline}, summary {run_dir / 'summary.json'}"
    )
    _log(f"done in {summary['seconds']:.0f} s")
    return 0 if not math.isnan(after.eval_success_rate) else 1
