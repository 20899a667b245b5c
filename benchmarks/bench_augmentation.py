"""Policy success with and without Play Segmentation augmentation (the paper's BabyAI experiment, scaled).

    .venv/bin/python benchmarks/bench_augmentation.py --data data/ps10k --model models/ps10k.pt \
        --play-episodes 1500 [--steps 3000 --channels 32 --seeds 0]

Policies are trained on
  1. the annotated `train` split of --data only;
  2. the same plus the segments the PS model extracts from --play-episodes unannotated play episodes
     (generated from seeds 200,000 up, so disjoint from --data), each labelled by the model's label head
     and kept if its confidence passes the checkpoint's calibrated threshold;
  3. the same plus that play's ground-truth segments (what perfect segmentation and labelling would add);
and evaluated on the fixed 512 seeded GoToLocal episodes (success within 25 steps).
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch

from playseg_core.augment.retraining import annotated_clips
from playseg_core.data.dataset import PlayDataset
from playseg_core.data.episode import Episode
from playseg_core.domains.babyai.evaluation import evaluate_policy
from playseg_core.domains.babyai.imitation import Demonstration, PolicyTrainConfig, train_policy
from playseg_core.domains.babyai.learner import demonstration
from playseg_core.domains.babyai.play import PlayConfig, generate_episode
from playseg_core.domains.babyai.policy import PolicyConfig
from playseg_core.ps.labelling import KeepRule
from playseg_core.ps.model import load_model
from playseg_core.ps.segmentation import segment_episode

PLAY_SEED = 200_000


def demonstrations(episodes: list[Episode]) -> list[Demonstration]:
    """(instruction, states, actions) of every labelled segment of ``episodes``."""
    return [demonstration(clip) for clip in annotated_clips(episodes)]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    parser.add_argument("--data", required=True, help="dataset whose annotated train split is the base")
    parser.add_argument("--model", required=True, help="PS checkpoint from `playseg train`")
    parser.add_argument("--play-episodes", type=int, default=1500)
    parser.add_argument("--steps", type=int, default=3000)
    parser.add_argument("--batch-size", type=int, default=256)
    parser.add_argument("--channels", type=int, default=32)
    parser.add_argument("--seeds", type=int, nargs="+", default=[0])
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)

    annotated = demonstrations(list(PlayDataset.open(args.data).episodes("train")))
    started = time.perf_counter()
    play: list[Episode] = []
    seed = PLAY_SEED
    while len(play) < args.play_episodes:
        episode = generate_episode(PlayConfig(), seed)
        seed += 1
        if episode.num_steps:
            play.append(episode)
    print(
        f"{len(play)} play episodes ({sum(e.num_steps for e in play)} steps) in {time.perf_counter() - started:.0f} s"
    )

    model, extra = load_model(args.model, kinds=("ps",))
    rule = KeepRule.of_checkpoint("label", extra, args.model)
    started = time.perf_counter()
    extracted = []
    for episode in play:
        segments = [s for s in segment_episode(model, episode) if rule.keeps(s)]
        extracted.append(episode.with_segments(segments))
    truth_count = sum(len(e.segments) for e in play)
    print(
        f"PS extracted {sum(len(e.segments) for e in extracted)} segments ({rule.describe()}; "
        f"{truth_count} true) in {time.perf_counter() - started:.0f} s"
    )
    settings = {
        "annotated only": annotated,
        "+ PS-extracted play": annotated + demonstrations(extracted),
        "+ ground-truth play": annotated + demonstrations(play),
    }
    print(
        f"policy: {args.channels} channels, {args.steps} steps, batch {args.batch_size}, {args.threads} threads"
    )
    print(f"{'training data':<22}{'segments':>9}{'seed':>6}{'train_s':>9}{'success':>9}")
    for name, demos in settings.items():
        scores = []
        for train_seed in args.seeds:
            config = PolicyTrainConfig(
                steps=args.steps,
                batch_size=args.batch_size,
                seed=train_seed,
                num_threads=args.threads,
                policy=PolicyConfig(channels=args.channels),
            )
            policy, stats = train_policy(demos, config, progress=False)
            result = evaluate_policy(policy, num_episodes=512, num_threads=args.threads)
            scores.append(result.success_rate)
            print(
                f"{name:<22}{len(demos):>9}{train_seed:>6}{stats.seconds:>9.0f}{result.success_rate:>9.3f}",
                flush=True,
            )
        if len(scores) > 1:
            print(f"{name:<22} mean {np.mean(scores):.3f} +- {np.std(scores):.3f}")


if __name__ == "__main__":
    main()
