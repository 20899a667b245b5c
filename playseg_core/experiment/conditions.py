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
  extracts from play, kept by its checkpoint's ``label`` keep rule (ps/labelling.py): PS's calibrated
  label threshold; the baselines record none, so all of theirs;
- ``ps_balanced``: what ``ps`` keeps, each instruction capped at its share of the start split
  (`balance_labels`; the most confident first);
- ``ps_own_cuts``: what PS cuts from play, kept when the label's probability times the cut's
  (`segment_probability`) reaches a threshold calibrated on PS's own cuts of the val episodes
  (`calibrate_on_own_cuts`), not on their true cuts as ``ps``'s; ``ps_own_cuts_balanced``: those, capped
  as ``ps_balanced`` (the most confident labels first, as there).

The ground-truth curve (``--conditions curve``) adds ``gt_<p>pct``: the first p% of the whole pool's
ground-truth segments (the start split's first, then play's), fewer than the start split when p is below
its share; it measures how much the policy gains from more correct data, i.e. the headroom a start split
leaves.
"""

from __future__ import annotations

import json
import math
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from playseg_core.data.episode import Episode, Segment
from playseg_core.errors import PlaysegError

GT_MULTIPLES = {"gt_2x": 2, "gt_4x": 4}
SEGMENTER_CONDITIONS = {"ps": "ps", "random_relabel": "random", "unloc": "unloc", "tridet": "tridet"}
"""condition -> the segmentation method (baselines/registry.py) whose segments it adds."""
CONDITIONS = ("gt_start", "gt_2x", "gt_4x", "gt_100", "oracle_relabel", "random_relabel", "ps")
"""The default conditions, in table order; ``ps_balanced``, ``ps_own_cuts``, ``ps_own_cuts_balanced``,
``unloc``, ``tridet`` and ``changepoint`` on request."""
BALANCED = {"ps_balanced": "ps", "ps_own_cuts_balanced": "ps_own_cuts"}
"""condition -> the condition whose kept segments it caps per instruction (`balance_labels`)."""
OWN_CUTS = {"ps_own_cuts": "ps"}
"""condition -> the segmentation method whose segments it keeps by the own-cut threshold."""
POOL_PERCENTS = (1, 2, 5, 10, 25, 50)
"""The ground-truth curve's shares of the pool besides the start split and 100% (``gt_<p>pct``)."""
CURVE_CONDITIONS = tuple(f"gt_{p}pct" for p in POOL_PERCENTS)
KNOWN_CONDITIONS = (
    *CONDITIONS,
    "ps_balanced",
    "ps_own_cuts",
    "ps_own_cuts_balanced",
    "unloc",
    "tridet",
    "changepoint",
    *CURVE_CONDITIONS,
)
CONDITION_GROUPS = {
    "default": CONDITIONS,
    "curve": ("gt_start", "gt_100", *CURVE_CONDITIONS),
    "baselines": ("unloc", "tridet", "changepoint"),
}
"""Names that stand for several conditions in ``--conditions``."""


@dataclass(frozen=True)
class AddedSegments:
    """The segments one condition adds, by play episode id."""

    condition: str
    by_episode: dict[str, list[Segment]]
    start_kept: int | None = None  # how many of the start split's segments are trained on (None: all)
    # the checkpoints the segments come from, their path under the experiment's out -> digest of the file
    # (None: not recorded in the file); a cache made from another one is stale
    made_from: dict[str, str] | None = None

    @property
    def count(self) -> int:
        return sum(len(segments) for segments in self.by_episode.values())

    def save(self, path: Path) -> None:
        rows = {
            episode_id: [[s.start, s.end, s.instruction, s.confidence, s.log_prob] for s in segments]
            for episode_id, segments in self.by_episode.items()
        }
        tmp = path.with_suffix(".tmp")
        record = {
            "condition": self.condition,
            "segments": rows,
            "start_kept": self.start_kept,
            "made_from": self.made_from,
        }
        tmp.write_text(json.dumps(record))
        tmp.replace(path)  # a cached file is always complete

    @classmethod
    def load(cls, path: Path) -> AddedSegments:
        data = json.loads(path.read_text())
        by_episode = {  # rows without log_prob have 4 columns
            episode_id: [Segment(int(r[0]), int(r[1]), str(r[2]), *map(float, r[3:5])) for r in rows]
            for episode_id, rows in data["segments"].items()
        }
        return cls(data["condition"], by_episode, data.get("start_kept"), data.get("made_from"))


def check_conditions(names: Sequence[str]) -> list[str]:
    """``names`` (groups expanded) in order without repeats; ValueError naming an unknown one."""
    expanded = [c for name in names for c in CONDITION_GROUPS.get(name, (name,))]
    unknown = [name for name in expanded if name not in KNOWN_CONDITIONS]
    if unknown:
        known = [*CONDITION_GROUPS, *KNOWN_CONDITIONS]
        raise PlaysegError(f"unknown conditions {unknown} (known: {', '.join(known)})")
    return list(dict.fromkeys(expanded))


def pool_percent(condition: str) -> int | None:
    """p of a ``gt_<p>pct`` condition, else None."""
    if condition.startswith("gt_") and condition.endswith("pct"):
        return int(condition[3:-3])
    return None


def pool_share_segments(percent: int, play: Sequence[Episode], start_segments: int) -> int:
    """How many segments p% of the pool (the start split's plus play's ground truth) is, at least one."""
    pool = start_segments + sum(len(episode.segments) for episode in play)
    return max(1, round(pool * percent / 100))


def ground_truth_added(condition: str, play: Sequence[Episode], start_segments: int) -> AddedSegments:
    """The ground-truth segments ``gt_*`` conditions add: all of them (``gt_100``), none (``gt_start``),
    the first ones in play order until start + added = the multiple of the start split, or the first p%
    of the pool (``gt_<p>pct``, keeping only part of the start split when p% of the pool is fewer)."""
    if condition == "gt_start":
        return AddedSegments(condition, {})
    percent = pool_percent(condition)
    if percent is not None:
        wanted = pool_share_segments(percent, play, start_segments)
        if wanted <= start_segments:
            return AddedSegments(condition, {}, start_kept=wanted)
        wanted -= start_segments
    else:
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


def balance_labels(added: AddedSegments, condition: str, start: Sequence[Episode]) -> AddedSegments:
    """``added`` with each instruction's segments capped at ceil(its share of the start split's segments x
    ``added.count``), the most confident kept (ties: play order), in play order.

    A segmenter's labels can pile onto the instructions it learnt best (the paper's CALVIN result,
    attributed to label imbalance); no instruction then gets more of what was kept than its share of
    the annotated segments. Nothing is added for the under-represented ones (there is nothing to add),
    so the balanced set is smaller; an instruction the start split lacks gets none.
    """
    start_counts = Counter(s.instruction for episode in start for s in episode.segments)
    total = sum(start_counts.values())
    if total == 0:
        raise PlaysegError("balance_labels needs a start split with annotated segments")
    caps = {label: math.ceil(count * added.count / total) for label, count in start_counts.items()}
    ranked = sorted(
        (
            (episode_id, index, segment)
            for episode_id, group in added.by_episode.items()
            for index, segment in enumerate(group)
        ),
        key=lambda item: -item[2].confidence,
    )
    taken: Counter[str] = Counter()
    kept: set[tuple[str, int]] = set()
    for episode_id, index, segment in ranked:
        if taken[segment.instruction] < caps.get(segment.instruction, 0):
            taken[segment.instruction] += 1
            kept.add((episode_id, index))
    by_episode = {
        episode_id: [s for index, s in enumerate(group) if (episode_id, index) in kept]
        for episode_id, group in added.by_episode.items()
    }
    kept_groups = {e: group for e, group in by_episode.items() if group}
    return AddedSegments(condition, kept_groups, made_from=added.made_from)
