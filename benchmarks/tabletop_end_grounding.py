"""PS on the tabletop with and without its end grounded on the label, trained as an experiment scale trains it.

Trains PS on a generated dataset's train split (the experiment's start split) with the scale's budget,
symmetries and label-accuracy target (the domain's `EXPERIMENT`, `--scale`), the end head's grounding
set to each of ``--grounding`` (attention heads; 0: none), and writes ``OUT/ps-grounding<N>.pt``. Score
each on the val split with `playseg segment` and `benchmarks/bench_tabletop_segmentation.py`:

    .venv/bin/playseg generate --domain tabletop --preset paper --out /tmp/ttps/data --workers 2 --quiet
    .venv/bin/python benchmarks/tabletop_end_grounding.py --data /tmp/ttps/data --out /tmp/ground --grounding 0,2
    .venv/bin/playseg segment --model /tmp/ground/ps-grounding2.pt --input /tmp/ttps/data --splits val \\
        --out /tmp/ground/val2 --keep all
    .venv/bin/python benchmarks/bench_tabletop_segmentation.py --pred /tmp/ground/val2 --truth /tmp/ttps/data
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from playseg_core.domains import load_domain
from playseg_core.experiment.runner import ExperimentData, train_on_start_split


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--data", required=True, help="a generated tabletop dataset (train: the start split)")
    parser.add_argument("--out", required=True, help="directory for the checkpoints")
    parser.add_argument("--grounding", default="0,2", help="end grounding heads to train, comma-separated")
    parser.add_argument("--scale", default="medium", help="the experiment scale whose budget PS trains with")
    parser.add_argument("--threads", type=int, default=2, help="torch threads")
    args = parser.parse_args()
    try:
        data = ExperimentData.open(Path(args.data))
        domain = load_domain(data.domain or "")
        scale = domain.EXPERIMENT.scale(args.scale)
        heads = [int(n) for n in args.grounding.split(",")]
    except (OSError, ValueError, AttributeError) as error:
        raise SystemExit(f"{args.data}: {error}") from None
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    default = getattr(domain, "END_GROUNDING", 0)
    for grounding in heads:
        domain.END_GROUNDING = grounding  # what PS's model_config_for reads as the domain's choice
        began = time.perf_counter()
        trained = train_on_start_split(data, "ps", scale, args.threads)
        path = out / f"ps-grounding{grounding}.pt"
        trained.save(path, {})
        print(
            f"grounding {grounding}: {trained.report} ({time.perf_counter() - began:.0f} s) -> {path}",
            flush=True,
        )
    domain.END_GROUNDING = default


if __name__ == "__main__":
    main()
