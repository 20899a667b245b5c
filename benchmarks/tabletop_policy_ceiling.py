"""What the tabletop policy could reach if it knew where things are: a perception oracle.

The ``bc`` policy from pixels learns the "move the arm" tasks and almost none of the block pushes
(docs/studies/2026-12-02-tabletop-policy-pushes.md). This script asks whether the pushes are learnable from
the annotated segments at all, and whether more segments help, when perception is solved: each step's
observation is the effector's position plus the positions the instruction names (the named block and the
other block relative to the effector, the named region's centre relative to the thing to move; zeros
where the instruction names none), read from the simulator. The annotated episodes are replayed from their
seeds (generation is deterministic; the replayed commands are checked against the recorded ones), and the
evaluation gives the policy the same oracle features on the same episodes `bench_tabletop_policy.py` uses.

Rows: nested seeded shares of the annotated segments, each with the measured velocity hidden (the
default) or read (``--read-velocity``), which lets behaviour cloning copy the last command instead of
choosing it.

    .venv/bin/playseg generate --domain tabletop --preset paper --out /tmp/ttps/data --workers 2 --quiet
    .venv/bin/python benchmarks/tabletop_policy_ceiling.py --data /tmp/ttps/data
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Sequence

import numpy as np
import torch

from playseg_core.augment.bc_policy import BCPolicy, BCPolicyLearner
from playseg_core.augment.retraining import annotated_clips
from playseg_core.data.dataset import PlayDataset
from playseg_core.data.episode import Episode, SegmentClip
from playseg_core.data.features import ACTION, STATE, Feature, Features
from playseg_core.domains.tabletop.evaluation import evaluation_start
from playseg_core.domains.tabletop.instructions import Task, is_done, region_box, task_for
from playseg_core.domains.tabletop.play import PlayConfig, replay_scenes
from playseg_core.domains.tabletop.robot_log import dataset_play_config
from playseg_core.domains.tabletop.sim import Scene
from playseg_core.domains.tabletop.spec import EVAL_STEP_BUDGET, MAX_SPEED
from playseg_core.experiment.runner import EVAL_SEED

ORACLE_NAMES = (
    "effector_x", "effector_y", "effector_velocity_x", "effector_velocity_y",
    "block_dx", "block_dy", "other_dx", "other_dy", "region_dx", "region_dy",
)  # fmt: skip


def oracle_features(task: Task, scene: Scene) -> np.ndarray:
    """The effector's state, then where the instruction's things are relative to what has to reach them."""
    effector = scene.effector
    block = scene.blocks[task.block] - effector if task.block >= 0 else np.zeros(2)
    other = scene.blocks[task.other] - effector if task.other >= 0 else np.zeros(2)
    region = np.zeros(2)
    if task.region:
        x_low, y_low, x_high, y_high = region_box(task.region)
        mover = scene.blocks[task.block] if task.block >= 0 else effector
        region = np.array([(x_low + x_high) / 2, (y_low + y_high) / 2]) - mover
    return np.concatenate([effector, scene.effector_velocity, block, other, region]).astype(np.float32)


def oracle_clips(episodes: Sequence[Episode], config: PlayConfig) -> list[SegmentClip]:
    """Every annotated segment with oracle observations, from its episode replayed."""
    clips = []
    for episode in episodes:
        if not episode.segments:
            continue
        scenes, _ = replay_scenes(config, episode.episode_id, episode.actions)
        for clip in annotated_clips([episode]):
            task = task_for(clip.segment.instruction)
            in_clip = scenes[clip.segment.start : clip.segment.end + 1]
            state = np.stack([oracle_features(task, scene) for scene in in_clip])
            clips.append(SegmentClip(clip.episode_id, clip.segment, clip.actions, {}, state, "annotation"))
    return clips


def evaluate(policy: BCPolicy, num_episodes: int) -> tuple[float, dict[str, list[int]]]:
    """Success on the evaluation episodes of `bench_tabletop_policy.py`, all run in lockstep."""
    runs = [evaluation_start(EVAL_SEED + k) for k in range(num_episodes)]
    starts = [sim.scene() for sim, _ in runs]
    running, done = list(range(num_episodes)), [False] * num_episodes
    for _ in range(EVAL_STEP_BUDGET):
        rows = np.stack([oracle_features(runs[k][1].task, runs[k][0].scene()) for k in running])
        actions = policy.act({STATE: rows}, [runs[k][1].task.text for k in running])
        still = []
        for k, action in zip(running, actions, strict=True):
            sim, episode = runs[k]
            sim.step(np.clip(action, -MAX_SPEED, MAX_SPEED))
            if is_done(episode.task, sim.scene(), starts[k]):
                done[k] = True
            else:
                still.append(k)
        running = still
        if not running:
            break
    families: dict[str, list[int]] = {}
    for (_, episode), success in zip(runs, done, strict=True):
        tally = families.setdefault(episode.task.family, [0, 0])
        tally[0] += success
        tally[1] += 1
    return sum(done) / num_episodes, dict(sorted(families.items()))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--data", required=True, help="a generated tabletop dataset")
    parser.add_argument("--shares", default="0.1,0.25,0.5,1.0", help="shares of the annotated segments")
    parser.add_argument("--steps", type=int, default=3000, help="optimizer steps per policy")
    parser.add_argument("--batch-size", type=int, default=64)
    parser.add_argument("--episodes", type=int, default=100, help="evaluation episodes per policy")
    parser.add_argument("--seed", type=int, default=0, help="policy seed and the shares' draw")
    parser.add_argument("--read-velocity", action="store_true", help="the policy reads the velocity")
    args = parser.parse_args()
    torch.set_num_threads(1)
    began = time.perf_counter()
    try:  # no dataset, not generated tabletop play, or a replay other than the recording: one line
        dataset = PlayDataset.open(args.data)
        clips = oracle_clips(
            [*dataset.episodes("train"), *dataset.episodes("val")], dataset_play_config(dataset)
        )
    except (OSError, ValueError) as error:
        raise SystemExit(str(error)) from None
    features = Features.of(
        [
            Feature(STATE, "state", "float32", (len(ORACLE_NAMES),), names=ORACLE_NAMES),
            dataset.features[ACTION],
        ],
        dataset.features.fps,
    )
    hidden = "" if args.read_velocity else "effector_velocity_x,effector_velocity_y"
    print(
        f"{args.data}: {len(clips)} annotated segments replayed in {time.perf_counter() - began:.0f} s; "
        f"{args.steps} steps x {args.batch_size}, {args.episodes} evaluation episodes, velocity "
        f"{'read' if args.read_velocity else 'hidden'}"
    )
    order = np.random.default_rng(args.seed).permutation(len(clips))
    for share in [float(s) for s in args.shares.split(",")]:
        chosen = [clips[i] for i in sorted(order[: max(2, round(share * len(clips)))])]
        settings = {
            "steps": args.steps, "batch_size": args.batch_size, "seed": args.seed,
            "instruction_film": True, "state_exclude": hidden,
        }  # fmt: skip
        learner = BCPolicyLearner.from_config(settings, features)
        began = time.perf_counter()
        policy, report = learner.train(chosen)
        success, families = evaluate(policy, args.episodes)
        se = float(np.sqrt(success * (1 - success) / args.episodes))
        tally = ", ".join(f"{name} {done}/{given}" for name, (done, given) in families.items())
        print(
            f"{share:>5.0%} ({len(chosen):>4} segments): success {success:.2f} +- {se:.2f} [{tally}]; "
            f"val loss {report.val_loss:.3f} (mean action {report.baseline_val_loss:.3f}); "
            f"{time.perf_counter() - began:.0f} s",
            flush=True,
        )


if __name__ == "__main__":
    main()
