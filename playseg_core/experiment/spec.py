"""What a domain declares to take part in the augmentation experiment (`Domain.experiment`: the policy,
the scales, the paper's figures) and the data one experiment reads; runner.py runs it, report.py reports it.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from playseg_core.data.dataset import PlayDataset
from playseg_core.data.episode import Episode
from playseg_core.data.features import Features
from playseg_core.domains import load_domain
from playseg_core.errors import PlaysegError
from playseg_core.ps.calibration import LABEL_ACCURACY_TARGET


@dataclass(frozen=True)
class ExperimentScale:
    """One size of the experiment: the domain's generation preset, the start split's share of the pool,
    the budgets."""

    preset: str
    start_share: float
    policy: dict[str, Any]  # the policy learner's settings (steps, batch_size, ...); the seed is the run's
    eval_episodes: int
    # the step cap of each segmentation method (None: its default budget); early stopping on the val
    # split may end a run sooner (baselines/common.py TrainOptions)
    segmenter_steps: int | None = None
    description: str = ""
    # How PS and the labelling model read the start split (TrainingData): whether they read the previous
    # action, and whether they train on the domain's symmetries (its clip_symmetries; without them, rotated/
    # mirrored frames, only where the domain's labels and ends do not depend on orientation).
    segmenter_reads_actions: bool = True
    segmenter_augment: bool = False
    # the held-out label accuracy PS's confidence threshold is calibrated for (ps/calibration.py)
    segmenter_label_accuracy: float = LABEL_ACCURACY_TARGET
    # the accuracy of the labels of PS's own val cuts that ``ps_own_cuts``' threshold is calibrated for
    # (None: segmenter_label_accuracy); only its conditions read it (`NEW_CONDITIONS_ONLY`)
    own_cuts_accuracy: float | None = None


NEW_CONDITIONS_ONLY = frozenset({"own_cuts_accuracy"})
"""Scale fields that only conditions added with them read: an ``out`` recorded before such a field
existed cached none of those conditions, so it resumes under the field's current value."""


@dataclass(frozen=True)
class ExperimentSpec:
    """What a domain declares to take part (its `Domain.experiment`): the policy it trains, its scales, and
    the paper's figures (condition -> (mean, std)); ``paper_only`` rows have no condition here."""

    policy: str
    scales: dict[str, ExperimentScale]
    paper: dict[str, tuple[float, float]] = field(default_factory=dict)
    paper_only: dict[str, tuple[float, float]] = field(default_factory=dict)
    paper_source: str = ""

    @classmethod
    def of_domain(cls, domain: str) -> ExperimentSpec:
        """The experiment of ``domain`` (its `Domain.experiment`, built now)."""
        build = load_domain(domain).experiment
        if build is None:
            raise PlaysegError(f"domain {domain!r} has no experiment (its Domain declares none)")
        return build()

    def scale(self, name: str) -> ExperimentScale:
        if name not in self.scales:
            raise PlaysegError(f"--scale {name!r}: this domain has {', '.join(self.scales)}")
        return self.scales[name]


@dataclass
class ExperimentData:
    """The start split (annotated train), its val split, and play with its ground truth."""

    start: list[Episode]
    val: list[Episode]
    play: list[Episode]
    instructions: list[str]
    features: Features
    domain: str | None

    @classmethod
    def open(cls, path: Path) -> ExperimentData:
        dataset = PlayDataset.open(path)
        return cls(
            list(dataset.episodes("train")),
            list(dataset.episodes("val")),
            list(dataset.episodes("play", truth=True)),
            list(dataset.instructions),
            dataset.features,
            dataset.domain,
        )

    @property
    def start_segments(self) -> int:
        return sum(len(episode.segments) for episode in self.start)
