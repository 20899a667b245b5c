"""`playseg segment --engine ray`: episodes segmented by Ray actors, each holding the checkpoint once.

The driver reads the episodes (a bag is read once, in order) and hands each to an actor, which calls
the same ``Segmenter.segment`` the local engine calls; results come back in input order, so the output
equals the local engine's. At most two episodes per actor are in flight, which bounds the memory the
object store holds. Ray starts or joins as playseg_ros/ray_session.py says.
"""

from __future__ import annotations

import re
from collections import deque
from collections.abc import Iterable, Iterator
from dataclasses import replace
from pathlib import Path
from typing import Any

from playseg_core.baselines.common import SegmentOptions
from playseg_core.data.episode import Episode, Segment
from playseg_core.errors import PlaysegError
from playseg_ros.ray_session import ray_session

ANSI_ESCAPE = re.compile(r"\x1b\[[0-9;]*m")
"""Colour codes in Ray's error texts."""

IN_FLIGHT_PER_ACTOR = 2
"""Episodes queued per actor: one running and one waiting keeps every actor busy."""


class EpisodeSegmenter:
    """A Ray actor's state: the segmenter of ``method`` loaded from ``model_path``."""

    def __init__(self, method: str, model_path: str, options: SegmentOptions) -> None:
        from playseg_core.baselines.registry import load_segmenter

        self.segmenter = load_segmenter(method, model_path, options)

    def segment(self, episode: Episode) -> list[Segment]:
        return self.segmenter.segment(episode)


def segment_on_ray(
    episodes: Iterable[Episode],
    method: str,
    model_path: str | Path,
    options: SegmentOptions,
    workers: int,
    address: str | None,
) -> Iterator[tuple[Episode, list[Segment]]]:
    """Each episode with its segments, in input order, segmented by ``workers`` actors (one CPU each, and
    a share of a GPU when ``options.device`` is CUDA: Ray hides the GPUs from actors that ask for none).
    An error raised while segmenting is raised here as the error it was (the local engine's one line); an
    actor that dies (its checkpoint unreadable on its node, the node lost) is a PlaysegError naming the
    episode."""
    path = str(Path(model_path).resolve())  # a cluster's nodes read it at the same path (shared storage)
    cuda = options.device.startswith("cuda")
    if cuda:  # each actor sees the GPU share Ray gives it as its only device
        options = replace(options, device="cuda")
    with ray_session(workers, address) as ray:
        if cuda and ray.cluster_resources().get("GPU", 0) < 1:
            raise PlaysegError(f"--device {options.device}: the Ray cluster has no GPU for the actors")
        actor_class = ray.remote(num_cpus=1, num_gpus=1 / workers if cuda else 0, max_restarts=0)(
            EpisodeSegmenter
        )
        actors = [actor_class.remote(method, path, options) for _ in range(workers)]
        pending: deque[tuple[Episode, Any]] = deque()

        def result(episode: Episode, ref: Any) -> tuple[Episode, list[Segment]]:
            try:
                return episode, ray.get(ref)
            except ray.exceptions.RayTaskError as error:  # segmenting raised: that error, as locally
                cause = getattr(error, "cause", None)
                raise (cause if isinstance(cause, Exception) else error) from None
            except ray.exceptions.RayActorError as error:  # the actor died (its checkpoint, its node)
                lines = [ANSI_ESCAPE.sub("", line).strip() for line in str(error).splitlines()]
                reason = [line for line in lines if line][-1:] or [type(error).__name__]  # the cause: last
                raise PlaysegError(
                    f"episode {episode.episode_id!r}: Ray actor failed: {reason[:300]}"
                ) from None

        for number, episode in enumerate(episodes):
            pending.append((episode, actors[number % workers].segment.remote(episode)))
            if len(pending) >= IN_FLIGHT_PER_ACTOR * workers:
                yield result(*pending.popleft())
        while pending:
            yield result(*pending.popleft())
