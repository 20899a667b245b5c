"""The policy interface augmentation trains through: train on segment clips, act, evaluate, save, load.

A `PolicyLearner` is one policy family: a generic one for any domain's data or one of a domain
(policies.py finds them by name). The trainer node and `AugmentationTrainer` know only this interface.
A learner without a simulator returns no evaluation.
"""

from __future__ import annotations

import contextlib
import threading
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Generic, Protocol, TypeVar

import numpy as np
import torch

from playseg_core.data.episode import SegmentClip
from playseg_core.data.features import Features
from playseg_core.errors import PlaysegError


@dataclass
class PolicyTrainReport:
    """What one training run of a policy did."""

    steps: int
    seconds: float
    num_segments: int
    final_loss: float
    losses: list[tuple[int, float]] = field(default_factory=list)  # (step, mean loss since the last entry)
    # On held-out clips, when the learner holds some out (None otherwise): its loss, its accuracy (a
    # discrete action), and the loss of predicting the training clips' mean action (marginal frequencies).
    num_val_segments: int = 0
    val_loss: float | None = None
    val_accuracy: float | None = None
    baseline_val_loss: float | None = None
    # how often the instruction's first attention query scores best the entity that moves most over its
    # segment, over held-out samples (steps) whose segment moves one (the `bc` policy's moved-entity
    # loss), None without it
    val_moved_entity_accuracy: float | None = None
    # the same for the second query and the entity the moved one ends nearest to (related-entity loss)
    val_related_entity_accuracy: float | None = None


@dataclass
class PolicyEvaluation:
    """Task success of a policy on fixed, seeded episodes of the domain's simulator."""

    success_rate: float
    num_episodes: int
    num_successes: int
    seed: int
    seconds: float
    episode_success: list[bool] = field(default_factory=list)
    episode_instructions: list[str] = field(default_factory=list)  # what episode k asked for


def success_difference_noise(before: Sequence[bool], after: Sequence[bool], seed_std: float = 0.0) -> float:
    """One standard error of the change in success from ``before`` to ``after``, two evaluations of the
    same fixed episodes (episode k of each is the same task): the paired standard error of the
    per-episode differences, combined with the spread that retraining with another seed gives each
    policy (``seed_std``, the std of one run's success over training seeds; 0 when not known)."""
    if len(before) != len(after) or len(before) == 0:
        raise PlaysegError(f"need two evaluations of the same episodes, got {len(before)} and {len(after)}")
    differences = np.asarray(after, np.float64) - np.asarray(before, np.float64)
    paired = differences.std(ddof=1) / np.sqrt(len(differences)) if len(differences) > 1 else 0.0
    return float(np.sqrt(paired**2 + 2.0 * seed_std**2))


def describe_success_change(before: Sequence[bool], after: Sequence[bool], seed_std: float = 0.0) -> str:
    """A policy's success before -> after on the same episodes, and whether the change is beyond two
    standard errors (`success_difference_noise`)."""
    noise = success_difference_noise(before, after, seed_std)
    rate_before, rate_after = float(np.mean(before)), float(np.mean(after))
    change = rate_after - rate_before
    if abs(change) <= 2.0 * noise:
        verdict = "no measurable change at this scale (within 2 standard errors)"
    else:
        verdict = "a gain beyond 2 standard errors" if change > 0 else "a drop beyond 2 standard errors"
    return f"{rate_before:.3f} -> {rate_after:.3f} ({change:+.3f}; one standard error {noise:.3f}: {verdict})"


class InstructionPolicy(Protocol):
    """An instruction-following policy: a batch of observations and instructions -> a batch of actions."""

    def act(self, observations: Mapping[str, np.ndarray], instructions: Sequence[str]) -> np.ndarray: ...


class PolicyLearner(Protocol):
    """How one policy family trains, evaluates, saves and loads.

    name: ``<domain>.<policy>``, recorded in its checkpoints.
    features: the data features it reads (a clip must hold them; a base dataset must declare them).
    """

    name: str

    @property
    def features(self) -> Features: ...

    def train(
        self, clips: Sequence[SegmentClip], progress: bool = False
    ) -> tuple[Any, PolicyTrainReport]: ...

    def evaluate(self, policy: Any, num_episodes: int, seed: int) -> PolicyEvaluation | None: ...

    def save(self, path: Path, policy: Any, meta: dict[str, Any]) -> None: ...

    def load(self, path: Path) -> tuple[Any, dict[str, Any]]: ...


T = TypeVar("T")


class SequentialDraws(Generic[T]):
    """Step ``s``'s batch of a run that draws every step's batch from one numpy generator seeded with
    ``seed``, in step order, as a function of ``s`` alone (the training loop's `TrainingTask.batch_at`).

    ``draw(rng, step)`` makes a step's batch from the generator. Asked for the steps in order (the loop
    does, prefetching included: one worker, in order), each step costs one draw and the batches are those
    of a plain ``for`` loop over one generator, so runs give the weights they always gave. Asked for a
    later step (a resumed run starts there), the skipped steps are drawn first, with ``skip(rng, step)``
    when given (the same generator calls without building the batch) or ``draw``; asked for an earlier
    one, it starts again from the seed. So a resumed run gets the very batches the uninterrupted one got,
    at the cost of replaying the draws of the steps before it.
    """

    def __init__(
        self,
        seed: int,
        draw: Callable[[np.random.Generator, int], T],
        skip: Callable[[np.random.Generator, int], object] | None = None,
    ) -> None:
        self._seed, self._draw, self._skip = seed, draw, skip or draw
        self._rng = np.random.default_rng(seed)
        self._next = 0  # the step the generator is at
        self._lock = threading.Lock()  # a prefetching loop asks from its worker thread

    def __call__(self, step: int) -> T:
        with self._lock:
            if step < self._next:
                self._rng, self._next = np.random.default_rng(self._seed), 0
            while self._next < step:
                self._skip(self._rng, self._next)
                self._next += 1
            batch = self._draw(self._rng, step)
            self._next = step + 1
            return batch


@contextlib.contextmanager
def torch_threads(num_threads: int) -> Iterator[None]:
    """Train or act on ``num_threads`` torch CPU threads, restoring the previous setting afterwards (more
    threads than free cores make a shared machine crawl)."""
    previous = torch.get_num_threads()
    torch.set_num_threads(num_threads)
    try:
        yield
    finally:
        torch.set_num_threads(previous)
