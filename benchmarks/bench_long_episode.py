"""Segmenting one long robot-shaped episode: time and peak memory grow linearly with its length.

    .venv/bin/python benchmarks/bench_long_episode.py [--steps 10000,100000] [--max-len 100] [--threads 1]

A randomly initialised PS model (speed and memory do not depend on the weights) reading a 96x96 camera
(image_cnn), a 7-D state (state_mlp) and 7-D continuous actions (continuous_action), L_max 100. The
camera frames are one frame broadcast over the episode (no memory of their own), so the figure is the
segmentation's own memory. Each size runs in a fresh process; peak RSS is that process's.
"""

from __future__ import annotations

import argparse
import subprocess
import sys

CHILD = """
import resource, sys, time
import numpy as np, torch
from playseg_core.data.episode import Episode
from playseg_core.data.features import ACTION, STATE, Feature, Features
from playseg_core.ps.model import PSModel
from playseg_core.ps.segmentation import segment_episode
from playseg_core.ps.training import model_config_for

steps, max_len, threads = int(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3])
torch.set_num_threads(threads)
camera = "observation.images.front"
features = Features.of([
    Feature(camera, "image", "uint8", (96, 96, 3)),
    Feature(STATE, "state", "float32", (7,)),
    Feature(ACTION, "action", "float32", (7,)),
], fps=10.0)
rng = np.random.default_rng(0)
frame = rng.integers(0, 256, size=(96, 96, 3), dtype=np.uint8)
episode = Episode("long", rng.normal(size=(steps, 7)).astype(np.float32),
                  {camera: np.broadcast_to(frame, (steps + 1, 96, 96, 3))},
                  rng.normal(size=(steps + 1, 7)).astype(np.float32))
torch.manual_seed(0)
model = PSModel(model_config_for(features, None, 4, max_len=max_len, episodes=[episode]), ["a", "b", "c", "d"])
began = time.perf_counter()
segments = segment_episode(model, episode)
seconds = time.perf_counter() - began
print(steps, len(segments), round(seconds, 1), round(steps / seconds), round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024))
"""


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--steps", default="10000,100000", help="episode lengths, comma-separated")
    parser.add_argument("--max-len", type=int, default=100, help="L_max")
    parser.add_argument("--threads", type=int, default=1, help="torch threads")
    args = parser.parse_args()
    print(f"{'steps':>8} {'segments':>9} {'seconds':>8} {'steps/s':>8} {'peak RSS MB':>12}")
    for steps in args.steps.split(","):
        result = subprocess.run(
            [sys.executable, "-c", CHILD, steps, str(args.max_len), str(args.threads)],
            capture_output=True,
            text=True,
            check=True,
        )
        count, segments, seconds, rate, peak = result.stdout.split()
        print(f"{count:>8} {segments:>9} {seconds:>8} {rate:>8} {peak:>12}")


if __name__ == "__main__":
    main()
