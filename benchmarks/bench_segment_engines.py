"""Segmentation of a fleet's recordings with each engine: bags per minute of `playseg convert --segment`
and episodes per minute of `playseg segment`, local (1 and 2 processes) against Ray (1 and 2 actors or
tasks, a local instance started by each run: its start-up is part of the time, as a user pays it).

Tabletop robot bags (standard messages, JPEG camera; playseg_ros/tabletop/bags.py) and a tabletop PS
checkpoint (default: the demo's sample model). Every run's output is compared with the local engine's.

    .venv/bin/python benchmarks/bench_segment_engines.py [--bags 8] [--model bags/models/tabletop-ps.pt]
"""

from __future__ import annotations

import argparse
import contextlib
import io
import shutil
import subprocess
import sys
import time
from pathlib import Path

from playseg_core.data.dataset import PlayDataset
from playseg_ros.cli import main

ROOT = Path(__file__).resolve().parents[1]
RUNS = [("local", 1), ("local", 2), ("ray", 1), ("ray", 2)]


def timed(argv: list[str]) -> float:
    began = time.perf_counter()
    with contextlib.redirect_stdout(io.StringIO()):
        code = main(argv)
    if code != 0:
        sys.exit(f"playseg {' '.join(argv)}: exit {code}")
    return time.perf_counter() - began


def segment_rows(path: Path) -> list[tuple]:
    data = PlayDataset.open(path)
    return [
        (r.episode_id, s.start, s.end, s.instruction)
        for i, r in enumerate(data.records)
        for s in data.segments(i, truth=True)
    ]


def main_bench() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--bags", type=int, default=8)
    parser.add_argument("--model", default=str(ROOT / "bags" / "models" / "tabletop-ps.pt"))
    parser.add_argument("--dir", default="/tmp/bench_segment_engines")
    args = parser.parse_args()
    root = Path(args.dir)
    shutil.rmtree(root, ignore_errors=True)
    bags = root / "bags"
    subprocess.run(
        [sys.executable, "-m", "playseg_ros.tabletop.bags", "--out", str(bags), "--episodes", str(args.bags),
         "--annotated", "0", "--images", "jpeg"],
        check=True, capture_output=True,
    )  # fmt: skip
    mapping = str(bags / "mapping.yaml")
    print(f"{args.bags} tabletop bags, model {args.model}")
    convert_argv = ["convert", str(bags), "--mapping", mapping, "--segment", args.model, "--quiet"]
    compare_engines("convert --segment", convert_argv, RUNS, root, args.bags, "bags")
    data = root / "convert-local-1"
    episodes = len(PlayDataset.open(data).episode_indices("play"))
    segment_argv = ["segment", "--model", args.model, "--input", str(data), "--splits", "play"]
    local_once = [run for run in RUNS if run != ("local", 2)]  # `playseg segment` runs in one process locally
    compare_engines("segment", segment_argv, local_once, root, episodes, "episodes")


def compare_engines(
    name: str, argv: list[str], runs: list[tuple[str, int]], root: Path, count: int, unit: str
) -> None:
    """Time ``argv`` with each (engine, workers) of ``runs``; print the rate in ``unit``/min and whether
    the segments equal the first run's."""
    reference = None
    for engine, workers in runs:
        out = root / f"{name.split()[0]}-{engine}-{workers}"
        seconds = timed([*argv, "--out", str(out), "--engine", engine, "--workers", str(workers)])
        rows = segment_rows(out)
        reference = rows if reference is None else reference
        same = "same output" if rows == reference else "OUTPUT DIFFERS"
        print(
            f"{name:18s} {engine:5s} x{workers}: {seconds:6.1f} s, {count / seconds * 60:6.1f} {unit}/min ({same})"
        )


if __name__ == "__main__":
    main_bench()
