"""Training time per optimizer step of each trainable segmentation method, and the time of a full budget
(the code's default and the paper's) as steps x seconds per step.

    .venv/bin/python benchmarks/bench_baseline_training.py --data /tmp/bl_babyai_small --threads 1

Each configuration trains through the registry (playseg_core.baselines.registry: the same code as
`playseg train --method`) on the dataset's train split and is stopped after ``--measure`` optimizer
steps. A global optimizer step hook records when each step ends; seconds per step is the median (and
the mean) of the intervals between consecutive steps after the first ``--warmup`` (batch assembly,
encoding, forward, backward and the optimizer step: the per-step cost of the training loop, without
the set-up, the val passes and the calibration). The budgets' times are extrapolations from those few
steps, not measured runs.

Time per step depends on the batch and the segment lengths, not on the number of annotated segments;
the only thing the dataset's size changes is the default PS / labelling-model step cap (TrainConfig:
``cap_epochs`` passes of ``segments_per_batch``, at least ``min_steps``, at most ``cap_steps``; early
stopping usually ends a run sooner, so the budgets are upper bounds), computed here for
``--annotated-segments`` (10,000: the paper's BabyAI corpus) rather than for the dataset given.
"""

from __future__ import annotations

import argparse
import statistics
import time
from dataclasses import dataclass

import torch
from torch.optim.optimizer import register_optimizer_step_post_hook

from playseg_core.baselines.common import WINDOW_STEP_CAP, TrainingData, TrainOptions
from playseg_core.baselines.labelled_pieces import train_labelling_model
from playseg_core.baselines.registry import get_method
from playseg_core.data.dataset import PlayDataset
from playseg_core.ps.training import TrainConfig, step_cap


@dataclass(frozen=True)
class Config:
    label: str
    method: str  # a registry method, or "labeller" (the labelling model of random / changepoint)
    batch: int
    budget: int  # optimizer steps of the budget the row extrapolates to
    budget_source: str


class _Enough(Exception):
    """Raised by the step hook once enough steps are timed."""


def default_ps_steps(annotated_segments: int) -> int:
    """The step cap of `playseg train` (TrainConfig defaults) on that many annotated segments."""
    cfg = TrainConfig()
    return step_cap(cfg, -(-annotated_segments // cfg.segments_per_batch))


def configurations(annotated_segments: int) -> list[Config]:
    ps_steps = default_ps_steps(annotated_segments)
    ps_source = f"default: TrainConfig on {annotated_segments:,} annotated segments"
    return [
        Config("PS", "ps", 16, ps_steps, ps_source),
        Config("labelling model (random, changepoint)", "labeller", 16, ps_steps, ps_source),
        Config(
            "UnLoc, default", "unloc", 32, WINDOW_STEP_CAP, f"default cap: {WINDOW_STEP_CAP:,} steps of 32"
        ),
        Config("UnLoc, paper batch", "unloc", 128, 20_000, "paper: 20,000 updates of 128"),
        Config(
            "TriDet, default", "tridet", 32, WINDOW_STEP_CAP, f"default cap: {WINDOW_STEP_CAP:,} steps of 32"
        ),
        Config("TriDet, paper batch", "tridet", 512, 2000, "paper: 2,000 updates of 512"),
    ]


def time_steps(config: Config, data: TrainingData, measure: int, warmup: int, threads: int) -> list[float]:
    """Seconds between consecutive optimizer steps, after ``warmup`` steps, ``measure`` of them."""
    ends: list[float] = []

    def hook(optimizer, args, kwargs) -> None:  # noqa: ARG001
        ends.append(time.perf_counter())
        if len(ends) > warmup + measure:
            raise _Enough

    handle = register_optimizer_step_post_hook(hook)
    options = TrainOptions(
        seed=0,
        max_steps=10 * (warmup + measure + 1),
        patience=0,
        batch_size=config.batch,
        num_threads=threads,
    )
    try:
        if config.method == "labeller":
            train_labelling_model(data, options)
        else:
            get_method(config.method).train(data, options)
    except _Enough:
        pass
    finally:
        handle.remove()
    if len(ends) <= warmup + measure:
        raise RuntimeError(f"{config.label}: training ended after {len(ends)} steps")
    return [b - a for a, b in zip(ends[warmup:], ends[warmup + 1 :], strict=False)]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    parser.add_argument("--data", required=True, help="a playseg dataset with annotated train episodes")
    parser.add_argument("--measure", type=int, default=10, help="optimizer steps timed per configuration")
    parser.add_argument("--warmup", type=int, default=2, help="steps before the timed ones")
    parser.add_argument("--threads", type=int, default=1, help="torch threads")
    parser.add_argument(
        "--annotated-segments", type=int, default=10_000, help="corpus size for the PS default budget"
    )
    parser.add_argument(
        "--only",
        default="",
        help="methods to time, comma-separated: ps, labeller, unloc, tridet (default: all)",
    )
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    dataset = PlayDataset.open(args.data)
    data = TrainingData(
        train=list(dataset.episodes("train")),
        val=list(dataset.episodes("val")),
        instructions=list(dataset.instructions),
        features=dataset.features,
        domain=dataset.domain,
    )
    wanted = {m for m in args.only.split(",") if m}
    print(
        f"{args.data} ({dataset.domain}, {len(dataset.instructions)} instructions), {args.threads} torch "
        f"thread(s), {args.measure} timed steps after {args.warmup}"
    )
    print(
        f"{'configuration':<40}{'batch':>6}{'s/step':>8}{'mean':>8}{'budget steps':>14}{'budget min':>12}  budget"
    )
    for config in configurations(args.annotated_segments):
        if wanted and config.method not in wanted:
            continue
        intervals = time_steps(config, data, args.measure, args.warmup, args.threads)
        median, mean = statistics.median(intervals), statistics.fmean(intervals)
        minutes = config.budget * median / 60
        print(
            f"{config.label:<40}{config.batch:>6}{median:>8.3f}{mean:>8.3f}{config.budget:>14,}{minutes:>12.1f}"
            f"  {config.budget_source} (extrapolated)",
            flush=True,
        )


if __name__ == "__main__":
    main()
