"""Load playseg's LeRobot exports with the real ``lerobot`` reader and compare them with their source.

Run with the lerobot environment's Python (scripts/setup_lerobot_env.sh builds ~/.cache/playseg/lerobot-venv), on
directories written by scripts/lerobot_export.py (each holds ``lerobot/``, ``expected.npz``,
``expected.json``); ``make lerobot-check`` does all three:

    $(LEROBOT_VENV)/bin/python scripts/lerobot_check.py DIR [DIR ...]

Offline: HF_HUB_OFFLINE=1 and the dataset's ``root`` is given, so nothing is looked up on the Hub (the
script refuses to run without HF_HUB_OFFLINE). For every frame, through ``LeRobotDataset.__getitem__``:

- ``action`` and ``observation.state``: exactly the source's (float32, the same values)
- ``episode_index``, ``frame_index``, ``index``, ``timestamp`` (frame_index / fps): exact
- each camera, decoded by lerobot (its default backend, torchcodec here, and PyAV) at the frame's
  timestamp: h264 is lossy, so the decoded frame (uint8) must be within a mean absolute error of
  ``--max-mean-error`` (default 4.0 of 255, as tests/test_convert_lerobot.py) of the source frame and, to be sure it is the right frame
  and not a neighbour, closer to it than to a neighbouring source frame that differs from it by more than that
  limit, and closer to its own source than to a differing neighbour in at least 90% of comparisons
- the instruction, two ways: ``item["task"]`` (the frame's task from meta/tasks.parquet) is the
  source's active instruction, "" outside any segment; and lerobot's own resolver
  ``language_render.active_at(timestamp, persistent=item["language_persistent"], style="subtask")``
  gives a row whose ``content`` is that instruction, or none / null content outside any segment

and the metadata: total frames and episodes, each episode's length and tasks.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

# a decoded frame may be as close to a neighbour that differs from its source by less than the codec's
# error (a still scene); over all frames, it must be nearer its own source nearly always
MIN_NEAREST = 0.9


def check(directory: Path, backend: str | None, max_mean_error: float, stride: int) -> list[str]:
    from lerobot.datasets.language_render import active_at
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    expected = dict(np.load(directory / "expected.npz"))
    meta = json.loads((directory / "expected.json").read_text(encoding="utf-8"))
    fps, cameras, instructions = meta["fps"], meta["cameras"], meta["instructions"]
    n = meta["frames"]
    failures: list[str] = []

    def fail(message: str) -> None:
        if len(failures) < 20:
            failures.append(f"{directory.name}: {message}")

    t0 = time.perf_counter()
    dataset = LeRobotDataset(
        repo_id=f"playseg/{directory.name}", root=directory / "lerobot", video_backend=backend
    )
    print(
        f"{directory.name}: LeRobotDataset opened in {time.perf_counter() - t0:.1f} s "
        f"(codebase {dataset.meta.info.codebase_version}, video backend {dataset._video_backend}, "
        f"{dataset.num_episodes} episodes, {len(dataset)} frames, fps {dataset.fps})"
    )
    if len(dataset) != n or dataset.num_frames != n:
        fail(f"{len(dataset)} frames, expected {n}")
    episodes = int(expected["episode_index"].max()) + 1
    if dataset.num_episodes != episodes:
        fail(f"{dataset.num_episodes} episodes, expected {episodes}")
    if dataset.fps != fps:
        fail(f"fps {dataset.fps}, expected {fps}")
    for e in range(episodes):
        rows = expected["episode_index"] == e
        record = dataset.meta.episodes[e]
        want_tasks = {instructions[k] or "" for k in np.flatnonzero(rows)}
        if record["length"] != int(rows.sum()) or set(record["tasks"]) != want_tasks:
            fail(f"episode {e}: length {record['length']} tasks {record['tasks']}, expected "
                 f"{int(rows.sum())} {sorted(want_tasks)}")  # fmt: skip

    errors: dict[str, list[float]] = {camera: [] for camera in cameras}
    nearest: dict[str, list[bool]] = {camera: [] for camera in cameras}
    t0 = time.perf_counter()
    decoded = 0
    for k in range(min(len(dataset), n)):
        decode = k % stride == 0 or k == n - 1
        item = dataset[k] if decode or not cameras else dataset.reader.hf_dataset[k]
        ep, fi = int(expected["episode_index"][k]), int(expected["frame_index"][k])
        got = (int(item["episode_index"]), int(item["frame_index"]), int(item["index"]))
        if got != (ep, fi, k):
            fail(f"frame {k}: (episode, frame, index) {got}, expected {(ep, fi, k)}")
        timestamp = float(item["timestamp"])
        if timestamp != float(np.float32(fi / fps)):
            fail(f"frame {k}: timestamp {timestamp}, expected {fi / fps}")
        for name in ("action", "observation.state"):
            if name not in expected:
                continue
            value = np.asarray(item[name])
            if value.dtype != expected[name].dtype or not np.array_equal(value, expected[name][k]):
                fail(f"frame {k}: {name} {value!r}, expected {expected[name][k]!r}")
        want = instructions[k]
        task = item.get("task", dataset.meta.tasks.iloc[int(item["task_index"])].name)
        if task != (want or ""):
            fail(f"frame {k}: task {task!r}, expected {want or ''!r}")
        row = active_at(timestamp, persistent=item["language_persistent"], style="subtask")
        content = None if row is None else row["content"]
        if content != want:
            fail(f"frame {k}: active subtask {content!r}, expected {want!r}")
        if not decode:
            continue
        decoded += 1
        for camera in cameras:
            image = item[camera]  # (C, H, W) float32 in [0, 1]
            hwc = np.round(np.asarray(image).transpose(1, 2, 0) * 255.0).astype(np.int16)
            source = expected[camera].astype(np.int16)
            if hwc.shape != source[k].shape:
                fail(f"frame {k}: {camera} shape {hwc.shape}, expected {source[k].shape}")
                continue
            error = float(np.abs(hwc - source[k]).mean())
            errors[camera].append(error)
            if error > max_mean_error:
                fail(f"frame {k}: {camera} mean abs error {error:.2f} > {max_mean_error}")
            for j in (k - 1, k + 1):
                if 0 <= j < n and expected["episode_index"][j] == ep and np.any(source[j] != source[k]):
                    other = float(np.abs(hwc - source[j]).mean())
                    nearest[camera].append(error < other)
                    if other <= error and np.abs(source[j] - source[k]).mean() > max_mean_error:
                        fail(
                            f"frame {k}: {camera} is closer to source frame {j} ({other:.2f} <= {error:.2f})"
                        )
    elapsed = time.perf_counter() - t0
    for camera, values in errors.items():
        if values:
            print(
                f"{directory.name}: {camera}: {len(values)} frames decoded, mean abs error (0-255) "
                f"mean {np.mean(values):.2f}, max {np.max(values):.2f} (limit {max_mean_error}); nearer to "
                f"its own source frame than to a differing neighbour in {np.mean(nearest[camera]):.1%} of "
                f"{len(nearest[camera])} comparisons (at least {MIN_NEAREST:.0%})"
            )
            if nearest[camera] and np.mean(nearest[camera]) < MIN_NEAREST:
                fail(f"{camera}: decoded frames nearest their own source in {np.mean(nearest[camera]):.1%}")
    print(f"{directory.name}: {n} frames compared ({decoded} with video) in {elapsed:.1f} s")

    # as a policy trains on it: windows of actions and past frames (delta_timestamps), in batches
    from lerobot.utils.collate import lerobot_collate_fn
    from torch.utils.data import DataLoader

    deltas = [-1, 0, 1, 2]
    windows = LeRobotDataset(
        repo_id=f"playseg/{directory.name}",
        root=directory / "lerobot",
        video_backend=backend,
        delta_timestamps={"action": [d / fps for d in deltas], **{c: [-1 / fps, 0.0] for c in cameras}},
    )
    loader = DataLoader(windows, batch_size=8, shuffle=False, collate_fn=lerobot_collate_fn)
    for b, batch in enumerate(loader):
        if b >= 3:
            break
        for i in range(len(batch["index"])):
            k = int(batch["index"][i])
            ep = expected["episode_index"][k]
            for j, d in enumerate(deltas):
                q = min(max(k + d, 0), n - 1)
                inside = expected["episode_index"][q] == ep and q == k + d
                if bool(batch["action_is_pad"][i][j]) == inside:
                    fail(f"frame {k}: action window {d}: is_pad {bool(batch['action_is_pad'][i][j])}")
                if inside and not np.array_equal(np.asarray(batch["action"][i][j]), expected["action"][q]):
                    fail(f"frame {k}: action window {d}: {np.asarray(batch['action'][i][j])}")
            for camera in cameras:
                shape = tuple(batch[camera][i].shape)
                if shape != (2, 3, *expected[camera].shape[1:3]):
                    fail(f"frame {k}: {camera} window shape {shape}")
        want = [instructions[int(k)] or "" for k in batch["index"]]
        if list(batch["task"]) != want:
            fail(f"batch {b}: tasks {batch['task']}, expected {want}")
    print(f"{directory.name}: windows (delta_timestamps) and DataLoader batches with lerobot_collate_fn read")
    return failures


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("dirs", type=Path, nargs="+")
    parser.add_argument("--backends", default="",
                        help="video backends to read with, comma-separated (default: lerobot's default, "
                             "torchcodec when it loads, and pyav)")  # fmt: skip
    parser.add_argument("--max-mean-error", type=float, default=4.0)
    parser.add_argument("--stride", type=int, default=1, help="decode video for every STRIDE-th frame")
    args = parser.parse_args(argv)
    if os.environ.get("HF_HUB_OFFLINE") != "1":
        print("set HF_HUB_OFFLINE=1: the check reads local exports only", file=sys.stderr)
        return 2
    import lerobot
    import torch

    print(f"lerobot {lerobot.__version__}, torch {torch.__version__}, Python {sys.version.split()[0]}")
    from lerobot.datasets.video_utils import get_safe_default_video_backend

    default = get_safe_default_video_backend()
    backends = args.backends.split(",") if args.backends else sorted({default, "pyav"})
    print(f"video backends: {', '.join(backends)} (lerobot's default here: {default})")
    failures = []
    for backend in backends:
        for directory in args.dirs:
            failures += check(directory.resolve(), backend, args.max_mean_error, args.stride)
    for line in failures:
        print("FAIL", line, file=sys.stderr)
    print("lerobot check:", "FAILED" if failures else "OK")
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
