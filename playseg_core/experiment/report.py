"""The experiment's report: a Markdown table of policy success per condition (mean +- std over seeds) next
to the paper's figures, the share of the gap between the start split and all the data each condition
recovers, and plots: success per condition, the ground-truth curve, segment lengths and labels of what
each condition adds, and the per-instruction gain against the number of segments added for it."""

from __future__ import annotations

from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np

from playseg_core.experiment.conditions import AddedSegments, pool_percent
from playseg_core.experiment.spec import ExperimentData, ExperimentSpec


def summarize(rows: list[dict[str, Any]]) -> dict[str, dict[str, Any]]:
    """condition -> mean and std of success over its seeds (population std, as the paper's +-), seeds,
    segments trained on."""
    by_condition: dict[str, list[dict[str, Any]]] = {}
    for row in rows:
        by_condition.setdefault(row["condition"], []).append(row)
    summary = {}
    for condition, runs in by_condition.items():
        success = [r["success"] for r in runs if r["success"] is not None]
        summary[condition] = {
            "mean": float(np.mean(success)) if success else float("nan"),
            "std": float(np.std(success)) if success else float("nan"),
            "seeds": len(success),  # runs with a success figure
            "segments": runs[0]["segments"],
            "added": runs[0]["added_segments"],
            "seconds": float(np.mean([r["seconds"] for r in runs])),
        }
    return summary


def gap_recovered(summary: dict[str, dict[str, Any]], condition: str) -> float | None:
    """(condition - gt_start) / (gt_100 - gt_start): the share of what all the data adds over the start
    split that this condition gets; None without both ends or a positive gap."""
    if not {"gt_start", "gt_100", condition} <= summary.keys():
        return None
    start, full = summary["gt_start"]["mean"], summary["gt_100"]["mean"]
    if not full > start:
        return None
    return (summary[condition]["mean"] - start) / (full - start)


def difference(summary: dict[str, dict[str, Any]], a: str, b: str) -> tuple[float, float]:
    """mean(a) - mean(b) and one standard error of it (each seed's run is an independent draw of
    training and of which evaluation episodes it solves)."""
    ra, rb = summary[a], summary[b]
    error = np.sqrt(ra["std"] ** 2 / max(1, ra["seeds"] - 1) + rb["std"] ** 2 / max(1, rb["seeds"] - 1))
    return ra["mean"] - rb["mean"], float(error)


def targets_text(summary: dict[str, dict[str, Any]]) -> list[str]:
    """The issue's targets, each with what this run reached: PS against GT 2x, the gap PS and random
    relabelling recover."""
    summary = {c: row for c, row in summary.items() if np.isfinite(row["mean"])}  # no simulator: no figure
    lines = []
    if {"ps", "gt_2x"} <= summary.keys():
        change, error = difference(summary, "ps", "gt_2x")
        if min(summary["ps"]["seeds"], summary["gt_2x"]["seeds"]) < 2:
            verdict, error_text = "vs", "no error estimate from one seed"
        else:
            verdict = "beats" if change > 2 * error else "is below" if change < -2 * error else "ties"
            error_text = f"one standard error {error:.3f}; beats = beyond 2 standard errors"
        lines.append(f"- PS {verdict} GT 2x the start split: {change:+.3f} ({error_text}).")
    if {"gt_start", "gt_100"} <= summary.keys() and gap_recovered(summary, "gt_100") is None:
        start, full = summary["gt_start"]["mean"], summary["gt_100"]["mean"]
        lines.append(
            f"- gt_100 ({full:.3f}) does not score above gt_start ({start:.3f}): no gap from gt_start to "
            "gt_100 to recover at this scale."
        )
    gap_goals = (
        ("ps", ">= 0.90"),
        ("ps_balanced", ""),
        ("ps_own_cuts", ""),
        ("ps_own_cuts_balanced", ""),
        ("oracle_relabel", ""),
        ("random_relabel", "well below PS"),
    )
    for condition, goal in gap_goals:
        share = gap_recovered(summary, condition)
        if share is not None:
            target = f" (target {goal})" if goal else ""
            lines.append(f"- {condition} recovers {share:.2f} of the gap from gt_start to gt_100{target}.")
    return lines


def added_quality(data: ExperimentData, added: dict[str, AddedSegments]) -> str:
    """A Markdown table of what each condition adds from play against play's ground truth: segments,
    the share whose span is exactly a true segment's, and the share of their steps whose label is the
    true instruction at that step."""
    truth_spans = {e.episode_id: {(s.start, s.end) for s in e.segments} for e in data.play}
    truth_steps = {}
    for episode in data.play:
        labels = np.full(episode.num_steps, "", dtype=object)
        for segment in episode.segments:
            labels[segment.start : segment.end] = segment.instruction
        truth_steps[episode.episode_id] = labels
    lines = [
        "| condition | segments added | exact true spans | steps labelled as the truth |",
        "|---|---|---|---|",
    ]
    for condition, segments in added.items():
        found = [(e, s) for e, group in segments.by_episode.items() for s in group]
        if not found:
            continue
        exact = sum((s.start, s.end) in truth_spans.get(e, ()) for e, s in found)
        steps = sum(s.length for _, s in found)
        right = sum(int((truth_steps[e][s.start : s.end] == s.instruction).sum()) for e, s in found)
        lines.append(
            f"| {condition} | {len(found)} | {exact / len(found):.3f} | {right / max(1, steps):.3f} |"
        )
    return "\n".join(lines) + "\n"


def results_table(spec: ExperimentSpec, scale: str, summary: dict[str, dict[str, Any]]) -> str:
    """The Markdown table: ours per condition, the paper's where it has the same condition."""
    lines = [
        "| condition | segments trained on (added) | success, mean +- std (seeds) | gap recovered | "
        f"paper {spec.paper_source} |",
        "|---|---|---|---|---|",
    ]
    for condition, row in summary.items():
        paper = spec.paper.get(condition)
        paper_text = f"{paper[0]:.3f} +- {paper[1]:.3f}" if paper else "-"
        share = gap_recovered(summary, condition)
        lines.append(
            f"| {condition} | {row['segments']} ({row['added']}) | {row['mean']:.3f} +- {row['std']:.3f} "
            f"({row['seeds']}) | {'-' if share is None else f'{share:.2f}'} | {paper_text} |"
        )
    for name, (mean, std) in spec.paper_only.items():
        lines.append(f"| {name} (paper only) | - | - | - | {mean:.3f} +- {std:.3f} |")
    return "\n".join(lines) + "\n"


def write_report(
    out: Path,
    spec: ExperimentSpec,
    scale: str,
    rows: list[dict[str, Any]],
    data: ExperimentData,
    added: dict[str, AddedSegments],
) -> Path:
    """out/results.md plus success.png, lengths.png and labels.png; returns the Markdown file."""
    summary = summarize(rows)
    text = [
        f"# Augmentation experiment, scale {scale!r}",
        "",
        f"Start split: {len(data.start)} annotated episodes, {data.start_segments} segments; play: "
        f"{len(data.play)} episodes, {sum(len(e.segments) for e in data.play)} ground-truth segments. Policy "
        f"`{spec.policy}`; success = the domain simulator's fixed seeded evaluation episodes.",
        "",
        results_table(spec, scale, summary),
        "Gap recovered: (condition - gt_start) / (gt_100 - gt_start).",
        "",
        *targets_text(summary),
        "",
        "What each condition adds, against play's ground truth:",
        "",
        added_quality(data, added),
        "Plots: success.png (per condition, error bars = std over seeds; paper's figures as crosses), "
        "curve.png (the ground-truth conditions: success against the segments trained on), "
        "lengths.png (segment lengths of what each condition adds vs play's ground truth), labels.png "
        "(label distribution of what each condition adds), gain.png (per instruction: success gain over "
        "gt_start against the segments added for that instruction).",
        "",
    ]
    path = out / "results.md"
    path.write_text("\n".join(text))
    _plot_success(out / "success.png", spec, summary)
    _plot_curve(out / "curve.png", summary)
    _plot_lengths(out / "lengths.png", data, added)
    _plot_labels(out / "labels.png", data, added)
    _plot_gain(out / "gain.png", rows, added)
    return path


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")  # files only, no display
    import matplotlib.pyplot as plt

    return plt


def _plot_success(path: Path, spec: ExperimentSpec, summary: dict[str, dict[str, Any]]) -> None:
    plt = _pyplot()
    names = list(summary)
    fig, ax = plt.subplots(figsize=(1.2 * len(names) + 2, 4))
    x = np.arange(len(names))
    ax.bar(x, [summary[n]["mean"] for n in names], yerr=[summary[n]["std"] for n in names], capsize=4)
    paper = [(i, spec.paper[n][0]) for i, n in enumerate(names) if n in spec.paper]
    if paper:
        ax.scatter(*zip(*paper, strict=True), marker="x", color="black", zorder=3, label="paper")
        ax.legend()
    ax.set_xticks(x, names, rotation=30, ha="right")
    ax.set_ylabel("policy success")
    ax.set_ylim(0, 1)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def _plot_lengths(path: Path, data: ExperimentData, added: dict[str, AddedSegments]) -> None:
    plt = _pyplot()
    truth = [s.length for e in data.play for s in e.segments]
    fig, ax = plt.subplots(figsize=(7, 4))
    bins = np.arange(0, max(truth, default=1) * 2 + 2)
    ax.hist(truth, bins=bins, histtype="step", linewidth=2, label="play ground truth", density=True)
    for condition, segments in added.items():
        if condition.startswith("gt_") or condition == "oracle_relabel":
            continue  # their lengths are the ground truth's
        lengths = [s.length for found in segments.by_episode.values() for s in found]
        if lengths:
            ax.hist(lengths, bins=bins, histtype="step", label=condition, density=True)
    ax.set_xlabel("segment length (steps)")
    ax.set_ylabel("share")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def _plot_labels(path: Path, data: ExperimentData, added: dict[str, AddedSegments]) -> None:
    plt = _pyplot()
    truth = Counter(s.instruction for e in data.play for s in e.segments)
    names = data.instructions
    fig, ax = plt.subplots(figsize=(max(7, 0.25 * len(names)), 4))
    total = max(1, sum(truth.values()))
    ax.plot([truth[n] / total for n in names], label="play ground truth", linewidth=2)
    for condition, segments in added.items():
        if condition.startswith("gt_"):
            continue
        counts = Counter(s.instruction for found in segments.by_episode.values() for s in found)
        if counts:
            ax.plot([counts[n] / sum(counts.values()) for n in names], label=condition)
    ax.set_xticks(range(len(names)), names, rotation=90, fontsize=6)
    ax.set_ylabel("share of added segments")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def _is_ground_truth(condition: str) -> bool:
    return condition.startswith("gt_")


def _plot_curve(path: Path, summary: dict[str, dict[str, Any]]) -> None:
    plt = _pyplot()
    points = sorted(
        (row["segments"], row["mean"], row["std"], condition)
        for condition, row in summary.items()
        if _is_ground_truth(condition)
    )
    fig, ax = plt.subplots(figsize=(7, 4))
    if points:
        x, mean, std, names = zip(*points, strict=True)
        ax.errorbar(x, mean, yerr=std, marker="o", capsize=4)
        for xi, yi, name in zip(x, mean, names, strict=True):
            ax.annotate(name, (xi, yi), textcoords="offset points", xytext=(4, -12), fontsize=7)
        ax.set_xscale("log")
    for condition, row in summary.items():
        if not _is_ground_truth(condition):
            ax.axhline(row["mean"], linestyle=":", linewidth=1, color="grey")
            ax.annotate(condition, (ax.get_xlim()[0], row["mean"]), fontsize=7, color="grey")
    ax.set_xlabel("annotated segments trained on (ground truth)")
    ax.set_ylabel("policy success")
    ax.set_ylim(0, 1)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def instruction_success(rows: list[dict[str, Any]], condition: str) -> dict[str, float]:
    """instruction -> success over every seed's evaluation episodes of that instruction."""
    totals: dict[str, list[int]] = {}
    for row in rows:
        if row["condition"] != condition:
            continue
        for instruction, (done, given) in row.get("per_instruction", {}).items():
            entry = totals.setdefault(instruction, [0, 0])
            entry[0] += done
            entry[1] += given
    return {name: done / given for name, (done, given) in totals.items() if given}


def _plot_gain(path: Path, rows: list[dict[str, Any]], added: dict[str, AddedSegments]) -> None:
    plt = _pyplot()
    start = instruction_success(rows, "gt_start")
    fig, ax = plt.subplots(figsize=(7, 4))
    for condition, segments in added.items():
        if condition == "gt_start" or pool_percent(condition) is not None:
            continue
        success = instruction_success(rows, condition)
        counts = Counter(s.instruction for found in segments.by_episode.values() for s in found)
        names = sorted(set(success) & set(start))
        if names:
            ax.scatter(
                [counts[n] for n in names], [success[n] - start[n] for n in names], s=12, label=condition
            )
    ax.axhline(0.0, color="black", linewidth=0.8)
    ax.set_xlabel("segments added for the instruction")
    ax.set_ylabel("success gain over gt_start")
    if ax.get_legend_handles_labels()[0]:
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
