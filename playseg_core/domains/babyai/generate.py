"""Generate a BabyAI play dataset: the presets and the episode source (the generic loop, seeds and
worker pool are in playseg_core/data/generation.py).

Episode ``i`` of a run with base seed ``s`` is generated from seed ``s * 10**9 + i``, so a dataset is a
pure function of (preset, seed): the worker count changes the speed, never the bytes. Episodes fill
the splits in order (test, then annotated train/val, then play) until each holds its segment target.
"""

from __future__ import annotations

import os
from dataclasses import asdict

from playseg_core.data import generation
from playseg_core.data.episode import Episode
from playseg_core.data.generation import SEED_STRIDE, EpisodeSource, GenerateSummary, episode_seed
from playseg_core.data.splits import SplitTargets
from playseg_core.domains.babyai.play import PlayConfig, generate_episode
from playseg_core.domains.babyai.spec import DOMAIN, INSTRUCTIONS

Preset = generation.Preset  # of PlayConfig

PRESETS: dict[str, Preset] = {
    "tiny": Preset(
        "tiny",
        "for tests: ~45 episodes, ~460 segments, a few seconds",
        PlayConfig(),
        SplitTargets.from_share(total_segments=400, annotated_share=0.25, test_segments=60),
    ),
    "sample": Preset(
        "sample",
        "the sample bags in bags/: ~200 annotated, ~80 play and ~30 test episodes (~2 MB as bags)",
        PlayConfig(),
        SplitTargets(test_segments=300, annotated_segments=2000, play_segments=800),
    ),
    "small": Preset(
        "small",
        "the demo: ~400 episodes, ~3,600 segments, under a minute on 2 cores",
        PlayConfig(),
        SplitTargets.from_share(total_segments=3200, annotated_share=0.25, test_segments=400),
    ),
    "medium": Preset(
        "medium",
        "the augmentation experiment's: 16,000 segments (1,600 annotated at 10%), about a minute on 2 cores",
        PlayConfig(),
        SplitTargets.from_share(total_segments=16_000, annotated_share=0.10, test_segments=400),
    ),
    "paper": Preset(
        "paper",
        "the paper's BabyAI scale: 10,000 annotated + 90,000 play segments, 2,000 test segments (~7 GB)",
        PlayConfig(),
        SplitTargets.from_share(total_segments=100_000, annotated_share=0.10, test_segments=2000),
    ),
}


def get_preset(name: str, annotated_share: float | None = None) -> Preset:
    """The preset ``name``; ``annotated_share`` re-divides its train+val+play segments (e.g. 0.1..1.0)."""
    return generation.get_preset(PRESETS, name, annotated_share)


def _episode(episode: Episode) -> Episode:
    return episode


# An episode is a few steps: four go to a worker at a time so the transfer does not dominate.
SOURCE = EpisodeSource(generate_episode, _episode, chunk_size=4, chunks_per_worker=4)
"""How BabyAI episodes are made; one without segments (the bot failed its first task) is skipped."""


def generate_dataset(
    out: str | os.PathLike[str],
    preset: Preset,
    seed: int = 0,
    workers: int = 1,
    progress: bool = True,
    overwrite: bool = False,
) -> GenerateSummary:
    """Generate ``preset`` into the dataset directory ``out`` (streamed; written atomically at the end)."""
    meta = {
        "generator": "playseg_core.domains.babyai.generate",
        "env": "BabyAI GoToLocal",
        "preset": preset.name,
        "seed": seed,
        "seed_rule": f"episode seed = seed * {SEED_STRIDE} + episode number",
        "play_config": asdict(preset.play),
        "split_targets": asdict(preset.targets),
    }
    return generation.write_dataset(
        out,
        preset,
        SOURCE,
        INSTRUCTIONS,
        preset.play.features,
        DOMAIN,
        meta,
        seed,
        workers,
        progress,
        overwrite,
    )


__all__ = [
    "PRESETS",
    "SEED_STRIDE",
    "GenerateSummary",
    "Preset",
    "episode_seed",
    "generate_dataset",
    "get_preset",
]
