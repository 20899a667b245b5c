"""The spread of `make demo`'s policy between training seeds: the seed term of the noise the demo states.

Trains the demo's policy (the trainer node's settings in playseg_ros/demo.py) on the annotated sample bag
with several seeds, evaluates each on the demo's fixed episodes, and prints success per seed, the mean and
the std (population, as the demo's `DEMO_POLICY_SEED_STD`).

    .venv/bin/python benchmarks/bench_demo_policy.py [--seeds 0 1 2 3 4]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from playseg_core.augment.policies import load_policy_learner
from playseg_core.augment.policy import torch_threads
from playseg_core.augment.retraining import TrainerConfig, annotated_clips
from playseg_ros.demo import DEMO_POLICY
from playseg_ros.play_bags import read_play_bag


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    parser.add_argument("--bag", default="bags/annotated", help="the annotated sample bag")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3, 4])
    args = parser.parse_args()

    clips = annotated_clips(read_play_bag(args.bag))
    eval_seed = TrainerConfig("", "").eval_seed  # the trainer node's evaluation episodes
    print(f"{len(clips)} annotated segments from {args.bag}; policy settings {DEMO_POLICY}")
    rates = []
    for seed in args.seeds:
        learner = load_policy_learner(
            "babyai.film",
            {
                "steps": DEMO_POLICY["train_steps"],
                "batch_size": DEMO_POLICY["batch_size"],
                "channels": DEMO_POLICY["policy_channels"],
                "seed": seed,
            },
        )
        began = time.perf_counter()
        with torch_threads(1):
            model, _ = learner.train(clips)
            evaluation = learner.evaluate(model, DEMO_POLICY["eval_episodes"], eval_seed)
        rates.append(evaluation.success_rate)
        print(f"seed {seed}: success {evaluation.success_rate:.3f} ({time.perf_counter() - began:.0f} s)")
    print(f"mean {np.mean(rates):.3f}, std over seeds {np.std(rates):.3f} ({len(rates)} seeds)")


if __name__ == "__main__":
    main()
