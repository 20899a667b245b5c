"""Generate a tabletop play dataset: the presets, the episode source and the teleoperator's record (the
generic loop, seeds and worker pool are in playseg_core/data/generation.py).

Episode ``i`` of a run with base seed ``s`` is generated from seed ``s * 10**9 + i``, so a dataset is a
pure function of (preset, seed): the worker count changes the speed, never the bytes. Episodes fill
the splits in order (test, then annotated train/val, then play) until each holds its segment target.
The teleoperator's record (tasks attempted and solved per family, instruction lengths) is kept in the
dataset's meta (``meta/info.json`` field ``meta.teleop``) and in the returned summary.
"""

from __future__ import annotations

import os
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

from playseg_core.data import generation
from playseg_core.data.episode import Episode
from playseg_core.data.generation import SEED_STRIDE, EpisodeSource, GenerateSummary, episode_seed
from playseg_core.data.splits import SplitTargets
from playseg_core.domains.tabletop.play import PlayConfig, PlayEpisode, PlayStats, generate_episode
from playseg_core.domains.tabletop.spec import DOMAIN

Preset = generation.Preset  # of PlayConfig

PRESETS: dict[str, Preset] = {
    "tiny": Preset(
        "tiny",
        "for tests: ~16 short episodes, ~76 segments, ~4,000 steps (~110 MB), a few seconds",
        PlayConfig(tasks_per_episode=(3, 6)),
        SplitTargets(test_segments=12, annotated_segments=24, play_segments=36, val_fraction=0.25),
    ),
    "small": Preset(
        "small",
        "the demo: 100 annotated + 300 play segments (25%), 80 test segments; ~24,000 steps (~0.67 GB)",
        PlayConfig(),
        SplitTargets.from_share(total_segments=400, annotated_share=0.25, test_segments=80),
    ),
    "paper": Preset(
        "paper",
        "the paper's CALVIN setting: a 25% annotated start split (1,000 segments), 3,000 play segments "
        "to augment to 100%, 500 held-out test segments; ~210,000 steps (~6 GB)",
        PlayConfig(),
        SplitTargets.from_share(total_segments=4000, annotated_share=0.25, test_segments=500),
    ),
    "calvin-small": Preset(
        "calvin-small",
        "CALVIN's shape (32 task types, instructions.CALVIN_INSTRUCTIONS), small: 400 annotated + 1,200 play "
        "segments (25%), 160 test segments; ~75,000 steps (~2 GB)",
        PlayConfig(task_set="calvin"),
        SplitTargets.from_share(total_segments=1600, annotated_share=0.25, test_segments=160),
    ),
    "calvin": Preset(
        "calvin",
        "CALVIN's shape (32 task types, instructions.CALVIN_INSTRUCTIONS): a 25% annotated start split "
        "(1,800 segments, >= 30 per task type), 5,400 play segments to augment to 100%, 500 held-out test "
        "segments; ~320,000 steps (~9 GB)",
        PlayConfig(task_set="calvin"),
        SplitTargets.from_share(total_segments=7200, annotated_share=0.25, test_segments=500),
    ),
}


def get_preset(name: str, annotated_share: float | None = None) -> Preset:
    """The preset ``name``; ``annotated_share`` re-divides its train+val+play segments (e.g. 0.1..1.0)."""
    return generation.get_preset(PRESETS, name, annotated_share, what="tabletop preset")


@dataclass
class TabletopSummary(GenerateSummary):
    """What a generation run wrote, and how the teleoperator did in the episodes written."""

    teleop: PlayStats = field(default_factory=PlayStats)


def length_summary(lengths: list[int]) -> dict[str, float]:
    """Mean, percentiles and the share in [20, 100] steps of instruction lengths."""
    if not lengths:
        return {}
    values = np.asarray(lengths)
    p5, p25, p50, p75, p95 = np.percentile(values, [5, 25, 50, 75, 95])
    return {
        "count": int(values.size),
        "mean": round(float(values.mean()), 2),
        "p5": round(float(p5), 1),
        "p25": round(float(p25), 1),
        "median": round(float(p50), 1),
        "p75": round(float(p75), 1),
        "p95": round(float(p95), 1),
        "max": int(values.max()),
        "share_20_to_100": round(float(((values >= 20) & (values <= 100)).mean()), 4),
    }


def _episode(played: PlayEpisode) -> Episode:
    return played.episode


class TeleopTally:
    """The teleoperator's record over the episodes written (not the skipped ones)."""

    def __init__(self) -> None:
        self.stats = PlayStats()

    def extra_of(self, seed: int, played: PlayEpisode) -> dict[str, Any]:
        self.stats.merge(played.stats)
        return {"seed": seed, "teleop": played.stats.to_json()}

    def final_meta(self) -> dict[str, Any]:
        return {
            "teleop": {**self.stats.to_json(), "instruction_steps": length_summary(self.stats.task_lengths)}
        }


def generate_dataset(
    out: str | os.PathLike[str],
    preset: Preset,
    seed: int = 0,
    workers: int = 1,
    progress: bool = True,
    overwrite: bool = False,
) -> TabletopSummary:
    """Generate ``preset`` into the dataset directory ``out`` (streamed; written atomically at the end).
    An episode in which the teleoperator solved nothing is skipped (nothing to learn from)."""
    meta: dict[str, Any] = {
        "generator": "playseg_core.domains.tabletop.generate",
        "env": "tabletop (pymunk)",
        "preset": preset.name,
        "seed": seed,
        "seed_rule": f"episode seed = seed * {SEED_STRIDE} + episode number",
        "play_config": asdict(preset.play),
        "split_targets": asdict(preset.targets),
        "unlabelled": "steps no segment covers (idle stretches, failed tasks) carry no instruction",
    }
    tally = TeleopTally()
    # An episode is hundreds of steps: one per worker task, the transfer is cheap next to it.
    source = EpisodeSource(generate_episode, _episode, tally.extra_of, tally.final_meta)
    summary = generation.write_dataset(
        out,
        preset,
        source,
        preset.play.instructions,
        preset.play.features,
        DOMAIN,
        meta,
        seed,
        workers,
        progress,
        overwrite,
    )
    return TabletopSummary(**vars(summary), teleop=tally.stats)


__all__ = [
    "PRESETS",
    "SEED_STRIDE",
    "Preset",
    "TabletopSummary",
    "episode_seed",
    "generate_dataset",
    "get_preset",
    "length_summary",
]
