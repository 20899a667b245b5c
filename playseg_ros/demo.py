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
from typing import TYPE_CHECKING

from playseg_core.errors import PlaysegError

if TYPE_CHECKING:
    pass

DEMO_DIR = Path("build/demo")
BABYAI_MODEL = "babyai-ps.pt"
TABLETOP_MODEL = "tabletop-ps.pt"
"""The sample models next to the sample bags (bags/models/, written by `make models`): with them the demo
trains no PS model."""
TABLETOP_RECIPE = {"preset": "calvin", "seed": 0}
"""How `make models` trains the tabletop sample model: generated play of this preset and seed, `playseg
train` with its defaults on the train split (calibrated on its val split), scored on its test split."""
TABLETOP_STAND_IN = {"preset": "calvin-small", "seed": 0, "max_steps": 500}
"""What the demo trains when the sample tabletop model is missing or stale: minutes, not the sample
model's ten, and weaker (it says so)."""
DEMO_POLICY = {"train_steps": 400, "batch_size": 128, "policy_channels": 32, "eval_episodes": 512}
"""The trainer node's policy settings in the demo: a short budget, so that both halves fit 5 minutes."""
DEMO_POLICY_SEED_STD = 0.007
"""The std of the demo policy's success over training seeds, part of the noise the demo states for its
before -> after change: 0.967, 0.971, 0.953, 0.957, 0.955 on the annotated sample bag (seeds 0-4,
benchmarks/bench_demo_policy.py measures them)."""
PLAY_TIMEOUT_S = 240.0
SEGMENT_TIMEOUT_S = 300.0


def _log(message: str) -> None:
    print(f"[demo {time.strftime('%H:%M:%S')}] {message}", flush=True)


def bag_digest(bag: Path) -> str:
    """The content of a bag's MCAP files: a model trained on the bag is reused only for the same content."""
    digest = hashlib.sha256()
    for file in sorted(bag.glob("*.mcap")):
        digest.update(file.name.encode())
        digest.update(file.read_bytes())
    return digest.hexdigest()[:16]


def _code_digest() -> str:
    """playseg_core's code: a model cached by a run of the demo is reused only by the same code."""
    import playseg_core

    digest = hashlib.sha256()
    for file in sorted(Path(playseg_core.__file__).parent.rglob("*.py")):
        digest.update(file.read_bytes())
    return digest.hexdigest()[:16]


def shipped_model(path: Path, trained_on: str) -> Path | None:
    """``path`` (a model `make models` wrote next to the sample bags) when it loads with this code and was
    trained on ``trained_on`` (a bag digest or a generator command); None, saying why, otherwise."""
    from playseg_core.checkpoint import CheckpointError
    from playseg_core.ps.model import load_model

    if not path.is_file():
        return None
    try:
        _, meta = load_model(path)
    except CheckpointError as error:
        _log(f"not using {path}: {error}; training instead (`make models` rewrites it)")
        return None
    if meta.get("trained_on") != trained_on:
        _log(f"not using {path}: trained on {meta.get('trained_on')!r}, not {trained_on!r}; training instead")
        return None
    return path


def train_babyai_model(annotated_bag: Path, model_path: Path) -> Path:
    """Train and calibrate the BabyAI demo's PS model on the annotated sample bag (4-8 minutes here)."""
    from playseg_core.ps.calibration import calibrate_ps_model
    from playseg_core.ps.model import save_model
    from playseg_core.ps.training import TrainConfig, model_config_for, segment_bounds, train_ps
    from playseg_ros.play_bags import load_annotated

    annotated = load_annotated(annotated_bag)
    info, episodes = annotated.info, annotated.episodes
    if info.features is None or not info.instructions:
        raise PlaysegError(f"{annotated_bag}: the bag declares no features or instructions (make bags)")
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
    model_path.parent.mkdir(parents=True, exist_ok=True)
    save_model(model_path, result.model, {"trained_on": bag_digest(annotated_bag), **calibrated})
    bias = calibrated["end_bias"]
    _log(
        f"PS model trained in {result.seconds:.0f} s -> {model_path}; end bias {bias['bias']:+.2f} "
        f"(val boundary F1 {bias['f1']:.3f}, {bias['f1_without_bias']:.3f} without it)"
    )
    return model_path


def ensure_ps_model(annotated_bag: Path, cache_dir: Path, shipped: Path | None = None) -> Path:
    """The BabyAI demo's PS model: ``shipped`` (the sample model, `make models`) when it was trained on this
    bag and loads, else one cached by an earlier run for this bag and code, else a newly trained one."""
    trained_on = bag_digest(annotated_bag)
    if shipped is not None and shipped_model(shipped, trained_on) is not None:
        _log(f"using the sample PS model {shipped} (trained on {annotated_bag} by `make models`)")
        return shipped
    model_path = cache_dir / f"ps-{trained_on}-{_code_digest()}.pt"
    if model_path.exists():
        _log(f"reusing cached PS model {model_path}")
        return model_path
    return train_babyai_model(annotated_bag, model_path)


def _recipe_text(recipe: dict) -> str:
    cap = f" --max-steps {recipe['max_steps']}" if "max_steps" in recipe else ""
    return (
        f"playseg generate --domain tabletop --preset {recipe['preset']} --seed {recipe['seed']}; "
        f"playseg train{cap} on its train split"
    )


def _stand_in_text() -> str:
    """The stand-in is cached by a demo run: reused only by the same code, as the BabyAI cache."""
    return f"{_recipe_text(TABLETOP_STAND_IN)}; code {_code_digest()}"


def held_out_figures(model_path: Path, dataset) -> dict:
    """A PS checkpoint's figures on ``dataset``'s held-out test split, as `playseg segment` + `playseg
    evaluate` give them: boundary F1 exact and within 2 steps, label accuracy."""
    from playseg_core.baselines.registry import load_segmenter
    from playseg_core.ps.metrics import evaluate

    segmenter = load_segmenter("ps", model_path)
    test = list(dataset.episodes("test", truth=True))
    predicted = {episode.episode_id: segmenter.segment(episode) for episode in test}
    metrics = evaluate(
        predicted,
        {episode.episode_id: episode.segments for episode in test},
        {episode.episode_id: episode.num_steps for episode in test},
    )
    return {
        "episodes": len(test),
        "true_segments": metrics["true_segments"],
        "f1_exact": metrics["boundary_f1_tol0"],
        "f1_tol2": metrics["boundary_f1_tol2"],
        "label_accuracy": metrics["label_accuracy"],
    }


def train_tabletop_model(
    recipe: dict, work_dir: Path, model_path: Path, trained_on: str | None = None
) -> Path:
    """Generate tabletop play as ``recipe`` says, train and calibrate a PS model on it with `playseg
    train`'s defaults, and keep its test-split figures in the checkpoint's meta (``test``)."""
    from playseg_core.data.dataset import PlayDataset
    from playseg_core.domains import load_domain
    from playseg_core.ps.model import load_model, save_model
    from playseg_ros.offline import train

    data = work_dir / f"tabletop-{recipe['preset']}-{recipe['seed']}"
    if not (data / "meta" / "info.json").is_file():
        _log(f"generating tabletop play ({recipe['preset']} preset) into {data} ...")
        load_domain("tabletop").generate_dataset(data, recipe["preset"], recipe["seed"], 2, False, True)
    dataset = PlayDataset.open(data)
    segments = sum(len(episode.segments) for episode in dataset.episodes("train"))
    _log(f"training the tabletop PS model on {segments} annotated segments ({_recipe_text(recipe)}) ...")
    began = time.monotonic()
    model_path.parent.mkdir(parents=True, exist_ok=True)
    budget = {"max_steps": recipe.get("max_steps")}
    given = {"epochs": None, "lr": None, "batch_segments": None, "seed": 0, "labeller": None}  # the CLI's
    if train(str(data), str(model_path), **given, overwrite=True, budget=budget) != 0:
        raise PlaysegError(f"training the tabletop PS model on {data} failed (see above)")
    figures = held_out_figures(model_path, dataset)
    model, meta = load_model(model_path, ("ps",))
    save_model(model_path, model, {**meta, "trained_on": trained_on or _recipe_text(recipe), "test": figures})
    _log(
        f"tabletop PS model trained in {time.monotonic() - began:.0f} s -> {model_path}; its test split: "
        f"F1 {figures['f1_exact']:.3f} exact, {figures['f1_tol2']:.3f} within 2 steps, label accuracy "
        f"{figures['label_accuracy']:.3f} ({figures['true_segments']} segments)"
    )
    return model_path


def ensure_tabletop_model(cache_dir: Path, shipped: Path | None = None) -> Path:
    """The robot half's PS model: ``shipped`` (`make models`) when it loads with this code, else a cached
    or newly trained stand-in (`TABLETOP_STAND_IN`)."""
    if shipped is not None and shipped_model(shipped, _recipe_text(TABLETOP_RECIPE)) is not None:
        _log(f"using the sample tabletop PS model {shipped} ({_recipe_text(TABLETOP_RECIPE)}; `make models`)")
        return shipped
    model_path = cache_dir / "tabletop-ps-stand-in.pt"
    if shipped_model(model_path, _stand_in_text()) is not None:
        _log(f"reusing the stand-in tabletop PS model {model_path} (`make models` trains the sample model)")
        return model_path
    _log(f"no sample tabletop model: training a weaker stand-in ({_recipe_text(TABLETOP_STAND_IN)})")
    return train_tabletop_model(TABLETOP_STAND_IN, cache_dir, model_path, _stand_in_text())


def train_sample_models(bags_dir: Path = Path("bags"), work_dir: Path = Path("build/models")) -> int:
    """`make models`: the sample models the demo uses, into ``bags_dir``/models."""
    out = bags_dir / "models"
    train_babyai_model(bags_dir / "annotated", out / BABYAI_MODEL)
    train_tabletop_model(TABLETOP_RECIPE, work_dir, out / TABLETOP_MODEL)
    return 0


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


def _episode_outcomes(policies: Path, version: int) -> list[bool]:
    """Episode by episode success of a policy version the trainer wrote (its checkpoint's meta)."""
    from playseg_core.checkpoint import read_checkpoint

    meta = read_checkpoint(policies / f"policy-v{version:04d}.pt", kinds=("policy",)).meta
    return [flag == "1" for flag in meta.get("episode_success", "")]


def run_demo(bags_dir: Path = Path("bags"), out_dir: Path = DEMO_DIR) -> int:
    from playseg_core.augment.policy import describe_success_change
    from playseg_core.ps.metrics import evaluate, format_metrics_table
    from playseg_ros.launch import Graph, GraphSpec, NodeSpec, player_graph
    from playseg_ros.play_bags import read_play_bag, read_segment_bag

    began = time.monotonic()
    annotated_bag, play_bag = bags_dir / "annotated", bags_dir / "play"
    from playseg_ros.demo_robot import RobotHalfError, robot_half_inputs, run_robot_half

    needed = [annotated_bag / "metadata.yaml", play_bag / "metadata.yaml", *robot_half_inputs(bags_dir)]
    for path in needed:
        if not path.is_file():
            print(f"error: sample bag file {path} is missing (regenerate with `make bags`)", file=sys.stderr)
            return 2
    model_path = ensure_ps_model(annotated_bag, out_dir / "cache", bags_dir / "models" / BABYAI_MODEL)
    robot_model = ensure_tabletop_model(out_dir / "cache", bags_dir / "models" / TABLETOP_MODEL)

    run_dir = out_dir / "run"
    if run_dir.exists():
        shutil.rmtree(run_dir)
    run_dir.mkdir(parents=True)
    output_bag = run_dir / "output_bag"
    policy_params = DEMO_POLICY
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
        player = player_graph(play_bag, run_dir / "logs", rate=0.0, wait_for_subscribers=2)
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
    }
    from playseg_core.ps.timeline import plot_timeline

    timeline = run_dir / "timeline.png"
    plot_timeline(timeline, truth_episodes[:6], predicted)
    print()
    _log(
        f"boundary precision {summary['precision']:.3f}  recall {summary['recall']:.3f}  "
        f"label accuracy {summary['label_accuracy']:.3f}  (exact match, vs ground truth of {play_bag})"
    )
    episodes = policy_params["eval_episodes"]
    before_outcomes, after_outcomes = (
        _episode_outcomes(run_dir / "policies", version.policy_version) for version in (before, after)
    )
    if before_outcomes and len(before_outcomes) == len(after_outcomes):
        change = describe_success_change(before_outcomes, after_outcomes, DEMO_POLICY_SEED_STD)
    else:  # a trainer that kept no episode-by-episode outcomes: the rates, without an error
        change = f"{before.eval_success_rate:.3f} -> {after.eval_success_rate:.3f} (no per-episode outcomes)"
    _log(
        f"policy success before augmentation -> after: {change}, on the same {episodes} seeded episodes of "
        "the policy's simulator (the error combines those episodes, paired, with the spread between "
        "training seeds); what augmentation does at the scales where it can be measured: "
        "`playseg experiment`, docs/augmentation.md"
    )
    _log(
        f"outputs: recorded bag {output_bag} (play steps + /segments), policies {run_dir / 'policies'}, "
        f"buffer {run_dir / 'buffer'}, timeline {timeline}"
    )

    print()
    _log(
        "robot half: a tabletop robot bag in standard messages (camera, joint states, velocity commands) ..."
    )
    (run_dir / "summary.json").write_text(json.dumps({"babyai": summary}, indent=2))
    try:
        robot = run_robot_half(bags_dir, run_dir, robot_model)
    except RobotHalfError as error:
        print(f"error: the robot half failed: {error}", file=sys.stderr)
        return 1
    print(robot.table)
    r = robot.summary
    # null in the summary: no threshold reached the calibration's accuracy target, so nothing is kept
    threshold = "none (keeps nothing)" if r["label_threshold"] is None else f"{r['label_threshold']:.2f}"
    _log(
        f"{r['bag']}: {r['segments']} segments live ({r['true_segments']} true); boundary precision "
        f"{r['precision']:.3f} recall {r['recall']:.3f} (exact), F1 {r['f1_tol2']:.3f} within 2 steps (0.2 s), "
        f"label accuracy {r['label_accuracy']:.3f}; convert --segment stored the {r['stored_segments']} at or above "
        f"the label threshold {threshold}, the same as live: {r['live_equals_convert']}"
    )
    held_out = r["model_test"]
    if held_out:
        _log(
            f"the same model on its training play's held-out test split ({held_out['true_segments']} segments, "
            f"`make models`): F1 {held_out['f1_exact']:.3f} exact, {held_out['f1_tol2']:.3f} within 2 steps, "
            f"label accuracy {held_out['label_accuracy']:.3f}"
        )
    lerobot = r["lerobot"]
    _log(
        f"LeRobot {lerobot['codebase_version']} dataset {lerobot['path']}: {lerobot['episodes']} episodes, "
        f"{lerobot['frames']} frames, {lerobot['tasks']} tasks, {lerobot['instructions']} distinct per-frame "
        f"instructions (language_persistent, style subtask), videos {', '.join(lerobot['videos'])}"
    )
    summary = {"babyai": summary, "robot": robot.summary, "seconds": time.monotonic() - began}
    (run_dir / "summary.json").write_text(json.dumps(summary, indent=2))
    _log(f"done in {summary['seconds']:.0f} s; summary {run_dir / 'summary.json'}")
    return 0 if not math.isnan(after.eval_success_rate) else 1
