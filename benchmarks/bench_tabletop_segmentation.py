"""PS on tabletop play: the issue's figures and where the errors are.

Reads a segmented dataset (`playseg segment` output) and the dataset it came from, and prints boundary
precision / recall / F1 exact, at +-2 and +-5 steps, the per-step label accuracy over covered steps (as
`playseg evaluate`), then the errors: unmatched predicted ends at the end of an unlabelled stretch (idle
or a failed task: the truth has no boundary there, a tiling segmenter must have one) or elsewhere,
missed true ends, the figures when a stretch's end counts as a boundary, per family of the true task how
many of its ends are found, how many of its spans are cut exactly and how many of those labelled right,
and the label accuracy per instruction family with the most frequent confusions.

    .venv/bin/python benchmarks/bench_tabletop_segmentation.py --pred /tmp/ttps/seg --truth /tmp/ttps/data
"""

from __future__ import annotations

import argparse
from collections import Counter

from playseg_core.data.dataset import PlayDataset
from playseg_core.data.episode import Segment
from playseg_core.domains.tabletop.instructions import task_for
from playseg_core.ps.metrics import evaluate, match_boundaries

TOLERANCES = (0, 2, 5)


def stretch_ends(truth: list[Segment]) -> set[int]:
    """Steps where an unlabelled stretch ends: a true segment starting where the previous one did not end
    (or after step 0)."""
    ends, previous_end = set(), 0
    for segment in sorted(truth, key=lambda s: s.start):
        if segment.start != previous_end:
            ends.add(segment.start)
        previous_end = segment.end
    return ends


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--pred", required=True, help="output of playseg segment")
    parser.add_argument("--truth", required=True, help="the tabletop dataset that was segmented")
    parser.add_argument("--tolerance", type=int, default=2, help="tolerance of the error analysis (steps)")
    args = parser.parse_args()
    predicted, reference = PlayDataset.open(args.pred), PlayDataset.open(args.truth)
    pred = {r.episode_id: predicted.segments(i, truth=True) for i, r in enumerate(predicted.records)}
    truth, steps = {}, {}
    for index, record in enumerate(reference.records):
        if record.episode_id in pred:
            truth[record.episode_id] = reference.segments(index, truth=True)
            steps[record.episode_id] = record.num_steps
    results = evaluate(pred, truth, steps, TOLERANCES)
    print(
        f"{results['episodes']} episodes, {sum(steps.values())} steps, {results['true_segments']} true "
        f"segments, {results['pred_segments']} predicted"
    )
    for tol in TOLERANCES:
        name = "exact" if tol == 0 else f"+-{tol} steps"
        print(
            f"  boundary {name:<12} P {results[f'boundary_precision_tol{tol}']:.3f}  "
            f"R {results[f'boundary_recall_tol{tol}']:.3f}  F1 {results[f'boundary_f1_tol{tol}']:.3f}"
        )
    print(f"  label accuracy {results['label_accuracy']:.3f} over {results['label_steps']} covered steps")

    tol = args.tolerance
    at_stretch, elsewhere, missed, matched_with_stretches, stretch_count = 0, 0, 0, 0, 0
    pred_total, true_total = 0, 0
    confusions: Counter[tuple[str, str]] = Counter()
    family_steps: Counter[str] = Counter()
    family_correct: Counter[str] = Counter()
    family_tasks: Counter[str] = Counter()
    family_ends_found: Counter[str] = Counter()
    family_exact: Counter[str] = Counter()
    family_exact_right: Counter[str] = Counter()
    for episode_id, true_segments in truth.items():
        pred_ends = [s.end for s in pred[episode_id]]
        true_ends = [s.end for s in true_segments]
        stretches = stretch_ends(true_segments)
        stretch_count += len(stretches)
        pred_total, true_total = pred_total + len(pred_ends), true_total + len(true_ends)
        for end in pred_ends:
            if not any(abs(end - t) <= tol for t in true_ends):
                if any(abs(end - s) <= tol for s in stretches):
                    at_stretch += 1
                else:
                    elsewhere += 1
        missed += sum(not any(abs(t - end) <= tol for end in pred_ends) for t in true_ends)
        matched_with_stretches += match_boundaries(pred_ends, sorted({*true_ends, *stretches}), tol)
        labels: list[str | None] = [None] * steps[episode_id]
        for segment in pred[episode_id]:
            labels[segment.start : segment.end] = [segment.instruction] * segment.length
        cut = {(s.start, s.end): s.instruction for s in pred[episode_id]}
        for segment in true_segments:
            family = task_for(segment.instruction).family
            family_tasks[family] += 1
            family_ends_found[family] += any(abs(segment.end - end) <= tol for end in pred_ends)
            exact = cut.get((segment.start, segment.end))
            family_exact[family] += exact is not None
            family_exact_right[family] += exact == segment.instruction
            for step in range(segment.start, segment.end):
                family_steps[family] += 1
                if labels[step] == segment.instruction:
                    family_correct[family] += 1
                else:
                    other = "(none)" if labels[step] is None else task_for(labels[step]).family
                    confusions[(family, other)] += 1
    print(f"errors at +-{tol} steps:")
    print(
        f"  unmatched predicted ends: {at_stretch + elsewhere} of {pred_total}: {at_stretch} at the end of an "
        f"unlabelled stretch ({stretch_count} stretches), {elsewhere} elsewhere"
    )
    print(f"  missed true ends: {missed} of {true_total}")
    truth_with_stretches = true_total + stretch_count
    precision = matched_with_stretches / pred_total if pred_total else 0.0
    recall = matched_with_stretches / truth_with_stretches if truth_with_stretches else 0.0
    f1 = 2 * precision * recall / (precision + recall) if precision + recall else 0.0
    print(f"  if a stretch's end were a boundary: P {precision:.3f}  R {recall:.3f}  F1 {f1:.3f}")
    print(f"by the true task's family: its end found (+-{tol} steps), its span cut exactly, labelled right:")
    for family in sorted(family_tasks):
        tasks = family_tasks[family]
        print(
            f"  {family:<22} {tasks:5d} tasks  ends found {family_ends_found[family] / tasks:.3f}  exact spans "
            f"{family_exact[family] / tasks:.3f}  of those labelled right {family_exact_right[family]}/{family_exact[family]}"
        )
    print("label accuracy by family (covered steps):")
    for family in sorted(family_steps):
        print(
            f"  {family:<22} {family_correct[family] / family_steps[family]:.3f} of {family_steps[family]} steps"
        )
    print("wrong steps, true family -> predicted family (same family: a wrong block, region or direction):")
    for (true_family, other), count in confusions.most_common(8):
        if count:
            print(f"  {true_family} -> {other}: {count}")


if __name__ == "__main__":
    main()
