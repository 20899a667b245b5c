"""Annotation effort: how many segments a human touches to label a pool of play, with `playseg review`'s
loop against annotating from scratch.

A simulated reviewer uses the ground truth as the oracle. Every strategy starts from the same seed (the
first ``--seed-segments`` true segments of the pool, annotated in play order) and then, each round, spends
``--k`` actions, after which PS is trained again (`playseg train --max-steps`) on the human labels and
proposes segments for the rest of the pool:

- ``scratch``: the next k true segments in play order are annotated (one action each);
- ``review-lowest``: the k open proposals of lowest label confidence (the page's queue order) are looked
  at: one that is exactly a true segment with its instruction is accepted (one action); any other is
  replaced by the true segments it overlaps (one action per segment written);
- ``review-random``: the same for k open proposals drawn at random.

After each round the pool's labelling (the human labels, and the model's proposals where no human label
lies) is scored against the truth: per-step label accuracy over every step of the pool (an unlabelled step
is wrong) and exact boundary F1 (playseg_core/ps/metrics.py). Annotating the whole pool from scratch takes
one action per true segment; the target is 0.90 label accuracy with at most a third of those.

    .venv/bin/python benchmarks/bench_annotation_effort.py --domain babyai --preset tiny --rounds 4 --k 25
"""

from __future__ import annotations

import argparse
import random
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from playseg_core.data.dataset import DatasetWriter, PlayDataset
from playseg_core.data.episode import Segment
from playseg_core.data.splits import annotated_splits
from playseg_core.ps.metrics import evaluate


@dataclass
class Pool:
    """The play to label: each episode's true segments, and what the strategy has so far."""

    dataset: PlayDataset
    indices: list[int]
    truth: dict[int, list[Segment]]
    human: dict[int, list[Segment]] = field(default_factory=dict)
    proposals: dict[int, list[Segment]] = field(default_factory=dict)
    actions: int = 0

    def true_in_order(self) -> list[tuple[int, Segment]]:
        return [(i, s) for i in self.indices for s in self.truth[i]]

    def add_human(self, index: int, segment: Segment) -> None:
        labels = self.human.setdefault(index, [])
        if segment not in labels:
            labels.append(segment)
            labels.sort()

    def labelling(self, index: int) -> list[Segment]:
        human = self.human.get(index, [])
        free = [p for p in self.proposals.get(index, []) if not any(overlaps(p, h) for h in human)]
        return sorted(human + free)

    def open_proposals(self) -> list[tuple[int, Segment]]:
        return [(i, p) for i in self.indices for p in self.labelling(i) if p not in self.human.get(i, [])]


def overlaps(a: Segment, b: Segment) -> bool:
    return a.start < b.end and b.start < a.end


def step_labels(segments: list[Segment], num_steps: int) -> np.ndarray:
    labels = np.full(num_steps, "", dtype=object)
    for s in segments:
        labels[s.start : s.end] = s.instruction
    return labels


def score(pool: Pool) -> dict[str, float]:
    correct = total = 0
    pred, truth, steps = {}, {}, {}
    for i in pool.indices:
        n = pool.dataset.records[i].num_steps
        mine, real = step_labels(pool.labelling(i), n), step_labels(pool.truth[i], n)
        covered = real != ""
        correct += int(np.sum((mine == real) & covered))
        total += int(np.sum(covered))
        key = pool.dataset.records[i].episode_id
        pred[key], truth[key], steps[key] = pool.labelling(i), pool.truth[i], n
    metrics = evaluate(pred, truth, steps, (0,))
    return {"label_accuracy": correct / max(total, 1), "boundary_f1": float(metrics["boundary_f1_tol0"])}


def retrain_and_propose(pool: Pool, work: Path, max_steps: int, round_index: int) -> float:
    """Train PS on the human labels (`playseg train`), propose for the pool; returns the seconds taken."""
    from playseg_core.baselines.common import SegmentOptions
    from playseg_core.baselines.registry import load_segmenter

    started = time.perf_counter()
    source = pool.dataset
    data, model = work / f"labels-{round_index}", work / f"ps-{round_index}.pt"
    labelled = [i for i in pool.indices if pool.human.get(i)]
    splits = annotated_splits([source.records[i].episode_id for i in labelled])
    with DatasetWriter(data, source.instructions, features=source.features, domain=source.domain) as writer:
        for i in labelled:
            episode = source.episode(i).with_segments(pool.human[i])
            writer.add(episode, splits[episode.episode_id])
    command = [sys.executable, "-m", "playseg_ros.cli", "train", "--data", str(data), "--out", str(model),
               "--max-steps", str(max_steps), "--overwrite"]  # fmt: skip
    subprocess.run(command, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    segmenter = load_segmenter("ps", model, SegmentOptions())
    for i in pool.indices:
        pool.proposals[i] = [s for s in segmenter.segment(source.episode(i)) if s.instruction]
    return time.perf_counter() - started


def review_round(pool: Pool, k: int, order: str, rng: random.Random) -> None:
    """The oracle looks at k open proposals (lowest confidence first, or random) and fixes each."""
    candidates = pool.open_proposals()
    if order == "lowest":
        candidates.sort(key=lambda item: item[1].confidence)
    else:
        rng.shuffle(candidates)
    spent = 0
    for index, proposal in candidates:
        if spent >= k:
            break
        truth = pool.truth[index]
        exact = [
            t
            for t in truth
            if (t.start, t.end, t.instruction) == (proposal.start, proposal.end, proposal.instruction)
        ]
        if exact:
            pool.add_human(index, exact[0])
            spent += 1
            continue
        written = [t for t in truth if overlaps(t, proposal) and t not in pool.human.get(index, [])]
        for t in written:
            pool.add_human(index, t)
        spent += max(1, len(written))  # a proposal over no true segment is deleted: one action
    pool.actions += spent


def scratch_round(pool: Pool, k: int) -> None:
    done = 0
    for index, segment in pool.true_in_order():
        if done == k:
            break
        if segment not in pool.human.get(index, []):
            pool.add_human(index, segment)
            done += 1
    pool.actions += done


def run(args: argparse.Namespace, strategy: str, dataset: PlayDataset, work: Path) -> list[dict[str, float]]:
    indices = dataset.episode_indices(args.split)[: args.episodes]
    pool = Pool(dataset, indices, {i: dataset.segments(i, truth=True) for i in indices})
    scratch_round(pool, args.seed_segments)
    rng = random.Random(0)
    rows = []
    for round_index in range(args.rounds + 1):
        seconds = retrain_and_propose(pool, work / strategy, args.max_steps, round_index)
        rows.append({"round": round_index, "actions": pool.actions, **score(pool), "seconds": seconds})
        print(
            f"{strategy:<14} round {round_index}: {pool.actions:4d} actions ({pool.actions / total_segments(pool):.2f} "
            f"of from-scratch), label accuracy {rows[-1]['label_accuracy']:.3f}, boundary F1 "
            f"{rows[-1]['boundary_f1']:.3f}  ({seconds:.0f} s)",
            flush=True,
        )
        if round_index == args.rounds:
            break
        if strategy == "scratch":
            scratch_round(pool, args.k)
        else:
            review_round(pool, args.k, strategy.removeprefix("review-"), rng)
    return rows


def total_segments(pool: Pool) -> int:
    return sum(len(t) for t in pool.truth.values())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--domain", default="babyai", help="babyai or tabletop (generated with --preset)")
    parser.add_argument("--preset", default="tiny")
    parser.add_argument("--data", help="an existing dataset instead of generating one")
    parser.add_argument("--split", default="play", help="the split whose episodes form the pool")
    parser.add_argument("--episodes", type=int, default=20, help="episodes in the pool")
    parser.add_argument("--seed-segments", type=int, default=20)
    parser.add_argument("--k", type=int, default=20, help="actions per round")
    parser.add_argument("--rounds", type=int, default=4)
    parser.add_argument("--max-steps", type=int, default=400, help="optimiser steps of each retraining")
    parser.add_argument("--strategies", default="scratch,review-lowest,review-random")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory(prefix="annotation-effort-") as tmp:
        work = Path(tmp)
        data = Path(args.data) if args.data else work / "data"
        if not args.data:
            subprocess.run([sys.executable, "-m", "playseg_ros.cli", "generate", "--domain", args.domain, "--preset",
                            args.preset, "--out", str(data), "--quiet"], check=True, stdout=subprocess.DEVNULL)  # fmt: skip
        dataset = PlayDataset.open(data)
        indices = dataset.episode_indices(args.split)[: args.episodes]
        total = sum(len(dataset.segments(i, truth=True)) for i in indices)
        name = f"{args.domain} {data.name if args.data else args.preset}"
        print(f"{name}: pool of {len(indices)} {args.split} episodes, {total} true segments "
              f"(from scratch: {total} actions; 0.90 without a model: {int(np.ceil(0.9 * total))})")  # fmt: skip
        for strategy in args.strategies.split(","):
            run(args, strategy, dataset, work)


if __name__ == "__main__":
    main()
