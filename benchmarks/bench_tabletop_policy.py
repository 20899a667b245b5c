"""Does data matter? Success of the ``tabletop.bc`` policy trained on shares of the annotated data.

Policies with the same settings and seed are trained on nested, seeded shares (default 10/25/50/100%)
of a tabletop dataset's annotated segments (train + val splits), each evaluated in the simulator on the
same fixed seeded episodes (evaluation.py; success = the task oracle says done within
spec.EVAL_STEP_BUDGET steps). Every share gets the same number of optimizer steps, so only the data
differs.

    .venv/bin/python benchmarks/bench_tabletop_policy.py --data /tmp/tt-paper --steps 400
    .venv/bin/python benchmarks/bench_tabletop_policy.py --preset small      # generates it into /tmp
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from playseg_core.augment.policies import load_policy_learner
from playseg_core.augment.retraining import annotated_clips
from playseg_core.data.dataset import PlayDataset, is_dataset
from playseg_core.domains.tabletop import CAMERA, generate_dataset
from playseg_core.experiment.runner import EVAL_SEED


def parse_args() -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--data", help="an existing tabletop dataset (default: generate --preset)")
    parser.add_argument(
        "--preset", default="small", help="generated into a temporary directory without --data"
    )
    parser.add_argument("--shares", default="0.1,0.25,0.5,1.0", help="shares of the annotated segments")
    parser.add_argument("--steps", type=int, default=400, help="optimizer steps per policy")
    parser.add_argument("--batch-size", type=int, default=32)
    parser.add_argument("--episodes", type=int, default=100, help="evaluation episodes per policy")
    parser.add_argument("--seed", type=int, default=0, help="policy seed and the shares' draw")
    parser.add_argument("--threads", type=int, default=1, help="torch threads")
    parser.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="any other policy setting (BCTrainConfig), e.g. --set camera_encoder=keypoints; repeatable",
    )
    parser.add_argument("--json", help="write the rows here too")
    return parser.parse_args()


def main() -> None:
    args = parse_args()
    torch.set_num_threads(args.threads)
    shares = [float(s) for s in args.shares.split(",")]
    extra = dict(item.split("=", 1) for item in args.set if "=" in item)
    if len(extra) != len(args.set):
        raise SystemExit(f"--set takes KEY=VALUE, got {args.set}")
    if not all(0.0 < s <= 1.0 for s in shares):
        raise SystemExit(f"--shares must be in (0, 1], got {args.shares}")
    with tempfile.TemporaryDirectory(prefix="bench-tt-policy-") as scratch:
        data = Path(args.data) if args.data else Path(scratch) / "data"
        if not is_dataset(data):
            if args.data:
                raise SystemExit(f"--data {data}: not a playseg dataset")
            print(f"generating tabletop preset {args.preset!r} into {data} ...")
            generate_dataset(data, args.preset, seed=0, workers=2, progress=False)
        dataset = PlayDataset.open(data)
        clips = annotated_clips([*dataset.episodes("train"), *dataset.episodes("val")])
        image_size = dataset.features[CAMERA].shape[0]
        order = np.random.default_rng(args.seed).permutation(len(clips))  # nested shares: one draw
        print(
            f"{data}: {len(clips)} annotated segments; {args.steps} steps x batch {args.batch_size} per "
            f"policy, {args.episodes} evaluation episodes (seeds from {EVAL_SEED}), {args.threads} thread(s)"
            f"{', settings ' + str(extra) if extra else ''}"
        )
        rows = []
        for share in shares:
            chosen = [clips[i] for i in sorted(order[: max(1, round(share * len(clips)))])]
            config = {
                "steps": args.steps, "batch_size": args.batch_size, "seed": args.seed,
                "image_size": image_size, "num_threads": args.threads, **extra,
            }  # fmt: skip
            learner = load_policy_learner("tabletop.bc", config)
            began = time.perf_counter()
            model, report = learner.train(chosen)
            trained = time.perf_counter() - began
            evaluation = learner.evaluate(model, args.episodes, EVAL_SEED)
            se = float(
                np.sqrt(evaluation.success_rate * (1 - evaluation.success_rate) / evaluation.num_episodes)
            )
            rows.append(
                {
                    "share": share,
                    "segments": len(chosen),
                    "success": evaluation.success_rate,
                    "standard_error": round(se, 4),
                    "by_family": evaluation.family_success,
                    "val_loss": report.val_loss,
                    "baseline_val_loss": report.baseline_val_loss,
                    "val_moved_entity_accuracy": report.val_moved_entity_accuracy,
                    "val_related_entity_accuracy": report.val_related_entity_accuracy,
                    "train_seconds": round(trained, 1),
                    "eval_seconds": round(evaluation.seconds, 1),
                }
            )
            families = ", ".join(
                f"{name} {done}/{given}" for name, (done, given) in evaluation.family_success.items()
            )
            print(
                f"{share:>5.0%} ({len(chosen):>4} segments): success {evaluation.success_rate:.3f} +- {se:.3f} "
                f"[{families}]; val loss {report.val_loss:.3f} (mean-action {report.baseline_val_loss:.3f}); "
                + (
                    f"moved entity found {report.val_moved_entity_accuracy:.2f}; "
                    if report.val_moved_entity_accuracy is not None
                    else ""
                )
                + (
                    f"related entity found {report.val_related_entity_accuracy:.2f}; "
                    if report.val_related_entity_accuracy is not None
                    else ""
                )
                + f"train {trained:.0f} s, eval {evaluation.seconds:.0f} s",
                flush=True,
            )
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=2))


if __name__ == "__main__":
    main()
