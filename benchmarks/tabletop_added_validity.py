"""What an augmentation condition adds from tabletop play, judged by the task oracle.

For each segment a condition of `playseg experiment tabletop` added (OUT/added/<condition>.json, or every
segment PS cut: OUT/found/ps.json), the play episode is replayed from its seed without rendering and the
oracle is asked whether the task its label names, given in the scene at the segment's start, is done at
its end ("valid": a correct demonstration of its label, whatever the operator was doing then). Prints,
for all of them, per labelled family, for the arm-labelled ones by the true task they lie in, and for
the most confident: count, oracle-valid share, share of steps labelled as the truth, exact true spans.

    .venv/bin/python benchmarks/tabletop_added_validity.py --out /tmp/tt-m6 --conditions ps,ps_own_cuts
"""

from __future__ import annotations

import argparse
from collections import Counter
from pathlib import Path

import numpy as np

from playseg_core.data.dataset import PlayDataset
from playseg_core.domains.tabletop import play
from playseg_core.domains.tabletop.instructions import FAMILIES, is_done, task_for
from playseg_core.domains.tabletop.robot_log import dataset_play_config
from playseg_core.experiment.conditions import AddedSegments


def judged_rows(config: play.PlayConfig, added: AddedSegments) -> list[dict]:
    rows = []
    for episode_id, segments in added.by_episode.items():
        scenes, truth = play.replay_scenes(config, episode_id)
        label = np.full(len(scenes) - 1, "", dtype=object)
        family = np.full(len(scenes) - 1, "(none)", dtype=object)
        for t in truth:
            label[t.start : t.end] = t.instruction
            family[t.start : t.end] = task_for(t.instruction).family
        spans = {(t.start, t.end, t.instruction) for t in truth}
        for s in segments:
            task = task_for(s.instruction)
            rows.append(
                {
                    "family": task.family,
                    "inside": Counter(family[s.start : s.end]).most_common(1)[0][0],
                    "valid": is_done(task, scenes[s.end], scenes[s.start]),
                    "hits": int(np.sum(label[s.start : s.end] == s.instruction)),
                    "steps": s.end - s.start,
                    "exact": (s.start, s.end, s.instruction) in spans,
                    "confidence": s.confidence,
                }
            )
    return rows


def summary(name: str, rows: list[dict]) -> None:
    if not rows:
        return
    steps = sum(r["steps"] for r in rows)
    print(
        f"  {name:40s} {len(rows):5d} segments  valid {np.mean([r['valid'] for r in rows]):.2f}  "
        f"steps right {sum(r['hits'] for r in rows) / steps:.3f}  exact {np.mean([r['exact'] for r in rows]):.2f}"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", required=True, help="a `playseg experiment tabletop` output directory")
    parser.add_argument("--conditions", default="ps", help="comma-separated; 'found' = every segment PS cut")
    args = parser.parse_args()
    out = Path(args.out)
    config = dataset_play_config(PlayDataset.open(out / "data"))
    for condition in args.conditions.split(","):
        path = out / "found" / "ps.json" if condition == "found" else out / "added" / f"{condition}.json"
        rows = judged_rows(config, AddedSegments.load(path))
        print(f"{condition} ({path}):")
        summary("all", rows)
        for family in FAMILIES:
            summary(f"labelled {family}", [r for r in rows if r["family"] == family])
        arm = [r for r in rows if r["family"] == "effector_to_region"]
        for family in [*FAMILIES, "(none)"]:
            summary(f"  arm-labelled, inside {family}", [r for r in arm if r["inside"] == family])
        ranked = sorted(rows, key=lambda r: -r["confidence"])
        for top in (25, 100):
            summary(f"top {top} by label confidence", ranked[:top])


if __name__ == "__main__":
    main()
