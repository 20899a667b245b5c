"""PNG timeline of predicted vs true segments, one row pair per episode (matplotlib, no display)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from playseg_core.data.episode import Episode, Segment  # noqa: E402


def plot_timeline(
    path: str | Path, episodes: Sequence[Episode], predicted: Mapping[str, Sequence[Segment]]
) -> None:
    """Draw each episode's true segments (upper bar) and predicted ones (lower bar), coloured by
    instruction, with predicted labels that differ from the truth marked in red."""
    instructions = sorted(
        {s.instruction for e in episodes for s in e.segments}
        | {s.instruction for e in episodes for s in predicted.get(e.episode_id, [])}
    )
    cmap = plt.get_cmap("tab20", max(1, len(instructions)))
    colour = {name: cmap(i) for i, name in enumerate(instructions)}
    fig, axes = plt.subplots(len(episodes), 1, figsize=(12, 1.3 * len(episodes) + 0.6), squeeze=False)
    for ax, episode in zip(axes[:, 0], episodes, strict=True):
        truth_at = {}
        for seg in episode.segments:
            ax.broken_barh(
                [(seg.start, seg.length)], (1.1, 0.8), facecolors=colour[seg.instruction], edgecolor="k"
            )
            for t in range(seg.start, seg.end):
                truth_at[t] = seg.instruction
        for seg in predicted.get(episode.episode_id, []):
            wrong = any(truth_at.get(t) != seg.instruction for t in range(seg.start, seg.end))
            ax.broken_barh(
                [(seg.start, seg.length)],
                (0.1, 0.8),
                facecolors=colour[seg.instruction],
                edgecolor="red" if wrong else "k",
                linewidth=2 if wrong else 1,
            )
        ax.set_xlim(0, episode.num_steps)
        ax.set_yticks([0.5, 1.5], ["predicted", "truth"])
        ax.set_title(episode.episode_id, fontsize=8, loc="left")
    axes[-1, 0].set_xlabel("step (red edge: predicted label differs from the truth somewhere in the segment)")
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)
