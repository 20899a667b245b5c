"""Random windows (the paper's "Random Segments"): each episode cut into back-to-back windows whose
lengths are uniform between the shortest and the longest annotated segment, each labelled by the
labelling model. It tiles the trajectory. Training it is training the labelling model."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from playseg_core.baselines.common import (
    Segmenter,
    SegmentOptions,
    TrainedSegmenter,
    TrainingData,
    TrainOptions,
    annotated_lengths,
    episode_rng,
)
from playseg_core.baselines.labelled_pieces import (
    label_pieces,
    load_labeller,
    save_labeller,
    train_labelling_model,
)
from playseg_core.data.episode import Episode, Segment
from playseg_core.errors import PlaysegError
from playseg_core.ps.model import LabelModel, PSModel

METHOD = "random"


def random_spans(
    num_steps: int, shortest: int, longest: int, rng: np.random.Generator
) -> list[tuple[int, int]]:
    """Back-to-back windows of uniform length in [shortest, longest] covering [0, num_steps); the last
    one is cut at the end."""
    if not 1 <= shortest <= longest:
        raise PlaysegError(f"random windows need 1 <= shortest <= longest, got {shortest}, {longest}")
    spans, start = [], 0
    while start < num_steps:
        end = min(num_steps, start + int(rng.integers(shortest, longest + 1)))
        spans.append((start, end))
        start = end
    return spans


class RandomWindowSegmenter(Segmenter):
    method = METHOD
    tiles = True

    def __init__(
        self, model: LabelModel | PSModel, shortest: int, longest: int, options: SegmentOptions
    ) -> None:
        self.model = model.eval()
        self.instructions = model.instructions
        self.features = model.cfg.features
        self.feature_names = model.cfg.feature_names
        self.shortest, self.longest = (options.min_len or shortest), max(options.min_len or shortest, longest)
        self.seed = options.seed

    def segment(self, episode: Episode) -> list[Segment]:
        rng = episode_rng(self.seed, episode.episode_id)
        return label_pieces(
            self.model, episode, random_spans(episode.num_steps, self.shortest, self.longest, rng)
        )


def train_random(data: TrainingData, options: TrainOptions) -> TrainedSegmenter:
    lengths = annotated_lengths(data.annotated())
    model, meta, seconds = train_labelling_model(data, options)
    settings = {"method": METHOD, "shortest": int(lengths.min()), "longest": int(lengths.max())}
    meta["baseline"] = settings

    def save(path: Path, extra: dict[str, Any]) -> Path:
        return save_labeller(path, model, {**meta, **extra})

    segmenter = RandomWindowSegmenter(model, settings["shortest"], settings["longest"], SegmentOptions())
    text = (
        f"labelling model for random windows of {settings['shortest']}..{settings['longest']} steps: "
        f"val accuracy {meta['val_label_accuracy']:.3f}, {seconds:.0f} s"
    )
    return TrainedSegmenter(segmenter, save, seconds, text)


def load_random_segmenter(path: str | Path, options: SegmentOptions) -> RandomWindowSegmenter:
    """From a checkpoint `train_random` wrote; any other labeller cuts L_min..L_max of its configuration."""
    model, meta = load_labeller(path)
    settings = meta.get("baseline", {})
    if settings.get("method") == METHOD:
        shortest, longest = int(settings["shortest"]), int(settings["longest"])
    else:
        shortest, longest = model.cfg.min_len, model.max_len
    return RandomWindowSegmenter(model, shortest, min(longest, model.max_len), options)
