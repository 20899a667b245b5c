"""The conditions of the paper's augmentation table: which segments join the annotated start split.

Every condition trains the same policy on the start split's annotated segments plus the segments it adds
from the rest of the pool (the play split, whose ground truth the segmenters never see):

- ``gt_start``: nothing added (the start split alone);
- ``gt_2x``, ``gt_4x``: ground-truth segments of play in order, until the set is 2x / 4x the start split;
- ``gt_100``: every ground-truth segment of play (all the data, labelled);
- ``oracle_relabel``: the ground-truth segments of play, labelled by the labelling model (perfect cuts);
- ``random_relabel``: random windows of play (lengths between the shortest and longest annotated
  segment), labelled by the labelling model;
- ``ps`` and the baselines (``unloc``, ``tridet``, ``changepoint``): what that segmentation method
  extracts from play, kept when its label confidence reaches the method's calibrated threshold.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from playseg_core.data.episode import Episode, Segment

GT_MULTIPLES = {"gt_2x": 2, "gt_4x": 4}
SEGMENTER_CONDITIONS = {"ps": "ps", "random_relabel": "random", "unloc": "unloc", "tridet": "tridet"}
"""condition -> the segmentation method (baselines/registry.py) whose segments it adds."""
CONDITIONS = ("gt_start", "gt_2x", "gt_4x", "gt_100", "oracle_relabel", "random_relabel", "ps")
"""The default conditions, in table order; ``unloc``, ``tridet`` and ``changepoint`` on request."""
KNOWN_CONDITIONS = (*CONDITIONS, "unloc", "tridet", "changepoint")


@dataclass(frozen=True)
class AddedSegments:
    """The segments one condition adds, by play episode id."""

    condition: str
    by_episode: dict[str, list[Segment]]

    @property
    def count(self) -> int:
        return sum(len(segments) for segments in self.by_episode.values())

    def save(self, path: Path) -> None:
        rows = {
            episode_id: [[s.start, s.end, s.instruction, s.confidence] for s in segments]
            for episode_id, segments in self.by_episode.items()
        }
        tmp = path.with_suffix(".tmp")
        tmp.write_text(json.dumps({"condition": self.condition, "segments": rows}))
        tmp.replace(path)  # a cached file is always complete

    @classmethod
    def load(cls, path: Path) -> AddedSegments:
        data = json.loads(path.read_text())
        by_episode = {
            episode_id: [Segment(int(a), int(b), str(label), float(conf)) for a, b, label, conf in rows]
            for episode_id, rows in data["segments"].items()
        }
        return cls(data["condition"], by_episode)


def check_conditions(names: Sequence[str]) -> list[str]:
    """``names`` in order without repeats; ValueError naming an unknown one."""
    unknown = [name for name in names if name not in KNOWN_CONDITIONS]
    if unknown:
        raise ValueError(f"unknown conditions {unknown} (known: {', '.join(KNOWN_CONDITIONS)})")
    return list(dict.fromkeys(names))


def ground_truth_added(condition: str, play: Sequence[Episode], start_segments: int) -> AddedSegments:
    """The ground-truth segments ``gt_*`` conditions add: all of them (``gt_100``), none (``gt_start``), or
    the first ones in play order until start + added = the multiple of the start split."""
    if condition == "gt_start":
        return AddedSegments(condition, {})
    wanted = None if condition == "gt_100" else (GT_MULTIPLES[condition] - 1) * start_segments
    by_episode: dict[str, list[Segment]] = {}
    taken = 0
    for episode in play:
        for segment in episode.segments:
            if wanted is not None and taken >= wanted:
                return AddedSegments(condition, by_episode)
            by_episode.setdefault(episode.episode_id, []).append(segment)
            taken += 1
    return AddedSegments(condition, by_episode)
