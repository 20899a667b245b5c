"""Tabletop play as standard-message robot bags (bags.py): camera, joint states, commands, timed
annotations, with the ground truth beside them. The tabletop domain's ROS side: it reads the domain's
spec and robot logs (playseg_core/domains/tabletop)."""

from __future__ import annotations

from pathlib import Path


def write_generated_bags(
    dataset_dir: str | Path, out_dir: str | Path, images: str = "raw", workers: int = 1
) -> list[str]:
    """The hook of `playseg generate --bag` (play_bags.write_generated_bags): a generated tabletop
    dataset as standard-message robot bags (bags.write_dataset_bags); one summary line per directory."""
    from playseg_ros.tabletop.bags import write_generated_bags as write

    return write(dataset_dir, out_dir, images=images, workers=workers)


__all__ = ["write_generated_bags"]
