"""Splits of a play corpus by episode: annotated ``train``/``val``, unannotated ``play``, held-out ``test``.

Episodes fill the splits in order (test, then annotated, then play) until each holds its segment target,
so no episode is in two splits.
"""

from __future__ import annotations

import hashlib
import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

from playseg_core.errors import PlaysegError

SPLITS: tuple[str, ...] = ("train", "val", "play", "test")
ANNOTATED_SPLITS: tuple[str, ...] = ("train", "val")
"""Splits whose episodes come with their segments; ``play`` and ``test`` hide them unless truth=True."""


@dataclass(frozen=True)
class SplitTargets:
    """How many segments each split should hold; episodes fill test, then annotated, then play.

    A split takes whole episodes until it holds at least its target, so it may exceed the target by
    less than one episode. Annotated episodes go to ``val`` in a share of ``val_fraction`` (by episode,
    spread evenly) and to ``train`` otherwise.
    """

    test_segments: int
    annotated_segments: int
    play_segments: int
    val_fraction: float = 0.2

    def __post_init__(self) -> None:
        if min(self.test_segments, self.annotated_segments, self.play_segments) < 0:
            raise PlaysegError("SplitTargets: segment targets must be >= 0")
        if not 0.0 <= self.val_fraction < 1.0:
            raise PlaysegError(f"SplitTargets.val_fraction must be in [0, 1), got {self.val_fraction}")

    @classmethod
    def from_share(
        cls, total_segments: int, annotated_share: float, test_segments: int, val_fraction: float = 0.2
    ) -> SplitTargets:
        """``annotated_share`` of ``total_segments`` annotated (train+val), the rest play."""
        if not 0.0 < annotated_share <= 1.0:
            raise PlaysegError(f"annotated_share must be in (0, 1], got {annotated_share}")
        annotated = round(total_segments * annotated_share)
        return cls(test_segments, annotated, total_segments - annotated, val_fraction)

    @property
    def total_segments(self) -> int:
        return self.test_segments + self.annotated_segments + self.play_segments


class SplitAssigner:
    """Assigns a stream of episodes (by their segment counts) to splits, in order, without leakage."""

    def __init__(self, targets: SplitTargets) -> None:
        self.targets = targets
        self.segments = {name: 0 for name in SPLITS}
        self._annotated_episodes = 0

    @property
    def done(self) -> bool:
        return self._next_group() is None

    def _next_group(self) -> str | None:
        if self.segments["test"] < self.targets.test_segments:
            return "test"
        if self.segments["train"] + self.segments["val"] < self.targets.annotated_segments:
            return "annotated"
        if self.segments["play"] < self.targets.play_segments:
            return "play"
        return None

    def assign(self, num_segments: int) -> str | None:
        """The split of the next episode, or None once every target is met."""
        group = self._next_group()
        if group == "annotated":
            k = self._annotated_episodes
            fraction = self.targets.val_fraction
            group = "val" if int((k + 1) * fraction) > int(k * fraction) else "train"
            self._annotated_episodes += 1
        if group is not None:
            self.segments[group] += num_segments
        return group


def assign_splits(segment_counts: Sequence[int], targets: SplitTargets) -> list[str | None]:
    """Split of each episode given its segment count (None: not needed to meet the targets)."""
    assigner = SplitAssigner(targets)
    return [assigner.assign(count) for count in segment_counts]


DEFAULT_VAL_SHARE = 0.2
"""Share of the annotated episodes held out for validation when a dataset has no ``val`` split."""


def episode_rank(episode_id: str) -> int:
    """A stable pseudo-random rank of an episode id (the same on every machine and every run), so the
    episodes held out do not depend on the order they were read in."""
    return int.from_bytes(hashlib.blake2b(episode_id.encode(), digest_size=8).digest(), "big")


def held_out_ids(episode_ids: Iterable[str], share: float = DEFAULT_VAL_SHARE) -> set[str]:
    """The annotated episodes to hold out for validation: ``share`` of them (rounded up, at least one),
    the lowest by `episode_rank`; none when fewer than two (one episode cannot be both trained on and
    held out) or ``share`` is 0."""
    if not 0.0 <= share < 1.0:
        raise PlaysegError(f"val share must be in [0, 1), got {share}")
    ids = sorted(set(episode_ids), key=lambda episode_id: (episode_rank(episode_id), episode_id))
    if len(ids) < 2 or share == 0.0:
        return set()
    count = min(len(ids) - 1, max(1, math.ceil(share * len(ids))))
    return set(ids[:count])


def annotated_splits(episode_ids: Iterable[str], share: float = DEFAULT_VAL_SHARE) -> dict[str, str]:
    """``train`` or ``val`` for each annotated episode id: `held_out_ids` go to ``val``, the rest to
    ``train``. A function of the set of ids alone (not their order), so a dataset written in parts
    splits the same however its episodes were gathered."""
    ids = set(episode_ids)
    held = held_out_ids(ids, share)
    return {episode_id: "val" if episode_id in held else "train" for episode_id in ids}
