"""Policy success rate vs number of demonstration segments, with training and evaluation time.

Demonstrations are BabyAIBot solutions of seeded GoToLocal (S8N7) episodes (seeds from 1,000,000 up, so
they never coincide with evaluation episodes 0..N-1). For every size and training seed: train, then
evaluate on the fixed 512 episodes; prints success mean +- std over the seeds.

    .venv/bin/python benchmarks/bench_policy.py --sizes 1000 5000 10000 --seeds 0 1 2
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from playseg_core.domains.babyai.evaluation import RandomPolicy, bot_demonstrations, evaluate_policy
from playseg_core.domains.babyai.imitation import PolicyTrainConfig, train_policy
from playseg_core.domains.babyai.policy import PolicyConfig

DEMONSTRATION_SEED = 1_000_000


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--sizes", type=int, nargs="+", default=[1000, 5000, 10000])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--steps", type=int, default=2000)
    parser.add_argument("--batch-size", type=int, default=256)
    parser.add_argument("--learning-rate", type=float, default=2e-3, help="peak (warm-up, cosine decay)")
    parser.add_argument("--channels", type=int, default=64)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--eval-episodes", type=int, default=512)
    parser.add_argument("--no-egocentric", action="store_true", help="the reference's allocentric input")
    parser.add_argument("--no-mirror", action="store_true", help="train without mirror augmentation")
    args = parser.parse_args()

    started = time.perf_counter()
    demonstrations = bot_demonstrations(max(args.sizes), seed=DEMONSTRATION_SEED)
    print(f"{len(demonstrations)} bot demonstrations in {time.perf_counter() - started:.1f} s")

    random_result = evaluate_policy(RandomPolicy(0), num_episodes=args.eval_episodes)
    print(f"random policy (left/right/forward): success {random_result.success_rate:.3f}")

    policy_config = PolicyConfig(channels=args.channels, egocentric=not args.no_egocentric)
    print(
        f"config: {policy_config}\nsteps {args.steps} batch {args.batch_size} lr {args.learning_rate} "
        f"threads {args.threads} mirror {not args.no_mirror}"
    )
    print("segments  seed  train_s  final_loss  train_acc  success  eval_s")
    for size in args.sizes:
        scores = []
        for seed in args.seeds:
            config = PolicyTrainConfig(
                steps=args.steps,
                batch_size=args.batch_size,
                learning_rate=args.learning_rate,
                seed=seed,
                num_threads=args.threads,
                mirror_augmentation=not args.no_mirror,
                policy=policy_config,
            )
            model, stats = train_policy(demonstrations[:size], config, progress=False)
            result = evaluate_policy(model, num_episodes=args.eval_episodes, num_threads=args.threads)
            scores.append(result.success_rate)
            print(
                f"{size:8d}  {seed:4d}  {stats.seconds:7.1f}  {stats.final_loss:10.3f}  "
                f"{stats.final_accuracy:9.3f}  {result.success_rate:7.3f}  {result.seconds:6.1f}",
                flush=True,
            )
        print(f"{size:8d}  success {np.mean(scores):.3f} +- {np.std(scores):.3f} over {len(scores)} seeds")


if __name__ == "__main__":
    main()
