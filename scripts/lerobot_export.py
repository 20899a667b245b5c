"""Make a LeRobot export for scripts/lerobot_check.py (run with playseg's .venv).

Two exports with ``playseg convert --format lerobot``, each into ``OUT/<name>/lerobot``:

    tabletop    the tabletop robot bags (bags/tabletop: JPEG CompressedImage camera 10 Hz, JointState
                50 Hz, Twist command, TimedAnnotation instructions on one bag, none on the other)
    synthetic   tests/test_convert.py's robot bags (rosbag2 MCAP and sqlite3): a labelled bag whose
                segments leave unlabelled play before and after them (a null ``language_persistent``
                row ends the last one) and an unlabelled bag

and next to each, what each LeRobot frame must hold, read back from the playseg dataset the converter
keeps next to the export (``.lerobot.playseg``, convert/run.py ``playseg_copy``):

    OUT/<name>/expected.npz    episode_index, frame_index, action, observation.state, and per camera the
                               frames as the playseg dataset holds them (uint8 HWC), in LeRobot frame order
    OUT/<name>/expected.json   fps, cameras, and each frame's instruction (null outside any segment)

Frame t of an episode is (o_t, a_t) for t < T (the episode's last observation has no action), as
docs/convert.md says; the instructions come from the episode's segments, not from the export.

    .venv/bin/python scripts/lerobot_export.py OUT
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from pathlib import Path

import numpy as np

from playseg_core.data.dataset import PlayDataset
from playseg_ros.cli import main as playseg_main
from playseg_ros.convert.run import playseg_copy

ROOT = Path(__file__).resolve().parent.parent
TABLETOP = ROOT / "bags" / "tabletop"


def expected_frames(dataset: PlayDataset) -> tuple[dict[str, np.ndarray], list[str | None]]:
    """Every LeRobot frame's source values, in export order (episodes with no action are left out)."""
    cameras = list(dataset.features.cameras)
    columns: dict[str, list[np.ndarray]] = {
        name: [] for name in ("episode_index", "frame_index", "action", "observation.state", *cameras)
    }
    instructions: list[str | None] = []
    episode_index = 0
    for index in range(len(dataset)):
        episode = dataset.episode(index, truth=True)
        t = episode.num_steps
        if t == 0:
            continue
        columns["episode_index"].append(np.full(t, episode_index, dtype=np.int64))
        columns["frame_index"].append(np.arange(t, dtype=np.int64))
        columns["action"].append(np.asarray(episode.actions).reshape(t, -1))
        if episode.state is not None:
            columns["observation.state"].append(np.asarray(episode.state)[:t].reshape(t, -1))
        for camera in cameras:
            columns[camera].append(np.asarray(episode.images[camera])[:t])
        active: list[str | None] = [None] * t
        for segment in episode.segments:
            for k in range(segment.start, min(segment.end, t)):
                active[k] = segment.instruction or None
        instructions += active
        episode_index += 1
    return {name: np.concatenate(parts) for name, parts in columns.items() if parts}, instructions


def synthetic_bags(where: Path) -> tuple[list[Path], Path]:
    """tests/test_convert_lerobot.py's two bags and mapping."""
    sys.path.insert(0, str(ROOT / "tests"))
    from test_convert import RobotBag, write_mapping, write_rosbag2

    write_rosbag2(where / "a_labelled", RobotBag(seconds=3.0))
    write_rosbag2(where / "b_play", RobotBag(seconds=1.0, labels=[]), "sqlite3")
    return [where / "a_labelled", where / "b_play"], write_mapping(where / "map.yaml")


def export(out: Path, bags: list[Path], mapping: Path) -> int:
    lerobot = out / "lerobot"
    shutil.rmtree(lerobot, ignore_errors=True)
    shutil.rmtree(playseg_copy(lerobot), ignore_errors=True)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    command = ["convert", *map(str, bags), "--out", str(lerobot), "--mapping", str(mapping)]
    code = playseg_main([*command, "--format", "lerobot", "--quiet"])
    if code != 0:
        print(f"playseg convert failed ({code})", file=sys.stderr)
        return code
    dataset = PlayDataset.open(playseg_copy(lerobot))
    arrays, instructions = expected_frames(dataset)
    np.savez(out / "expected.npz", **arrays)
    meta = {
        "fps": dataset.features.fps,
        "cameras": list(dataset.features.cameras),
        "frames": len(instructions),
        "instructions": instructions,
    }
    (out / "expected.json").write_text(json.dumps(meta) + "\n", encoding="utf-8")
    labelled = sum(i is not None for i in instructions)
    print(
        f"exported {lerobot} in {time.perf_counter() - t0:.1f} s: {int(arrays['episode_index'].max()) + 1} "
        f"episodes, {len(instructions)} frames ({labelled} inside a segment, "
        f"{len(set(instructions) - {None})} instructions), cameras {meta['cameras']}"
    )
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("out", type=Path, help="a directory (its tabletop/ and synthetic/ are replaced)")
    out: Path = parser.parse_args(argv).out.resolve()
    code = export(out / "tabletop", sorted(TABLETOP.glob("tabletop-*")), TABLETOP / "mapping.yaml")
    if code == 0:
        shutil.rmtree(out / "synthetic-bags", ignore_errors=True)
        bags, mapping = synthetic_bags(out / "synthetic-bags")
        code = export(out / "synthetic", bags, mapping)
    return code


if __name__ == "__main__":
    sys.exit(main())
