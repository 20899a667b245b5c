"""Peak memory of `playseg segment` on play bags of growing length: it streams episode by episode, so the
peak should not grow with the bag.

    .venv/bin/python benchmarks/bench_segment_memory.py [--episodes 20,80,320] [--work DIR]

Writes BabyAI play bags of the given numbers of episodes (about 50 steps each, 64x64 frames), a randomly
initialised PS model (speed and memory do not depend on the weights), then runs `playseg segment` on each
bag in a fresh process and prints its peak RSS and throughput.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch

from playseg_core.domains.babyai.play import PlayConfig, generate_episode
from playseg_core.domains.babyai.spec import DOMAIN, INSTRUCTIONS
from playseg_core.ps.model import PSModel, save_model
from playseg_core.ps.training import model_config_for
from playseg_ros.play_bags import DataInfo, write_play_bag

CHILD = """
import resource, sys
from playseg_ros.offline import segment
segment(sys.argv[1], sys.argv[2], sys.argv[3], ["play"], 1, False)
print("peak_rss_mb", resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024)
"""


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--episodes", default="20,80,320", help="bag sizes in episodes, comma-separated")
    parser.add_argument("--work", help="working directory (default: a temporary one)")
    args = parser.parse_args()
    work = Path(args.work or tempfile.mkdtemp(prefix="bench-segment-"))
    config = PlayConfig()
    torch.manual_seed(0)
    model = work / "ps-random.pt"
    save_model(
        model, PSModel(model_config_for(config.features, DOMAIN, len(INSTRUCTIONS)), list(INSTRUCTIONS))
    )
    info = DataInfo(config.features, DOMAIN, INSTRUCTIONS)
    print(f"{'episodes':>8} {'steps':>8} {'bag MB':>8} {'peak RSS MB':>12} {'steps/s':>8}")
    for count in (int(n) for n in args.episodes.split(",")):
        bag = work / f"play-{count}"
        episodes = (generate_episode(config, 10_000 + i) for i in range(count))
        summary = write_play_bag(bag, episodes, annotated=False, info=info)
        steps = summary.topic_counts["/play/steps"] - count  # T+1 messages per episode
        size = sum(f.stat().st_size for f in bag.glob("*.mcap")) / 1e6
        began = time.perf_counter()
        result = subprocess.run(
            [sys.executable, "-c", CHILD, str(model), str(bag), str(work / f"out-{count}")],
            capture_output=True,
            text=True,
            check=True,
        )
        seconds = time.perf_counter() - began
        peak = next(
            float(line.split()[1]) for line in result.stdout.splitlines() if line.startswith("peak_rss_mb")
        )
        print(f"{count:>8} {steps:>8} {size:>8.1f} {peak:>12.0f} {steps / seconds:>8.0f}")


if __name__ == "__main__":
    main()
