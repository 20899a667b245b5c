"""The paper's segmentation baselines next to PS: training time, segmentation throughput and quality.

    .venv/bin/python benchmarks/bench_baselines.py --data /tmp/babyai_small --models build/baselines \\
        --methods unloc,tridet,random,changepoint --ps-model models/ps.pt --max-minutes 9

Each method of playseg_core.baselines.registry is trained on the dataset's train/val splits (budget:
at most ``--steps METHOD=N`` optimizer steps, the method's default cap otherwise, ended earlier by early
stopping on the val loss or after ``--max-minutes``; baselines/common.py TrainOptions), saved to
MODELS/<method>.pt (an existing file is reused with ``--reuse``: no training time then), and segments
the ``--split`` episodes; ``--ps-model`` adds a trained PS checkpoint. Printed per method: training
seconds, segmentation throughput (steps/s, encoding included), the number of segments, boundary
precision (segment ends, exact), segment precision (start, end and label all right), label accuracy
over all steps and over the steps the segments cover, and boundary recall where the method covers the
trajectory. UnLoc is also scored with the paper's literal cropping ("open crop": the kept run may touch
the window's edge). A ground-truth relabelling row (the true segments labelled by the labelling model of the
random-window baseline) gives the labelling model's own accuracy. The changepoint baseline reuses that
labelling model when MODELS/random.pt exists (its training time is then PELT's penalty search only). The paper's BabyAI figures are
printed alongside (precision and label accuracy; DESIGN.md "Paper figures to beat").
"""

from __future__ import annotations

import argparse
import copy
import time
from pathlib import Path

import torch

from playseg_core.baselines.changepoint import train_changepoint
from playseg_core.baselines.common import SegmentOptions, TrainingData, TrainOptions, covered_metrics
from playseg_core.baselines.labelled_pieces import label_pieces, load_labeller
from playseg_core.baselines.random_windows import RandomWindowSegmenter
from playseg_core.baselines.registry import get_method, load_segmenter
from playseg_core.data.dataset import PlayDataset
from playseg_core.ps.metrics import evaluate

PAPER = {"ps": (0.826, 0.516), "unloc": (0.283, 0.353), "tridet": (0.338, 0.323)}
"""The paper's BabyAI table: (precision, label accuracy)."""


def _budgets(items: list[str]) -> dict[str, int]:
    budgets = {}
    for item in items:
        method, _, steps = item.partition("=")
        get_method(method)
        budgets[method] = int(steps)
    return budgets


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    parser.add_argument("--data", required=True, help="a playseg dataset with train/val and the --split")
    parser.add_argument("--models", default="build/baselines", help="where the checkpoints are written")
    parser.add_argument("--methods", default="unloc,tridet,random,changepoint")
    parser.add_argument("--ps-model", help="a trained PS checkpoint to compare with")
    parser.add_argument("--split", default="test")
    parser.add_argument(
        "--steps", action="append", default=[], metavar="METHOD=N", help="at most N optimizer steps of METHOD"
    )
    parser.add_argument("--max-minutes", type=float, help="stop each training after this long")
    parser.add_argument(
        "--patience",
        type=int,
        help="evaluations without a better val loss that end a training (default: the method's; 0: never "
        "early, the whole --steps budget, the best evaluated weights kept)",
    )
    parser.add_argument("--reuse", action="store_true", help="load MODELS/<method>.pt where it exists")
    parser.add_argument(
        "--labeller",
        help="label the changepoint pieces (and random windows) with this labelling model or PS model",
    )
    parser.add_argument(
        "--signal", default="state_action", help="changepoint signal: state_action, features, all"
    )
    parser.add_argument(
        "--encoders-from", help="unloc and tridet read this PS / labeller checkpoint's step encoders, frozen"
    )
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    budgets = _budgets(args.steps)
    dataset = PlayDataset.open(args.data)
    episodes = list(dataset.episodes(args.split, truth=True))
    truth = {e.episode_id: e.segments for e in episodes}
    steps = {e.episode_id: e.num_steps for e in episodes}
    data = TrainingData(
        train=list(dataset.episodes("train")),
        val=list(dataset.episodes("val")),
        instructions=list(dataset.instructions),
        features=dataset.features,
        domain=dataset.domain,
        encoders_from=args.encoders_from,
    )
    models = Path(args.models)
    models.mkdir(parents=True, exist_ok=True)
    runs: list[tuple[str, float | None, object]] = []
    for name in [m for m in args.methods.split(",") if m]:
        path = models / f"{name}.pt"
        seconds = None
        if not (args.reuse and path.exists()):
            options = TrainOptions(
                seed=args.seed,
                max_steps=budgets.get(name),
                max_minutes=args.max_minutes,
                patience=args.patience,
            )
            if name == "changepoint" and args.labeller:
                trained = train_changepoint(
                    data, options, signal=args.signal, labeller=load_labeller(args.labeller)
                )
            elif name == "changepoint" and (models / "random.pt").exists():
                # The same labelling model as the random windows: only PELT's penalty is chosen here.
                labeller = load_labeller(models / "random.pt")
                trained = train_changepoint(data, options, signal=args.signal, labeller=labeller)
            else:
                trained = get_method(name).train(data, options)
            trained.save(path, {"method": name, "dataset": str(Path(args.data).resolve())})
            seconds = trained.seconds
            print(f"{name}: {trained.report}", flush=True)
        if name == "random" and args.labeller and not (args.reuse and path.exists()):
            raise SystemExit("--labeller: the random windows need their lengths; train random without it")
        runs.append((name, seconds, load_segmenter(name, path, SegmentOptions(seed=args.seed))))
        if name == "random" and args.labeller:  # the same windows labelled by the given model
            other = RandomWindowSegmenter(
                load_labeller(args.labeller)[0],
                runs[-1][2].shortest,
                runs[-1][2].longest,
                SegmentOptions(seed=args.seed),
            )
            runs.append(("random, --labeller", None, other))
    if args.ps_model:
        runs.insert(0, ("ps", None, load_segmenter("ps", args.ps_model)))

    total_steps = sum(steps.values())
    print(f"\n{len(episodes)} episodes ({total_steps} steps) of {args.data} split {args.split}")
    header = (
        f"{'method':<22}{'train s':>8}{'steps/s':>9}{'segs':>6}{'end P':>7}{'seg P':>7}{'label':>7}"
        f"{'covered':>8}{'end R':>7}   paper P / label"
    )
    print(header)
    relabel_model = None
    unloc = next((segmenter for name, _, segmenter in runs if name == "unloc"), None)
    if unloc is not None:  # the paper's literal cropping too: a run may touch the window's edge
        open_crop = copy.deepcopy(unloc)
        open_crop.model.cfg.closed_crop = False
        runs.append(("unloc", None, open_crop))
    for name, seconds, segmenter in runs:
        if name == "unloc" and not segmenter.model.cfg.closed_crop:
            name = "unloc (open crop)"
        began = time.perf_counter()
        pred = {e.episode_id: segmenter.segment(e) for e in episodes}
        rate = total_steps / (time.perf_counter() - began)
        m = evaluate(pred, truth, steps) | covered_metrics(pred, truth, steps)
        recall = f"{m['boundary_recall_tol0']:>7.3f}" if segmenter.tiles else f"{'-':>7}"
        paper = "{:.3f} / {:.3f}".format(*PAPER[name.split()[0]]) if name.split()[0] in PAPER else ""
        trained = f"{seconds:>8.0f}" if seconds is not None else f"{'-':>8}"
        print(
            f"{name:<22}{trained}{rate:>9.0f}{m['pred_segments']:>6}{m['boundary_precision_tol0']:>7.3f}"
            f"{m['segment_precision']:>7.3f}{m['label_accuracy']:>7.3f}{m['covered_label_accuracy']:>8.3f}"
            f"{recall}   {paper}",
            flush=True,
        )
        if name == "random":
            relabel_model = segmenter.model
    if relabel_model is not None:
        pred = {
            e.episode_id: label_pieces(relabel_model, e, [(s.start, s.end) for s in e.segments])
            for e in episodes
        }
        m = evaluate(pred, truth, steps)
        print(
            f"{'ground truth relabelled':<22}{'-':>8}{'-':>9}{m['pred_segments']:>6}{1.0:>7.3f}"
            f"{m['segment_precision']:>7.3f}{m['label_accuracy']:>7.3f}{m['label_accuracy']:>8.3f}{1.0:>7.3f}"
        )


if __name__ == "__main__":
    main()
