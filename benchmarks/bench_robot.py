"""Robot-shaped Play Segmentation: segmentation throughput against the reference's way, and training time
and peak memory for 2,000 annotated segments.

    .venv/bin/python benchmarks/bench_robot.py throughput [--steps 3000] [--reference-steps 150]
        [--max-len 100] [--threads 1]
    .venv/bin/python benchmarks/bench_robot.py train [--segments 2000] [--epochs 1] [--threads 2]

Data: a 96x96 camera (image_cnn), a 7-D state (state_mlp), 7-D continuous actions (continuous_action).
Speed and memory do not depend on the pixel values, so each episode's frames are one random frame
broadcast over its steps (no memory of their own: the figures are the model's and the training loop's);
states and actions are random, segments 20-100 steps long.

throughput: a randomly initialised model at L_max 100; `segment_episode` on one long episode (steps/s of
wall and of CPU time, one core) and `reference_style_segment` (the whole model re-run on every prefix,
the paper's DP with Python loops) on a shorter one; both must give the same segmentation on the shorter episode. Then the
live way, one step at a time (`StreamingSegmenter`, as the segmenter node runs it), and its incremental
scoring against `PSModel.end_column` scoring every window from scratch at each step. The ratio is
a lower bound: on an episode shorter than L_max the reference's way runs fewer and shorter prefixes per
step than it would on a long one (its cost per step grows with L_max squared).
train: `train_ps` for ``--epochs`` epochs over the segments (16 per batch); the seconds per optimiser step
extrapolate to the default step cap (16 epochs or 3,200 steps, whichever is more; early stopping
usually ends a run sooner). Each mode runs in its
own process, so peak RSS is that process's.
"""

from __future__ import annotations

import argparse
import resource
import time

import numpy as np
import torch

from playseg_core.data.episode import Episode, Segment
from playseg_core.data.features import ACTION, STATE, Feature, Features
from playseg_core.ps.encoders import as_tensors
from playseg_core.ps.incremental import IncrementalEndScorer
from playseg_core.ps.model import PSModel
from playseg_core.ps.reference_style import reference_style_segment
from playseg_core.ps.segmentation import segment_episode
from playseg_core.ps.streaming import StreamingSegmenter
from playseg_core.ps.training import TrainConfig, model_config_for, segment_bounds, step_cap, train_ps
from playseg_core.training.device import resolve_device, to_device

CAMERA = "observation.images.front"
FEATURES = Features.of(
    [
        Feature(CAMERA, "image", "uint8", (96, 96, 3)),
        Feature(STATE, "state", "float32", (7,), names=tuple(f"joint_{i}" for i in range(7))),
        Feature(ACTION, "action", "float32", (7,), low=(-1.0,) * 7, high=(1.0,) * 7),
    ],
    fps=10.0,
)
INSTRUCTIONS = [f"task {i}" for i in range(16)]


def robot_episode(seed: int, num_segments: int) -> Episode:
    """``num_segments`` labelled segments of 20-100 steps in a row."""
    rng = np.random.default_rng(seed)
    lengths = rng.integers(20, 101, size=num_segments)
    bounds = np.concatenate([[0], np.cumsum(lengths)])
    steps = int(bounds[-1])
    frame = rng.integers(0, 256, size=(96, 96, 3), dtype=np.uint8)
    segments = [
        Segment(int(a), int(b), INSTRUCTIONS[int(rng.integers(len(INSTRUCTIONS)))])
        for a, b in zip(bounds, bounds[1:], strict=False)
    ]
    return Episode(
        f"robot-{seed}",
        rng.normal(size=(steps, 7)).astype(np.float32),
        {CAMERA: np.broadcast_to(frame, (steps + 1, 96, 96, 3))},
        rng.normal(size=(steps + 1, 7)).astype(np.float32),
        segments,
    )


def peak_rss_mb() -> int:
    return round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024)


def throughput(args: argparse.Namespace) -> None:
    torch.set_num_threads(args.threads)
    long_episode, short_episode = robot_episode(0, args.steps // 60), robot_episode(1, 3)
    short_episode = Episode(  # cut to --reference-steps: the reference's way is quadratic in L_max
        "short",
        short_episode.actions[: args.reference_steps],
        {CAMERA: short_episode.images[CAMERA][: args.reference_steps + 1]},
        short_episode.state[: args.reference_steps + 1],
    )
    torch.manual_seed(0)
    config = model_config_for(
        FEATURES, None, len(INSTRUCTIONS), max_len=args.max_len, episodes=[long_episode]
    )
    model = PSModel(config, INSTRUCTIONS).eval().to(resolve_device(args.device))
    segment_episode(model, short_episode)  # warm-up

    began, began_cpu = time.perf_counter(), time.process_time()
    segment_episode(model, long_episode)
    ours, ours_cpu = time.perf_counter() - began, time.process_time() - began_cpu
    ours_rate = long_episode.num_steps / ours
    print(
        f"ours: {long_episode.num_steps} steps at L_max {args.max_len} in {ours:.1f} s = {ours_rate:.0f} steps/s "
        f"on {args.threads} thread(s), device {model.device} (target >= 1,000); peak RSS {peak_rss_mb()} MB"
    )
    # On a machine shared with other jobs the wall time includes waiting for a core; CPU time does not.
    print(f"ours in CPU time: {ours_cpu:.1f} s = {long_episode.num_steps / ours_cpu:.0f} steps/s")
    streaming(model, long_episode, args.stream_steps)
    if args.skip_reference:
        return
    began = time.perf_counter()
    ours_short = segment_episode(model, short_episode)
    ours_short_s = time.perf_counter() - began
    began = time.perf_counter()
    reference = reference_style_segment(model, short_episode)
    reference_s = time.perf_counter() - began
    same = [(s.start, s.end, s.instruction) for s in ours_short] == [
        (s.start, s.end, s.instruction) for s in reference
    ]
    reference_rate = short_episode.num_steps / reference_s
    print(
        f"reference way: {short_episode.num_steps} steps in {reference_s:.1f} s = {reference_rate:.1f} steps/s "
        f"(ours on the same episode: {short_episode.num_steps / ours_short_s:.0f} steps/s); "
        f"same segmentation: {same}"
    )
    print(
        f"ratio (ours on the long episode / reference way): {ours_rate / reference_rate:.0f}x (target >= 100x)"
    )


def streaming(model: PSModel, episode: Episode, steps: int) -> None:
    """The segmenter node's way: one step at a time (`StreamingSegmenter`), and its scoring alone against
    `PSModel.end_column` scoring every window from scratch at each step."""
    steps = min(steps, episode.num_steps)
    stream = StreamingSegmenter(model, model.cfg.min_len)
    began = time.perf_counter()
    for t in range(steps + 1):
        observation = {CAMERA: episode.images[CAMERA][t], STATE: episode.state[t]}
        stream.push(observation, episode.actions[t])
    pushed = time.perf_counter() - began
    with torch.no_grad():
        features = model.encode_steps(
            to_device(as_tensors(model.encoders.episode_inputs(episode)), model.device)
        )[: steps + 1]
    scorer = IncrementalEndScorer(model)
    began = time.perf_counter()
    for t in range(steps + 1):
        scorer.push(features[t])
        scorer.column(0)
    incremental = time.perf_counter() - began
    began = time.perf_counter()
    with torch.no_grad():
        for t in range(1, steps + 1):
            model.end_column(
                features[max(0, t - model.max_len - model.lookahead) : t + 1], t <= model.max_len
            )
    from_scratch = time.perf_counter() - began
    print(
        f"streaming (StreamingSegmenter, {steps} steps): {steps / pushed:.0f} steps/s = {pushed / steps * 1e3:.2f} "
        f"ms/step; its scoring {incremental / steps * 1e3:.2f} ms/step, end_column from scratch "
        f"{from_scratch / steps * 1e3:.2f} ms/step ({from_scratch / incremental:.0f}x)"
    )


def train(args: argparse.Namespace) -> None:
    per_episode = 50
    episodes = [robot_episode(seed, per_episode) for seed in range(-(-args.segments // per_episode))]
    val = [robot_episode(10_000, 10)]
    num_segments = sum(len(e.segments) for e in episodes)
    bounds = segment_bounds(episodes)
    config = model_config_for(
        FEATURES, None, len(INSTRUCTIONS), max_len=bounds.max_len, episodes=episodes, min_len=bounds.min_len
    )
    cfg = TrainConfig(
        epochs=args.epochs, k_max=bounds.k_max, num_threads=args.threads, progress=False,
        log_epochs=False, device=args.device,
    )  # fmt: skip
    steps_per_epoch = -(-num_segments // cfg.segments_per_batch)
    before = peak_rss_mb()
    result = train_ps(episodes, val, INSTRUCTIONS, cfg, config)
    optimiser_steps = steps_per_epoch * args.epochs
    per_step = result.seconds / optimiser_steps
    default_steps = step_cap(TrainConfig(), steps_per_epoch)
    print(
        f"{num_segments} segments ({sum(e.num_steps for e in episodes)} steps), L_min/L_max/k_max "
        f"{bounds.min_len}/{bounds.max_len}/{bounds.k_max}, {args.threads} thread(s), device "
        f"{resolve_device(args.device)}"
    )
    print(
        f"{args.epochs} epoch(s) = {optimiser_steps} optimiser steps (validation included) in {result.seconds:.0f} s "
        f"= {per_step:.2f} s/step; the default step cap ({default_steps} steps) ~ {default_steps * per_step / 60:.0f} min"
    )
    print(f"peak RSS {peak_rss_mb()} MB (data and model before training: {before} MB)")


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    sub = parser.add_subparsers(dest="mode", required=True)
    speed = sub.add_parser("throughput")
    speed.add_argument("--steps", type=int, default=3000)
    speed.add_argument("--reference-steps", type=int, default=150)
    speed.add_argument("--max-len", type=int, default=100)
    speed.add_argument("--stream-steps", type=int, default=600, help="steps pushed one at a time")
    speed.add_argument("--threads", type=int, default=1)
    speed.add_argument("--device", default="cpu", help="auto, cpu, cuda or cuda:N")
    speed.add_argument(
        "--skip-reference", action="store_true", help="only ours (the reference way is CPU-bound)"
    )
    fit = sub.add_parser("train")
    fit.add_argument("--segments", type=int, default=2000)
    fit.add_argument("--epochs", type=int, default=1)
    fit.add_argument("--threads", type=int, default=2)
    fit.add_argument("--device", default="cpu", help="auto, cpu, cuda or cuda:N")
    args = parser.parse_args()
    throughput(args) if args.mode == "throughput" else train(args)


if __name__ == "__main__":
    main()
