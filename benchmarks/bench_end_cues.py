"""Where do a dataset's segment ends show? A per-step probe of the actions and state around each step.

For every step t of the annotated episodes, an MLP on the state s_t, the `--past` actions before t and
the first `--future` actions from t on (a_t is the first command after an end at t) predicts whether a
segment ends at t; trained on the train split, scored on the val split by per-step average precision and
the best F1 over thresholds. What it answers: how much the commands after a candidate end tell, the
question behind PS's `end_lookahead` (docs/segmentation.md "Reading past the end").

    .venv/bin/python benchmarks/bench_end_cues.py --data /tmp/tt-medium/data --future 0 1 2 4
"""

from __future__ import annotations

import argparse

import numpy as np
import torch
import torch.nn.functional as F

from playseg_core.data.dataset import PlayDataset


def step_rows(dataset: PlayDataset, split: str, past: int, future: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(rows, is_end) over steps 1..T-1 of the split's annotated episodes."""
    rows, ends = [], []
    for episode in dataset.episodes(split):
        if not episode.segments:
            continue
        actions = np.asarray(episode.actions, np.float32).reshape(episode.num_steps, -1)
        recorded = episode.state if episode.state is not None else np.zeros((episode.num_steps + 1, 0))
        state = np.asarray(recorded, np.float32).reshape(episode.num_steps + 1, -1)
        padded = np.zeros((episode.num_steps + past + future, actions.shape[1]), np.float32)
        padded[past : past + episode.num_steps] = actions
        end_steps = {segment.end for segment in episode.segments}
        for t in range(1, episode.num_steps):
            around = padded[t : t + past + future].reshape(-1)  # a_{t-past} .. a_{t+future-1}
            rows.append(np.concatenate([around, state[t]]))
            ends.append(t in end_steps)
    return torch.from_numpy(np.array(rows)), torch.tensor(ends, dtype=torch.float32)


def end_probe(
    dataset: PlayDataset, past: int, future: int, steps: int, seed: int
) -> tuple[float, float, int]:
    """(val average precision, val best F1, val ends) of the probe."""
    train_x, train_y = step_rows(dataset, "train", past, future)
    val_x, val_y = step_rows(dataset, "val", past, future)
    mean, std = train_x.mean(0), train_x.std(0) + 1e-6
    train_x, val_x = (train_x - mean) / std, (val_x - mean) / std
    torch.manual_seed(seed)
    net = torch.nn.Sequential(
        torch.nn.Linear(train_x.shape[1], 128), torch.nn.GELU(), torch.nn.Linear(128, 128), torch.nn.GELU(),
        torch.nn.Linear(128, 1),
    )  # fmt: skip
    optimizer = torch.optim.Adam(net.parameters(), 1e-3)
    positive_weight = torch.tensor(4.0)  # ends are rare
    for _ in range(steps):
        batch = torch.randint(len(train_x), (512,))
        logits = net(train_x[batch]).squeeze(-1)
        loss = F.binary_cross_entropy_with_logits(logits, train_y[batch], pos_weight=positive_weight)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    with torch.no_grad():
        ranked = val_y[torch.argsort(net(val_x).squeeze(-1), descending=True)]
    hits = torch.cumsum(ranked, 0)
    precision = hits / torch.arange(1, len(ranked) + 1)
    recall = hits / ranked.sum()
    best_f1 = float((2 * precision * recall / (precision + recall + 1e-9)).max())
    average_precision = float((precision * ranked).sum() / ranked.sum())
    return average_precision, best_f1, int(val_y.sum())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--data", required=True, help="a dataset with annotated train and val splits")
    parser.add_argument("--past", type=int, default=4, help="actions before the step the probe reads")
    parser.add_argument(
        "--future", type=int, nargs="+", default=[0, 1, 2, 4], help="actions from the step on"
    )
    parser.add_argument("--steps", type=int, default=3000, help="optimizer steps of 512 rows")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    dataset = PlayDataset.open(args.data)
    torch.set_num_threads(2)
    for future in args.future:
        average_precision, best_f1, ends = end_probe(dataset, args.past, future, args.steps, args.seed)
        print(
            f"past {args.past} actions, next {future}: val per-step AP {average_precision:.3f}, "
            f"best F1 {best_f1:.3f} ({ends} ends)",
            flush=True,
        )


if __name__ == "__main__":
    main()
