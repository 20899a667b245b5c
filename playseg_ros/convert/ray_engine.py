"""`playseg convert --engine ray`: the same per-bag function (run.convert_one) as Ray tasks, one CPU each.

Ray starts or joins as playseg_ros/ray_session.py says (``--workers`` CPUs, or ``--address``). Each
task writes its bag's part under ``.<OUT>.convert/`` and returns a `BagReport`; the driver merges the
parts exactly as the local engine does, so the dataset is the same. On a cluster the bags and the
directory of ``--out`` must be on storage every node sees at the same path (a shared filesystem).

run.py imports this module, and so Ray, only when this engine is chosen.
"""

from __future__ import annotations

from collections.abc import Callable

from playseg_ros.convert.run import BagReport, BagTask, convert_one
from playseg_ros.ray_session import ray_session


def run_ray_tasks(
    tasks: list[BagTask], workers: int, address: str | None, on_done: Callable[[BagReport], None]
) -> list[BagReport]:
    """Convert each task's bag as a Ray task; ``on_done`` is called per finished bag (progress)."""
    with ray_session(workers, address) as ray:
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
