"""A generic robot's bags through the CLI's defaults: does PS segment its unannotated play?

    nice -n 10 .venv/bin/python benchmarks/bench_generic_robot.py [--bags 40] [--seconds 60] [--work DIR]

The robot (benchmarks/generic_robot.py) has no domain package: a five-joint arm with a gripper, a 64x48
camera (sensor_msgs/Image, 30 Hz), JointState (100 Hz) and the operator's Twist (30 Hz), six skills
in play with pauses between some; a quarter of the bags carry their skills as sidecar labels, every
bag its ground truth in another sidecar. Then exactly these commands, with their defaults (printed as
run, each with its time): convert every bag at 10 steps/s, train PS, segment the unannotated episodes
(the `play` split), convert the bags again with the ground truth, evaluate the segments against it.

Printed: boundary F1 exact and within +-2 steps (without the trivial final boundary; with it in
brackets), per-step label accuracy, per skill the label accuracy of its steps and the share of its
ends found within +-2 steps, against the targets F1 (+-2) >= 0.95 and label accuracy >= 0.95.
Bags are kept in --work and reused when they are there with the same size settings.

Prints figures; not a test.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

from generic_robot import INSTRUCTIONS, pipeline, write_fleet

from playseg_core.data.dataset import PlayDataset
from playseg_core.ps.metrics import boundary_key, match_boundaries

TARGET = 0.95


def per_skill(segmented: Path, truth: Path) -> dict[str, tuple[float, float, int]]:
    """Per instruction: (label accuracy of its true steps, share of its true ends matched within +-2
    steps by a predicted end, its true segments)."""
    predicted = PlayDataset.open(segmented)
    reference = PlayDataset.open(truth)
    truth_by_id = {r.episode_id: reference.segments(i, truth=True) for i, r in enumerate(reference.records)}
    counts = {name: [0, 0, 0, 0] for name in INSTRUCTIONS}  # correct steps, steps, ends found, segments
    for index, record in enumerate(predicted.records):
        pred = predicted.segments(index, truth=True)
        labels: list[str | None] = [None] * record.num_steps
        for seg in pred:
            labels[seg.start : seg.end] = [seg.instruction] * seg.length
        ends = [seg.end for seg in pred]
        for seg in truth_by_id[record.episode_id]:
            count = counts[seg.instruction]
            count[0] += sum(labels[t] == seg.instruction for t in range(seg.start, seg.end))
            count[1] += seg.length
            count[2] += match_boundaries(ends, [seg.end], 2)
            count[3] += 1
    return {name: (c[0] / max(c[1], 1), c[2] / max(c[3], 1), c[3]) for name, c in counts.items()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--bags", type=int, default=40)
    parser.add_argument("--seconds", type=float, default=60.0, help="each bag's length")
    parser.add_argument("--annotated", type=int, help="bags with labels (default: a quarter)")
    parser.add_argument("--seed", type=int, default=0, help="the robot's play")
    parser.add_argument("--work", default="build/bench_generic_robot", help="bags, datasets and the model")
    args = parser.parse_args()

    root = Path(args.work)
    annotated = args.bags // 4 if args.annotated is None else args.annotated
    settings = {"bags": args.bags, "seconds": args.seconds, "annotated": annotated, "seed": args.seed}
    stamp = root / "bags.json"
    if not stamp.exists() or json.loads(stamp.read_text()) != settings:
        shutil.rmtree(root, ignore_errors=True)
        root.mkdir(parents=True)
        began = time.perf_counter()
        write_fleet(root, args.bags, args.seconds, annotated, seed=args.seed)
        stamp.write_text(json.dumps(settings))
        print(
            f"wrote {args.bags} bags of {args.seconds:.0f} s in {time.perf_counter() - began:.0f} s",
            flush=True,
        )
    else:
        for output in ("data", "ps.pt", "segmented", "truth"):
            path = root / output
            shutil.rmtree(path) if path.is_dir() else path.unlink(missing_ok=True)
    size = sum(f.stat().st_size for f in (root / "bags").rglob("*") if f.is_file())
    print(f"bags: {root}/bags ({size / 2**20:.0f} MiB, {annotated} of {args.bags} annotated)")

    seconds: dict[str, float] = {}
    for command in pipeline(root):
        print(f"$ playseg {' '.join(command)}", flush=True)
        log = root / f"{command[0]}-{len(seconds)}.log"
        began = time.perf_counter()
        with log.open("w") as out:
            code = subprocess.call(
                [sys.executable, "-m", "playseg_ros.cli", *command], stdout=out, stderr=out
            )
        seconds[command[0] + str(len(seconds))] = elapsed = time.perf_counter() - began
        lines = [line.split("\r")[-1] for line in log.read_text().splitlines() if line.strip()]
        tail = [line for line in lines if not line.startswith("run_")][-3:]
        print("\n".join(f"    {line}" for line in tail))
        print(f"    ({elapsed:.0f} s, exit {code}; log {log})", flush=True)
        if code != 0:
            raise SystemExit(f"playseg {command[0]} failed")

    metrics = json.loads((root / "segmented" / "metrics.json").read_text())

    def f1(tolerance: int) -> str:
        return (
            f"{metrics[boundary_key('f1', tolerance, False)]:.3f} "
            f"({metrics[boundary_key('f1', tolerance, True)]:.3f} with the final boundary)"
        )

    f1_2, label = metrics[boundary_key("f1", 2, False)], metrics["label_accuracy"]
    met = "met" if f1_2 >= TARGET and label >= TARGET else "missed"
    print(
        f"\nunannotated bags: {metrics['episodes']} episodes, {metrics['true_segments']} true segments, "
        f"{metrics['pred_segments']} kept by the model\n"
        f"boundary F1 exact {f1(0)}, +-2 {f1(2)}; label accuracy {label:.3f}; segment precision "
        f"{metrics['segment_precision']:.3f}\n"
        f"targets F1 (+-2) >= {TARGET} and label accuracy >= {TARGET}: {met}; training took "
        f"{seconds['train1']:.0f} s"
    )
    print("per skill: label accuracy, ends found within +-2 steps, true segments")
    for name, (accuracy, ends, count) in per_skill(root / "segmented", root / "truth").items():
        print(f"  {name:34s} {accuracy:.3f}  {ends:.3f}  {count}")


if __name__ == "__main__":
    main()
