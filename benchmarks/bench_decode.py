"""Play Segmentation throughput with model inference, ours vs the reference's way, on one CPU core.

Same model, same episodes: `segment_episode` (frames encoded once, one batched pass over all windows,
O(T * L_max) decoder) against `reference_style_segment` (the whole model re-run on every prefix, then the
paper's DP with Python loops). Both must return the same segmentation; the script checks it.

    .venv/bin/python benchmarks/bench_decode.py [--model MODEL] [--data DATASET] [--episodes 20]
        [--reference-episodes 3] [--train-epochs 0]

Without --model a randomly initialised default-size PS model is used (speed does not depend on the
weights). Without --data, BabyAI play episodes are generated. --train-epochs N also times `train_ps` on
the dataset's train/val splits and reports peak RSS.

    .venv/bin/python benchmarks/bench_decode.py --make-data DIR [--split-episodes 800,200,500]

writes the dataset the figures in docs/segmentation.md were measured on: BabyAI play episodes from
consecutive seeds starting at 100000 (empty episodes skipped), split in order into train / val / test
(800 + 200 annotated episodes = ~10,000 annotated segments, the paper's 10% start split; 500 test
episodes of held-out play with ground truth).
"""

from __future__ import annotations

import argparse
import resource
import time

import torch

from playseg_core.data.episode import Episode
from playseg_core.ps.model import ModelConfig, PSModel, load_model
from playseg_core.ps.reference_style import reference_style_segment
from playseg_core.ps.segmentation import segment_episode
from playseg_core.ps.training import TrainConfig, model_config_for, train_ps


def _episodes(data: str | None, count: int) -> tuple[list[Episode], list[str], ModelConfig]:
    """Episodes to segment, their instructions and the default model configuration for their features."""
    if data:
        from playseg_core.data.dataset import PlayDataset

        dataset = PlayDataset.open(data)
        split = "test" if dataset.episode_indices("test") else dataset.splits[0]
        episodes = [dataset.episode(i) for i in dataset.episode_indices(split)[:count]]
        model_cfg = model_config_for(dataset.features, dataset.domain, len(dataset.instructions))
        return episodes, list(dataset.instructions), model_cfg
    from playseg_core.domains.babyai.play import PlayConfig, generate_episode
    from playseg_core.domains.babyai.spec import DOMAIN, INSTRUCTIONS

    episodes = []
    seed = 10_000
    while len(episodes) < count:
        episode = generate_episode(PlayConfig(), seed)
        seed += 1
        if episode.num_steps > 0:
            episodes.append(episode)
    return episodes, list(INSTRUCTIONS), model_config_for(PlayConfig().features, DOMAIN, len(INSTRUCTIONS))


def make_dataset(path: str, split_episodes: list[int], first_seed: int = 100_000) -> None:
    from playseg_core.data.dataset import DatasetWriter
    from playseg_core.domains.babyai.play import PlayConfig, generate_episode
    from playseg_core.domains.babyai.spec import DOMAIN, INSTRUCTIONS

    seed = first_seed
    meta = {"source": "bench_decode.py --make-data"}
    with DatasetWriter(path, INSTRUCTIONS, meta, features=PlayConfig().features, domain=DOMAIN) as writer:
        for split, count in zip(("train", "val", "test"), split_episodes, strict=True):
            added = 0
            while added < count:
                episode = generate_episode(PlayConfig(), seed)
                seed += 1
                if episode.num_steps > 0:
                    writer.add(episode, split)
                    added += 1
    print(f"{path}: {sum(split_episodes)} episodes (train, val, test = {split_episodes})")


def _time_segmentation(fn, model: PSModel, episodes: list[Episode]) -> tuple[float, list]:
    began = time.perf_counter()
    results = [fn(model, episode) for episode in episodes]
    return time.perf_counter() - began, results


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    parser.add_argument("--model", help="PS checkpoint (default: random default-size model)")
    parser.add_argument("--data", help="dataset directory (default: generate BabyAI play)")
    parser.add_argument("--episodes", type=int, default=20, help="episodes for our segmentation")
    parser.add_argument("--reference-episodes", type=int, default=3, help="episodes for the reference way")
    parser.add_argument("--train-epochs", type=int, default=0, help="also time training (needs --data)")
    parser.add_argument("--make-data", help="write the benchmark dataset to this directory and exit")
    parser.add_argument("--split-episodes", default="800,200,500", help="train,val,test episodes")
    args = parser.parse_args()
    if args.make_data:
        make_dataset(args.make_data, [int(n) for n in args.split_episodes.split(",")])
        return
    torch.set_num_threads(1)

    episodes, instructions, model_cfg = _episodes(args.data, max(args.episodes, args.reference_episodes))
    if args.model:
        model, _ = load_model(args.model, kinds=("ps",))
    else:
        torch.manual_seed(0)
        model = PSModel(model_cfg, instructions).eval()
    params = sum(p.numel() for p in model.parameters())
    print(f"model: {params / 1e3:.0f}k parameters, L_max {model.max_len}; 1 CPU thread")

    ours_eps = episodes[: args.episodes]
    segment_episode(model, ours_eps[0])  # warm-up
    ours_s, ours = _time_segmentation(segment_episode, model, ours_eps)
    ours_steps = sum(e.num_steps for e in ours_eps)
    ref_eps = episodes[: args.reference_episodes]
    ref_s, ref = _time_segmentation(reference_style_segment, model, ref_eps)
    ref_steps = sum(e.num_steps for e in ref_eps)
    same = all(
        [(s.start, s.end, s.instruction) for s in a] == [(s.start, s.end, s.instruction) for s in b]
        for a, b in zip(ours[: len(ref)], ref, strict=True)
    )
    ours_rate, ref_rate = ours_steps / ours_s, ref_steps / ref_s
    print(f"{'method':<28}{'episodes':>9}{'steps':>8}{'seconds':>10}{'steps/s':>10}")
    print(f"{'ours (segment_episode)':<28}{len(ours_eps):>9}{ours_steps:>8}{ours_s:>10.3f}{ours_rate:>10.1f}")
    print(f"{'reference-style':<28}{len(ref_eps):>9}{ref_steps:>8}{ref_s:>10.3f}{ref_rate:>10.2f}")
    print(f"speed-up: {ours_rate / ref_rate:.0f}x; identical segmentations: {same}")

    if args.train_epochs:
        from playseg_core.data.dataset import PlayDataset

        dataset = PlayDataset.open(args.data)
        train_eps, val_eps = list(dataset.episodes("train")), list(dataset.episodes("val"))
        cfg = TrainConfig(epochs=args.train_epochs, progress=False, log_epochs=False, num_threads=2)
        result = train_ps(train_eps, val_eps, dataset.instructions, cfg, model_cfg)
        segments = sum(len(e.segments) for e in train_eps)
        peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
        print(
            f"training: {args.train_epochs} epochs on {len(train_eps)} episodes ({segments} segments) "
            f"in {result.seconds:.0f} s with 2 threads; peak RSS {peak_mb:.0f} MB"
        )


if __name__ == "__main__":
    main()
