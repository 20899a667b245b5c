"""Generating a play dataset from a domain's episode generator: presets, seeds, parallel episodes, the
writing loop. Domain-free: a domain supplies its episode function, play settings, instructions and meta.

Episode ``i`` of a run with base seed ``s`` is generated from seed ``s * 10**9 + i``, so a dataset is a
pure function of (preset, seed): the worker count changes the speed, never the bytes. Episodes fill the
splits in order (test, then annotated train/val, then play) until each holds its segment target.
"""

from __future__ import annotations

import multiprocessing
import os
import sys
import time
from collections import deque
from collections.abc import Callable, Iterator, Mapping, Sequence
from concurrent.futures import Future, ProcessPoolExecutor
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Generic, TypeVar

from tqdm import tqdm

from playseg_core.data.dataset import DatasetWriter
from playseg_core.data.episode import Episode
from playseg_core.data.features import Features
from playseg_core.data.splits import SPLITS, SplitAssigner, SplitTargets
from playseg_core.errors import PlaysegError

SEED_STRIDE = 10**9
"""Episode seeds of one run are ``base_seed * SEED_STRIDE + index``."""

PlayT = TypeVar("PlayT")  # a domain's play settings (picklable: they go to the worker processes)
ProducedT = TypeVar("ProducedT")  # what a domain's episode function returns


@dataclass(frozen=True)
class Preset(Generic[PlayT]):
    """A named dataset size: the domain's play settings and the split targets."""

    name: str
    description: str
    play: PlayT
    targets: SplitTargets


class UnknownPresetError(PlaysegError, KeyError):
    """A preset name a domain does not know (a KeyError for lookups, a ValueError for the CLI)."""

    def __str__(self) -> str:  # KeyError would print the message quoted
        return str(self.args[0])


def get_preset(
    presets: Mapping[str, Preset[PlayT]],
    name: str,
    annotated_share: float | None = None,
    what: str = "preset",
) -> Preset[PlayT]:
    """The preset ``name``; ``annotated_share`` re-divides its train+val+play segments (e.g. 0.1..1.0).
    UnknownPresetError naming ``what`` (e.g. "tabletop preset") and the known ones."""
    if name not in presets:
        raise UnknownPresetError(f"unknown {what} {name!r} (expected one of {', '.join(presets)})")
    preset = presets[name]
    if annotated_share is None:
        return preset
    targets = preset.targets
    total = targets.annotated_segments + targets.play_segments
    new_targets = SplitTargets.from_share(total, annotated_share, targets.test_segments, targets.val_fraction)
    return replace(preset, targets=new_targets)


@dataclass
class GenerateSummary:
    """What a generation run wrote."""

    path: Path
    preset: str
    seed: int
    workers: int
    episodes: int
    steps: int
    segments_per_split: dict[str, int]
    episodes_per_split: dict[str, int]
    skipped_episodes: int
    seconds: float
    bytes_on_disk: int

    @property
    def steps_per_second(self) -> float:
        return self.steps / self.seconds if self.seconds > 0 else 0.0


def episode_seed(base_seed: int, index: int) -> int:
    """Seed of episode ``index`` in a run with ``base_seed``."""
    if base_seed < 0 or not 0 <= index < SEED_STRIDE:
        raise PlaysegError(f"seed {base_seed} must be >= 0 and episode index {index} in [0, {SEED_STRIDE})")
    return base_seed * SEED_STRIDE + index


def _generate_chunk(
    generate: Callable[[PlayT, int], ProducedT], config: PlayT, seeds: list[int]
) -> list[ProducedT]:
    return [generate(config, seed) for seed in seeds]


def episode_stream(
    generate: Callable[[PlayT, int], ProducedT],
    config: PlayT,
    base_seed: int,
    workers: int = 1,
    chunk_size: int = 1,
    chunks_per_worker: int = 2,
) -> Iterator[tuple[int, ProducedT]]:
    """Endless (seed, ``generate(config, seed)``) stream in seed order, made by ``workers`` processes.

    ``generate`` must be picklable (a module-level function). Episodes go to the workers ``chunk_size``
    at a time (several when one episode is quick, so the transfer does not dominate), at most
    ``chunks_per_worker * workers`` chunks in flight: memory stays bounded however long it runs, and
    little is generated past the last episode needed.
    """
    if workers < 1 or chunk_size < 1 or chunks_per_worker < 1:
        raise PlaysegError(
            f"workers, chunk_size and chunks_per_worker must be >= 1, got {workers}, {chunk_size}, "
            f"{chunks_per_worker}"
        )
    index = 0
    if workers == 1:
        while True:
            seed = episode_seed(base_seed, index)
            yield seed, generate(config, seed)
            index += 1
    # spawn: the parent may hold threads (tqdm, ROS, torch) that fork would copy half-locked.
    # An executor, not multiprocessing.Pool: when the caller stops early, the chunks not started are
    # cancelled and the running ones finish. Pool.terminate instead kills workers that may hold the
    # task queue's lock, and then waits for that lock forever (seen as a rare hang at the end).
    pool = ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn"))
    pending: deque[tuple[list[int], Future]] = deque()
    try:
        while True:
            while len(pending) < chunks_per_worker * workers:
                seeds = [episode_seed(base_seed, index + k) for k in range(chunk_size)]
                index += chunk_size
                pending.append((seeds, pool.submit(_generate_chunk, generate, config, seeds)))
            seeds, result = pending.popleft()
            yield from zip(seeds, result.result(), strict=True)
    finally:
        pool.shutdown(wait=True, cancel_futures=True)


@dataclass(frozen=True)
class EpisodeSource(Generic[PlayT, ProducedT]):
    """How a domain's episodes are made and recorded.

    generate: (play settings, seed) -> what the domain produces (picklable; runs in the workers);
    episode_of: that -> the Episode to store; extra_of: (seed, that) -> the extra fields of its row in
    ``meta/episodes.jsonl``, called once per episode written (a domain may keep its own tally there);
    final_meta: -> entries added to the dataset's meta after the last episode (e.g. that tally).
    """

    generate: Callable[[PlayT, int], ProducedT]
    episode_of: Callable[[ProducedT], Episode]
    extra_of: Callable[[int, ProducedT], dict[str, Any]] = lambda seed, produced: {"seed": seed}
    final_meta: Callable[[], dict[str, Any]] = dict
    chunk_size: int = 1
    chunks_per_worker: int = 2


def generated_source(domain: str, preset: str, seed: int, episode_seed: int) -> dict[str, Any]:
    """A generated episode's ``source`` (docs/dataset-format.md): the domain whose generator made it, the
    preset, the run's seed and the episode's own seed (the episode again: the domain's generator with the
    preset's play settings and ``episode_seed``)."""
    return {"generator": domain, "preset": preset, "seed": seed, "episode_seed": episode_seed}


def write_dataset(
    out: str | os.PathLike[str],
    preset: Preset[PlayT],
    source: EpisodeSource[PlayT, ProducedT],
    instructions: Sequence[str],
    features: Features,
    domain: str,
    meta: dict[str, Any],
    seed: int = 0,
    workers: int = 1,
    progress: bool = True,
    overwrite: bool = False,
) -> GenerateSummary:
    """Generate ``preset`` into the dataset directory ``out`` (streamed; written atomically at the end).

    Each episode's ``source`` names its generator (`generated_source`). An episode without segments is
    skipped (nothing to learn from) and counted."""
    out = Path(out)
    targets = preset.targets
    assigner = SplitAssigner(targets)
    skipped = 0
    started = time.perf_counter()
    with (
        DatasetWriter(
            out, instructions, meta, overwrite=overwrite, features=features, domain=domain
        ) as writer,
        tqdm(
            total=targets.total_segments, unit="seg", file=sys.stderr, disable=not progress, desc=preset.name
        ) as bar,
    ):
        stream = episode_stream(
            source.generate, preset.play, seed, workers, source.chunk_size, source.chunks_per_worker
        )
        try:
            for episode_seed_value, produced in stream:
                episode = replace(
                    source.episode_of(produced),
                    source=generated_source(domain, preset.name, seed, episode_seed_value),
                )
                if not episode.segments:
                    skipped += 1
                    continue
                split = assigner.assign(len(episode.segments))
                assert split is not None
                writer.add(episode, split, extra=source.extra_of(episode_seed_value, produced))
                bar.update(len(episode.segments))
                if assigner.done:
                    break
        finally:
            stream.close()  # stops the worker pool
        # The writer stores its meta when it closes.
        writer.meta.update(source.final_meta())
        counts = writer.split_counts
        steps = sum(c["steps"] for c in counts.values())
        episodes = writer.num_episodes
    seconds = time.perf_counter() - started
    size = sum(f.stat().st_size for f in out.rglob("*") if f.is_file())
    return GenerateSummary(
        path=out,
        preset=preset.name,
        seed=seed,
        workers=workers,
        episodes=episodes,
        steps=steps,
        segments_per_split={name: counts[name]["segments"] for name in SPLITS},
        episodes_per_split={name: counts[name]["episodes"] for name in SPLITS},
        skipped_episodes=skipped,
        seconds=seconds,
        bytes_on_disk=size,
    )


__all__ = [
    "SEED_STRIDE",
    "EpisodeSource",
    "GenerateSummary",
    "Preset",
    "UnknownPresetError",
    "episode_seed",
    "episode_stream",
    "generated_source",
    "get_preset",
    "write_dataset",
]
