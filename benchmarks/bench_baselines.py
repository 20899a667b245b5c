"""The paper's simple baselines, scored like PS: random windows and ground-truth relabelling.

    .venv/bin/python benchmarks/bench_baselines.py --data data/ps10k --labeller models/labeller.pt

Both use the stand-alone labelling model (`playseg train --labeller`):
- random windows: each episode cut into consecutive windows of 2..22 steps (uniform), each labelled by
  the labeller (the paper's "Random" baseline);
- ground-truth relabelling: the true segments, labelled by the labeller (its boundaries are perfect by
  construction; its label accuracy is the labeller's accuracy on held-out play).
UnLoc and TriDet need CLIP / I3D features and are not reproduced here.
"""

from __future__ import annotations

import argparse

import numpy as np
import torch

from playseg_core.data.dataset import PlayDataset
from playseg_core.ps.labelling import label_segments
from playseg_core.ps.metrics import evaluate
from playseg_core.ps.model import LabelModel, load_model


def random_windows(
    num_steps: int, rng: np.random.Generator, shortest: int = 2, longest: int = 22
) -> list[tuple[int, int]]:
    """Consecutive windows of random length covering [0, num_steps); the last one may be shorter."""
    spans, start = [], 0
    while start < num_steps:
        end = min(num_steps, start + int(rng.integers(shortest, longest + 1)))
        spans.append((start, end))
        start = end
    return spans


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    parser.add_argument("--data", required=True)
    parser.add_argument("--labeller", required=True, help="labelling-model checkpoint")
    parser.add_argument("--split", default="test")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    torch.set_num_threads(2)
    model, _ = load_model(args.labeller)
    if not isinstance(model, LabelModel):
        raise SystemExit(f"{args.labeller}: not a labelling-model checkpoint")
    episodes = list(PlayDataset.open(args.data).episodes(args.split, truth=True))
    truth = {e.episode_id: e.segments for e in episodes}
    steps = {e.episode_id: e.num_steps for e in episodes}
    rng = np.random.default_rng(args.seed)
    runs = {
        "random windows 2..22": {
            e.episode_id: label_segments(model, e, random_windows(e.num_steps, rng)) for e in episodes
        },
        "ground truth relabelled": {
            e.episode_id: label_segments(model, e, [(s.start, s.end) for s in e.segments]) for e in episodes
        },
    }
    print(f"{len(episodes)} episodes of {args.data} split {args.split}; exact boundaries, final included")
    print(f"{'baseline':<26}{'precision':>10}{'recall':>8}{'F1':>7}{'label acc':>11}")
    for name, pred in runs.items():
        m = evaluate(pred, truth, steps)
        print(
            f"{name:<26}{m['boundary_precision_tol0']:>10.3f}{m['boundary_recall_tol0']:>8.3f}"
            f"{m['boundary_f1_tol0']:>7.3f}{m['label_accuracy']:>11.3f}"
        )


if __name__ == "__main__":
    main()
