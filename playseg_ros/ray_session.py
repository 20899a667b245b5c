"""Ray for the commands that offer ``--engine ray``: a local instance for one run, or a cluster to join.

Without an address a local instance is started with ``workers`` CPUs and stopped when the run ends; with
one (``ray://host:10001``, ``host:6379`` or ``auto``) the run joins that cluster and leaves it running.
Ray is imported only here, only when the engine is chosen.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

OBJECT_STORE_BYTES = 128 * 1024 * 1024
"""A local instance's object store: big enough for a few episodes in flight; frames written by tasks go
to disk, not through Ray."""


@contextmanager
def ray_session(workers: int, address: str | None) -> Iterator[Any]:
    """The ``ray`` module, initialised for the run (a local instance or ``address``'s cluster)."""
    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")  # no usage reporting, no prompt
    import ray

    started_here = not ray.is_initialized()
    if started_here:
        options: dict[str, Any] = {"include_dashboard": False, "logging_level": logging.WARNING}
        if address is None:
            options |= {"num_cpus": workers, "object_store_memory": OBJECT_STORE_BYTES}
        ray.init(address=address, **options)
    try:
        yield ray
    finally:
        if started_here:
            ray.shutdown()
