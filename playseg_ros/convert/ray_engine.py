"""`playseg convert --engine ray`: the same per-bag function (run.convert_one) as Ray tasks, one CPU each.

Without ``--address`` a local Ray instance is started for the run (``--workers`` CPUs) and stopped after;
with ``--address`` (``ray://host:10001`` or ``host:6379``, or ``auto``) the run joins that cluster. Each
task writes its bag's part under ``.<OUT>.convert/`` and returns a `BagReport`; the driver merges the
parts exactly as the local engine does, so the dataset is the same. On a cluster the bags and the
directory of ``--out`` must be on storage every node sees at the same path (a shared filesystem).

Ray is imported only here, only when this engine is chosen.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Callable

from playseg_ros.convert.run import BagReport, BagTask, convert_one

OBJECT_STORE_BYTES = 128 * 1024 * 1024
"""A local instance's object store: tasks and reports are small (the frames go to disk, not through Ray)."""


def run_ray_tasks(
    tasks: list[BagTask], workers: int, address: str | None, on_done: Callable[[BagReport], None]
) -> list[BagReport]:
    """Convert each task's bag as a Ray task; ``on_done`` is called per finished bag (progress)."""
    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")  # no usage reporting, no prompt
    import ray

    started_here = not ray.is_initialized()
    if started_here:
        options: dict = {"include_dashboard": False, "logging_level": logging.WARNING}
        if address is None:  # a local instance for this run
            options |= {"num_cpus": workers, "object_store_memory": OBJECT_STORE_BYTES}
        ray.init(address=address, **options)
    try:
        remote = ray.remote(num_cpus=1, max_retries=0)(convert_one)
        pending = {remote.remote(task): task for task in tasks}
        reports: list[BagReport] = []
        while pending:
            (done,), _ = ray.wait(list(pending), num_returns=1)
            task = pending.pop(done)
            try:
                report = ray.get(done)
            except Exception as error:  # noqa: BLE001 -- a worker that died: its bag failed, the rest go on
                reason = " ".join(str(error).split())[:300]
                report = BagReport(
                    task.bag, "failed", error=f"bag {str(task.bag)!r}: ray task failed: {reason}"
                )
            reports.append(report)
            on_done(report)
        return reports
    finally:
        if started_here:
            ray.shutdown()
