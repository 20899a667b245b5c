"""How long does PS's default training take on a small robot-shaped dataset, and to a model of what held-out
quality, against the old fixed budget of 3,200 optimiser steps?

    .venv/bin/python benchmarks/bench_training_budget.py --budget default [--seed 0] [--threads 2] [--log]
    .venv/bin/python benchmarks/bench_training_budget.py --budget old [--seed 0] [--threads 2] [--log]

Data: 10 annotated episodes of 8 segments each, and 5 test episodes of 8 (their segments are used only
to score). One 72x96 camera, a 2-D state, 2-D continuous actions, 4 instructions. Each episode is a
planar arm "pressing" one of four coloured pads: the state is the gripper's position, the action the
velocity command that moved it (with noise), and a segment is a minimum-jerk move of 12-28 steps from
where the last one ended to the instructed pad (never the pad it is on). The camera shows the four pads
and the gripper (with sensor noise); the pad lights up in the frame where it is pressed, the
observation that ends the segment. So the end shows in the frames exactly and in the state and actions
(the gripper slows and stops) within a step or two; the label shows in where the gripper goes.

Training as `playseg train` does it, in-process: no val split is given, so `hold_out_for_validation`
moves 20% of the annotated episodes (2 of 10) to val, for early stopping and calibration; bounds from
`segment_bounds`, the default model from `model_config_for`; then `calibrate_ps_model` on the held-out
episodes, and `segment_episode` (at the model's L_min) on the test episodes, scored with
playseg_core.ps.metrics `evaluate`.

--budget default: `TrainConfig()` as it stands: the step cap `step_cap` (16 epochs, at least 3,200
steps: 3,200 here), a held-out evaluation every `evaluation_interval` steps, stopping after `patience`
evaluations without a better `val_error`, the best weights kept.
--budget old: `TrainConfig(max_steps=3200, patience=10**9)`: the old fixed 3,200 steps. ``patience``
applies only when ``epochs`` is None, so a huge patience (not ``epochs``) is what disables early
stopping here; the run goes to the cap and still keeps the best-val_error weights, with the same cap,
evaluation interval and learning-rate schedule (cosine over the cap) as the default. The default run is
therefore a prefix of the old one (the same batches at the same steps); the old run also says where
patience would have stopped it.

Printed: the steps taken against the cap and why it stopped, the training seconds and s/step, the
test boundary F1 within +-2 steps and exact, with and without the trivial final boundary, and the
per-step label accuracy. Timings are wall-clock on ``--threads`` torch threads and move with whatever
else the machine runs.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch

from playseg_core.data.episode import Episode, Segment
from playseg_core.data.features import ACTION, STATE, Feature, Features
from playseg_core.ps.calibration import calibrate_ps_model
from playseg_core.ps.metrics import boundary_key, evaluate
from playseg_core.ps.segmentation import segment_episode
from playseg_core.ps.training import (
    TrainConfig,
    evaluation_interval,
    hold_out_for_validation,
    model_config_for,
    segment_bounds,
    step_cap,
    steps_per_epoch,
    train_ps,
)
from playseg_core.training.device import resolve_device
from playseg_core.training.loop import LoopConfig

CAMERA = "observation.images.front"
HEIGHT, WIDTH = 72, 96
FEATURES = Features.of(
    [
        Feature(CAMERA, "image", "uint8", (HEIGHT, WIDTH, 3)),
        Feature(STATE, "state", "float32", (2,), names=("x", "y")),
        Feature(ACTION, "action", "float32", (2,), low=(-1.0,) * 2, high=(1.0,) * 2),
    ],
    fps=10.0,
)
INSTRUCTIONS = ["press the red pad", "press the green pad", "press the blue pad", "press the yellow pad"]
PADS = np.array([[-0.75, 0.7], [0.75, 0.7], [-0.75, -0.7], [0.75, -0.7]])  # (x, y) of each instruction's pad
COLOURS = np.array([[200, 40, 40], [40, 190, 60], [50, 70, 210], [210, 190, 40]], dtype=np.float32)
SEGMENTS_PER_EPISODE = 8
SEGMENT_LENGTHS = (12, 28)
MAX_SPEED = 0.25  # position units per step that an action of 1 commands
OLD_STEPS = 3200


def _pixel(position: np.ndarray) -> tuple[int, int]:
    """(row, column) of a position in [-1, 1]^2 (y up)."""
    row = int(round((1.0 - position[1]) / 2.0 * (HEIGHT - 1)))
    col = int(round((position[0] + 1.0) / 2.0 * (WIDTH - 1)))
    return min(max(row, 0), HEIGHT - 1), min(max(col, 0), WIDTH - 1)


def _render(positions: np.ndarray, pressed: dict[int, int], rng: np.random.Generator) -> np.ndarray:
    """The camera: dim pads, a lit pad in the frame where it is pressed, the gripper, sensor noise."""
    scene = np.full((HEIGHT, WIDTH, 3), 70.0, dtype=np.float32)
    for pad, colour in zip(PADS, COLOURS, strict=True):
        row, col = _pixel(pad)
        scene[max(0, row - 6) : row + 7, max(0, col - 6) : col + 7] = 0.45 * colour
    frames = np.repeat(scene[None], len(positions), axis=0)
    for t, pad in pressed.items():
        row, col = _pixel(PADS[pad])
        frames[t, max(0, row - 6) : row + 7, max(0, col - 6) : col + 7] = COLOURS[pad]
    for t, position in enumerate(positions):
        row, col = _pixel(position)
        frames[t, max(0, row - 3) : row + 4, max(0, col - 3) : col + 4] = 245.0
    frames += rng.normal(0.0, 8.0, size=frames.shape).astype(np.float32)
    return np.clip(frames, 0, 255).astype(np.uint8)


def robot_episode(episode_id: str, seed: int, annotated: bool = True) -> Episode:
    """Eight segments: minimum-jerk reaches to the instructed pad, pressed at the segment's last frame."""
    rng = np.random.default_rng(seed)
    position = rng.uniform(-0.3, 0.3, size=2)
    positions, segments, pressed = [position], [], {}
    pad = -1
    for _ in range(SEGMENTS_PER_EPISODE):
        pad = int(rng.choice([p for p in range(len(PADS)) if p != pad]))
        length = int(rng.integers(SEGMENT_LENGTHS[0], SEGMENT_LENGTHS[1] + 1))
        goal = PADS[pad] + rng.normal(0.0, 0.03, size=2)
        tau = np.arange(1, length + 1) / length
        profile = 10 * tau**3 - 15 * tau**4 + 6 * tau**5
        path = position + profile[:, None] * (goal - position)
        path[:-1] += rng.normal(0.0, 0.01, size=(length - 1, 2))  # tremor; the press lands on the goal
        start = len(positions) - 1
        positions.extend(path)
        segments.append(Segment(start, start + length, INSTRUCTIONS[pad]))
        pressed[start + length] = pad
        position = path[-1]
    state = np.array(positions, dtype=np.float32)
    commands = np.diff(state, axis=0) / MAX_SPEED + rng.normal(0.0, 0.05, size=(len(state) - 1, 2))
    actions = np.clip(commands, -1.0, 1.0).astype(np.float32)
    return Episode(episode_id, actions, {CAMERA: _render(state, pressed, rng)}, state, segments)


def would_have_stopped(history: list[dict[str, float]], measure: str, patience: int) -> tuple[int, int]:
    """(the step where `patience` evaluations without improvement would have ended the run, the step
    whose weights it would have kept), replaying training/loop.py's rule on the evaluations."""
    min_improvement = LoopConfig(steps=1).min_improvement
    best, best_step, since = float("inf"), 0, 0
    for entry in history:
        value = entry[measure]
        if best_step == 0 or value < best - min_improvement * abs(best):
            best, best_step, since = value, int(entry["step"]), 0
        else:
            since += 1
        if since >= patience:
            return int(entry["step"]), best_step
    return int(history[-1]["step"]), best_step


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--budget", choices=["default", "old"], default="default")
    parser.add_argument("--seed", type=int, default=0, help="data and training seed")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--annotated", type=int, default=10, help="annotated episodes")
    parser.add_argument("--test", type=int, default=5, help="test episodes")
    parser.add_argument("--log", action="store_true", help="one line per evaluation on stderr")
    parser.add_argument("--device", default="cpu", help="auto, cpu, cuda or cuda:N (training/device.py)")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)

    base = 1000 * args.seed
    annotated = [robot_episode(f"robot-{base + i}", base + i) for i in range(args.annotated)]
    test = [robot_episode(f"test-{base + i}", 10**6 + base + i) for i in range(args.test)]
    train, val, held = hold_out_for_validation(annotated, [])
    bounds = segment_bounds(train)
    model_cfg = model_config_for(
        FEATURES, None, len(INSTRUCTIONS), max_len=bounds.max_len, episodes=train, min_len=bounds.min_len
    )
    common = {
        "seed": args.seed,
        "k_max": bounds.k_max,
        "num_threads": args.threads,
        "progress": False,
        "log_epochs": args.log,
        "device": args.device,
    }
    if args.budget == "default":
        cfg = TrainConfig(**common)
    else:
        cfg = TrainConfig(max_steps=OLD_STEPS, patience=10**9, **common)
    epoch_steps = steps_per_epoch(train, cfg)
    print(
        f"data: {len(annotated)} annotated episodes x {SEGMENTS_PER_EPISODE} segments "
        f"({sum(e.num_steps for e in annotated)} steps), {len(held)} held out for validation "
        f"({', '.join(held)}); {len(test)} test episodes ({sum(e.num_steps for e in test)} steps); "
        f"{bounds.describe()}"
    )
    print(
        f"model reads {', '.join(f'{s.feature} ({s.kind})' for s in model_cfg.encoders)}; "
        f"{args.threads} thread(s), seed {args.seed}, device {args.device}"
    )
    patience = "none (epochs)" if cfg.epochs is not None else str(cfg.patience)
    print(
        f"budget {args.budget}: cap {step_cap(cfg, epoch_steps)} steps ({epoch_steps} steps/epoch), "
        f"evaluation every {evaluation_interval(cfg, epoch_steps)} steps, patience {patience}"
    )

    result = train_ps(train, val, INSTRUCTIONS, cfg, model_cfg)
    loop = result.loop
    assert loop is not None
    print(
        f"trained: {loop.steps} of at most {loop.cap} steps, stopped by {loop.stopped}; kept step "
        f"{loop.best_step} (val_error {loop.best.get(loop.measure, float('nan')):.4f}, val label accuracy "
        f"{result.label_accuracy:.3f}); {loop.seconds:.1f} s = {loop.seconds / loop.steps:.3f} s/step"
    )
    if args.budget == "old":
        stop, kept = would_have_stopped(loop.history, loop.measure, TrainConfig().patience)
        print(
            f"with patience {TrainConfig().patience} this run would have stopped at step {stop}, "
            f"keeping step {kept} (~{stop * loop.seconds / loop.steps:.0f} s)"
        )

    model = result.model.to(resolve_device(args.device))  # calibrated and run where it trained
    began = time.perf_counter()
    record = calibrate_ps_model(model, val)
    calibrated = time.perf_counter() - began
    began = time.perf_counter()
    predicted = {e.episode_id: segment_episode(model, e.with_segments([]), model.cfg.min_len) for e in test}
    scores = evaluate(
        predicted, {e.episode_id: e.segments for e in test}, {e.episode_id: e.num_steps for e in test}, (0, 2)
    )
    scored = time.perf_counter() - began

    def f1(tolerance: int) -> str:
        with_final = scores[boundary_key("f1", tolerance, True)]
        return (
            f"{scores[boundary_key('f1', tolerance, False)]:.3f} (with the final boundary {with_final:.3f})"
        )

    print(
        f"calibrated on the {len(val)} held-out episodes in {calibrated:.1f} s "
        f"(end bias {record['end_bias']['bias']:+.2f}); segmented the test episodes in {scored:.1f} s"
    )
    print(
        f"test ({scores['episodes']} episodes, {scores['true_segments']} segments, "
        f"{scores['pred_segments']} predicted): boundary F1 +-2 {f1(2)}; exact {f1(0)}; "
        f"label accuracy {scores['label_accuracy']:.3f}"
    )


if __name__ == "__main__":
    main()
