"""The experiment's report: a Markdown table of policy success per condition (mean +- std over seeds) next
to the paper's figures, and plots of success, segment lengths and labels of what each condition adds."""

from __future__ import annotations

from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np

from playseg_core.experiment.conditions import AddedSegments
from playseg_core.experiment.runner import ExperimentData, ExperimentSpec


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
            "seeds": len(runs),
            "segments": runs[0]["segments"],
            "added": runs[0]["added_segments"],
            "seconds": float(np.mean([r["seconds"] for r in runs])),
        }
    return summary


def results_table(spec: ExperimentSpec, scale: str, summary: dict[str, dict[str, Any]]) -> str:
    """The Markdown table: ours per condition, the paper's where it has the same condition."""
    lines = [
        f"| condition | segments trained on (added) | success, mean +- std (seeds) | paper {spec.paper_source} |",
        "|---|---|---|---|",
    ]
    for condition, row in summary.items():
        paper = spec.paper.get(condition)
        paper_text = f"{paper[0]:.3f} +- {paper[1]:.3f}" if paper else "-"
        lines.append(
            f"| {condition} | {row['segments']} ({row['added']}) | {row['mean']:.3f} +- {row['std']:.3f} "
            f"({row['seeds']}) | {paper_text} |"
        )
    for name, (mean, std) in spec.paper_only.items():
        lines.append(f"| {name} (paper only) | - | - | {mean:.3f} +- {std:.3f} |")
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
        "Plots: success.png (per condition, error bars = std over seeds; paper's figures as crosses), "
        "lengths.png (segment lengths of what each condition adds vs play's ground truth), labels.png "
        "(label distribution of what each condition adds).",
        "",
    ]
    path = out / "results.md"
    path.write_text("\n".join(text))
    _plot_success(out / "success.png", spec, summary)
    _plot_lengths(out / "lengths.png", data, added)
    _plot_labels(out / "labels.png", data, added)
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
