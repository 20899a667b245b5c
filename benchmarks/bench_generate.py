"""Measure BabyAI play generation: steps/s per core with rendering, and a preset's time and size.

.venv/bin/python benchmarks/bench_generate.py                 # single-core steps/s
.venv/bin/python benchmarks/bench_generate.py --preset small --workers 2
"""

from __future__ import annotations

import argparse
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from playseg_core.domains.babyai.generate import generate_dataset, get_preset
from playseg_core.domains.babyai.play import PlayConfig, generate_episode


@dataclass
class CoreFigures:
    episodes: int
    steps: int
    segments: int
    seconds: float
    task_lengths: np.ndarray


def measure_single_core(episodes: int, seed: int) -> CoreFigures:
    """Generate ``episodes`` episodes in this process (one core), rendering every frame."""
    config = PlayConfig()
    generate_episode(config, seed=10**6)  # warm-up: imports, tile cache
    started = time.perf_counter()
    steps = 0
    lengths: list[int] = []
    for index in range(episodes):
        episode = generate_episode(config, seed=seed + index)
        steps += episode.num_steps
        lengths.extend(seg.length for seg in episode.segments)
    seconds = time.perf_counter() - started
    return CoreFigures(episodes, steps, len(lengths), seconds, np.array(lengths))


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--episodes", type=int, default=200, help="episodes for the single-core figure")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--preset", choices=("tiny", "small", "paper"), default=None, help="also time a preset"
    )
    parser.add_argument("--annotated-share", type=float, default=None)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--out", default=None, help="where to write the preset (default: a temporary dir)")
    args = parser.parse_args()

    core = measure_single_core(args.episodes, args.seed)
    lengths = core.task_lengths
    print(
        f"single core: {core.episodes} episodes, {core.steps} steps, {core.segments} segments in "
        f"{core.seconds:.2f} s -> {core.steps / core.seconds:.0f} steps/s per core with rendering"
    )
    print(
        f"task length: mean {lengths.mean():.2f}, median {np.median(lengths):.0f}, max {lengths.max()} steps; "
        f"{core.segments / core.episodes:.2f} tasks per episode"
    )
    if args.preset is None:
        return
    preset = get_preset(args.preset, annotated_share=args.annotated_share)
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(args.out) if args.out else Path(tmp) / args.preset
        summary = generate_dataset(out, preset, seed=args.seed, workers=args.workers)
        print(
            f"preset {summary.preset}: {summary.episodes} episodes, {summary.steps} steps, "
            f"segments {summary.segments_per_split}, {summary.bytes_on_disk / 1e6:.1f} MB, "
            f"{summary.seconds:.1f} s with {summary.workers} workers "
            f"({summary.steps_per_second:.0f} steps/s overall, {summary.bytes_on_disk / max(summary.steps, 1):.0f} "
            "bytes/step)"
        )


if __name__ == "__main__":
    main()
