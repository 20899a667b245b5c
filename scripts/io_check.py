"""`make io-check`: the ROS-free I/O part of playseg, installed alone (scripts/setup_io_env.sh), reads,
recovers and converts the sample robot bags.

Run with the I/O environment's interpreter: python scripts/io_check.py REPO_ROOT WORK_DIR. It checks that
rclpy, playseg_msgs and torch are not importable there, that playseg comes from that environment (not
the work tree), then runs the installed `playseg` on a copy of bags/tabletop: `bag info`, `bag recover`
of a cut-short copy, `convert` into a playseg dataset (opened with PlayDataset) and into LeRobot v3
(its tables read with pyarrow, a video frame decoded with PyAV), and a torch-needing command, which must
fail with one line naming what is missing.
"""

from __future__ import annotations

import importlib.util
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

NOT_INSTALLED = ("rclpy", "playseg_msgs", "torch")


def run(playseg: Path, *args: str, expect: int = 0) -> str:
    done = subprocess.run([str(playseg), *args], capture_output=True, text=True)
    shown = " ".join(["playseg", *args])
    if done.returncode != expect:
        raise SystemExit(
            f"io-check: `{shown}` exited {done.returncode}, not {expect}:\n{done.stdout}{done.stderr}"
        )
    print(f"ok   {shown}")
    return done.stdout + done.stderr


def main(root: Path, work: Path) -> None:
    for name in NOT_INSTALLED:
        if importlib.util.find_spec(name) is not None:
            raise SystemExit(f"io-check: {name} is importable in {sys.prefix}: not the I/O part alone")
    print(f"ok   {', '.join(NOT_INSTALLED)} not importable in {sys.prefix}")
    import playseg_ros

    if not Path(playseg_ros.__file__).resolve().is_relative_to(Path(sys.prefix).resolve()):
        raise SystemExit(f"io-check: playseg_ros comes from {playseg_ros.__file__}, not {sys.prefix}")
    playseg = Path(sys.prefix) / "bin" / "playseg"

    shutil.rmtree(work, ignore_errors=True)
    bags = work / "tabletop"
    shutil.copytree(root / "bags" / "tabletop", bags)
    sources = sorted(str(path) for path in bags.glob("tabletop-*"))

    info = run(playseg, "bag", "info", sources[0])
    assert "topics:" in info and "/camera/image_raw/compressed" in info, info

    cut = work / "cut"
    shutil.copytree(sources[0], cut)
    (mcap,) = cut.glob("*.mcap")
    os.truncate(mcap, mcap.stat().st_size * 7 // 10)
    run(playseg, "bag", "recover", str(cut))
    assert "messages:" in run(playseg, "bag", "info", str(cut))

    mapping = str(bags / "mapping.yaml")
    run(playseg, "convert", *sources, "--mapping", mapping, "--out", str(work / "dataset"), "--quiet")
    from playseg_core.data.dataset import PlayDataset

    dataset = PlayDataset.open(work / "dataset")
    assert len(dataset) == len(sources), len(dataset)
    assert len(dataset.array("action")) > 0
    print(f"ok   dataset opens: {len(dataset)} episodes, {len(dataset.array('action'))} steps")

    lerobot = work / "lerobot"
    run(
        playseg,
        "convert",
        *sources,
        "--mapping",
        mapping,
        "--out",
        str(lerobot),
        "--format",
        "lerobot",
        "--quiet",
    )
    import av
    import pyarrow.parquet as pq

    meta = json.loads((lerobot / "meta" / "info.json").read_text())
    rows = sum(pq.read_table(path).num_rows for path in (lerobot / "data").rglob("*.parquet"))
    assert meta["total_episodes"] == len(sources) and rows == meta["total_frames"] > 0, (meta, rows)
    video = next((lerobot / "videos").rglob("*.mp4"))
    with av.open(str(video)) as container:
        frame = next(container.decode(video=0))
    print(f"ok   LeRobot export opens: {rows} frames, {video.name} decodes ({frame.width}x{frame.height})")

    # a command that needs the full install: one line saying what is missing, no traceback
    message = run(playseg, "convert", sources[0], "--mapping", mapping, "--out", str(work / "segmented"),
                  "--segment", str(root / "bags" / "models" / "tabletop-ps.pt"), expect=1)  # fmt: skip
    assert len(message.splitlines()) == 1 and "needs " in message, message
    print(f"     {message.strip()}")
    print("io-check passed")


if __name__ == "__main__":
    main(Path(sys.argv[1]), Path(sys.argv[2]))
