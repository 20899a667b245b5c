"""Measure tabletop play generation: steps/s per core with rendering (where the time goes), the
teleoperator's success rate per family, the instruction-length distribution, and a preset's time and size.

.venv/bin/python benchmarks/bench_tabletop_generation.py                  # single core, 40 episodes
.venv/bin/python benchmarks/bench_tabletop_generation.py --preset small --workers 2

The machine may be shared: CPU seconds (this process) are reported next to wall seconds, and the figure
per core uses the CPU seconds.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from playseg_core.domains.tabletop.generate import generate_dataset, get_preset, length_summary
from playseg_core.domains.tabletop.play import PlayConfig, PlayStats, generate_episode
from playseg_core.domains.tabletop.render import Renderer
from playseg_core.domains.tabletop.sim import TabletopSim
from playseg_core.domains.tabletop.spec import MAX_SPEED


def measure_parts(steps: int = 3000) -> dict[str, float]:
    """Microseconds per control step of the physics alone, of the camera alone."""
    sim = TabletopSim()
    sim.place_randomly(np.random.default_rng(0))
    actions = np.random.default_rng(1).uniform(-MAX_SPEED, MAX_SPEED, size=(steps, 2))
    started = time.process_time()
    for action in actions:
        sim.step(action)
    physics = time.process_time() - started
    renderer, scene = Renderer(), sim.scene()
    started = time.process_time()
    for _ in range(steps):
        renderer.render(scene)
    render = time.process_time() - started
    return {"physics_us": physics / steps * 1e6, "render_us": render / steps * 1e6}


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--episodes", type=int, default=40, help="episodes for the single-core figures")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--preset", choices=("tiny", "small", "paper"), default=None, help="also time a preset"
    )
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--out", default=None, help="where to write the preset (default: a temporary dir)")
    args = parser.parse_args()

    config = PlayConfig()
    generate_episode(PlayConfig(tasks_per_episode=(1, 1)), seed=10**6)  # warm-up: imports
    stats, steps = PlayStats(), 0
    wall, cpu = time.perf_counter(), time.process_time()
    for index in range(args.episodes):
        played = generate_episode(config, seed=args.seed + index)
        stats.merge(played.stats)
        steps += played.episode.num_steps
    wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
    parts = measure_parts()
    print(
        f"single core: {args.episodes} episodes, {steps} steps ({steps / args.episodes:.0f} per episode) in "
        f"{cpu:.2f} CPU s ({wall:.2f} s wall) -> {steps / cpu:.0f} steps/s per core with rendering "
        f"({steps / wall:.0f} by the wall clock); physics {parts['physics_us']:.0f} us/step, "
        f"96x96 camera {parts['render_us']:.0f} us/step"
    )
    attempted, solved = sum(stats.attempted.values()), sum(stats.solved.values())
    families = ", ".join(
        f"{family} {stats.solved.get(family, 0)}/{count}" for family, count in sorted(stats.attempted.items())
    )
    print(f"teleoperator: {solved}/{attempted} tasks solved ({stats.success_rate:.1%}): {families}")
    print(
        f"unlabelled steps: {stats.idle_steps} idle + {stats.failed_steps} of failed tasks "
        f"({(stats.idle_steps + stats.failed_steps) / steps:.1%} of all steps)"
    )
    lengths = length_summary(stats.task_lengths)
    print(
        f"instruction length (steps at 10 Hz): mean {lengths['mean']:.1f}, p5 {lengths['p5']:.0f}, "
        f"p25 {lengths['p25']:.0f}, median {lengths['median']:.0f}, p75 {lengths['p75']:.0f}, "
        f"p95 {lengths['p95']:.0f}, max {lengths['max']}; {lengths['share_20_to_100']:.1%} in 20-100"
    )
    if args.preset is None:
        return
    preset = get_preset(args.preset)
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(args.out) if args.out else Path(tmp) / args.preset
        summary = generate_dataset(out, preset, seed=args.seed, workers=args.workers)
        print(
            f"preset {summary.preset}: {summary.episodes} episodes, {summary.steps} steps, "
            f"segments {summary.segments_per_split}, {summary.bytes_on_disk / 1e6:.1f} MB, "
            f"{summary.seconds:.1f} s with {summary.workers} workers ({summary.steps_per_second:.0f} steps/s "
            f"overall); teleoperator {summary.teleop.success_rate:.1%}"
        )


if __name__ == "__main__":
    main()
