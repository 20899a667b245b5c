"""`playseg convert --format lerobot`: the export checked against LeRobot v3.0's documented layout with
pyarrow and PyAV (frames, actions, per-frame instructions against what the bags hold)."""

from __future__ import annotations

import json
from pathlib import Path

import av
import numpy as np
import pyarrow.parquet as pq
import pytest
from test_convert import (
    HEIGHT,
    WIDTH,
    RobotBag,
    expected_steps,
    frame,
    joint_position,
    twist_values,
    write_mapping,
    write_rosbag2,
)

from playseg_ros.cli import main

FPS = 10


@pytest.fixture(scope="module")
def export(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, list[RobotBag]]:
    root = tmp_path_factory.mktemp("lerobot")
    specs = [RobotBag(seconds=3.0), RobotBag(seconds=1.0, labels=[])]
    write_rosbag2(root / "bags" / "a_labelled", specs[0])
    write_rosbag2(root / "bags" / "b_play", specs[1], "sqlite3")
    mapping = write_mapping(root / "map.yaml")
    args = ["convert", str(root / "bags"), "--out", str(root / "lerobot"), "--mapping", str(mapping)]
    assert main([*args, "--format", "lerobot", "--quiet"]) == 0
    return root / "lerobot", specs


def source_frames(specs: list[RobotBag]) -> list[tuple[int, int]]:
    """(episode, camera frame) of every LeRobot frame: each episode's steps but the last observation."""
    return [(e, i) for e, spec in enumerate(specs) for i in expected_steps(spec)[:-1]]


def test_info_json_declares_the_v3_layout(export: tuple[Path, list[RobotBag]]) -> None:
    root, specs = export
    info = json.loads((root / "meta/info.json").read_text())
    frames = len(source_frames(specs))
    assert info["codebase_version"] == "v3.0" and info["fps"] == FPS
    assert (info["total_episodes"], info["total_frames"], info["total_tasks"]) == (2, frames, 3)
    assert (info["chunks_size"], info["data_files_size_in_mb"], info["video_files_size_in_mb"]) == (
        1000,
        100,
        200,
    )
    assert info["data_path"] == "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"
    assert info["video_path"] == "videos/{video_key}/chunk-{chunk_index:03d}/file-{file_index:03d}.mp4"
    assert info["splits"] == {"train": "0:2"}
    features = info["features"]
    camera = features["observation.images.front"]
    assert camera["dtype"] == "video" and camera["shape"] == [HEIGHT, WIDTH, 3]
    assert camera["names"] == ["height", "width", "channels"]
    assert camera["info"]["video.codec"] == "h264" and camera["info"]["video.pix_fmt"] == "yuv420p"
    assert features["observation.state"] == {
        "dtype": "float32",
        "shape": [3],
        "names": ["shoulder", "elbow", "wrist"],
    }
    assert features["action"] == {
        "dtype": "float32",
        "shape": [3],
        "names": ["linear.x", "linear.y", "angular.z"],
    }
    for name, dtype in [("timestamp", "float32"), ("frame_index", "int64"), ("episode_index", "int64"),
                        ("index", "int64"), ("task_index", "int64")]:  # fmt: skip
        assert features[name] == {"dtype": dtype, "shape": [1], "names": None}
    assert features["language_persistent"] == {"dtype": "language", "shape": [1], "names": None}


def test_frames_states_actions_and_instructions_match_the_bags(export: tuple[Path, list[RobotBag]]) -> None:
    root, specs = export
    data = pq.read_table(root / "data/chunk-000/file-000.parquet").to_pydict()
    sources = source_frames(specs)
    n = len(sources)
    assert data["index"] == list(range(n))
    assert data["episode_index"] == [e for e, _ in sources]
    frame_index = [data["frame_index"][k] for k in range(n)]
    assert frame_index == [i // 3 for _, i in sources]
    np.testing.assert_array_equal(
        np.float32(data["timestamp"]), (np.array(frame_index) / FPS).astype(np.float32)
    )
    states = np.array(data["observation.state"], dtype=np.float32)
    np.testing.assert_array_equal(states, np.stack([joint_position(round(i * 10 / 3)) for _, i in sources]))
    actions = np.array(data["action"], dtype=np.float32)
    np.testing.assert_array_equal(actions, np.array([twist_values(i // 3) for _, i in sources], np.float32))
    # tasks.parquet is indexed by the task string (pandas metadata), as LeRobot reads it
    tasks_table = pq.read_table(root / "meta/tasks.parquet")
    assert json.loads(tasks_table.schema.metadata[b"pandas"])["index_columns"] == ["task"]
    tasks = dict(
        zip(tasks_table.column("task_index").to_pylist(), tasks_table.column("task").to_pylist(), strict=True)
    )
    frame_task = [tasks[t] for t in data["task_index"]]
    # bag a: labels [0.3, 1.2] s -> frames 3..11, [1.2, 2.5] s -> frames 12..24 (segment [12, 25))
    expected = [
        "pick up the cup" if 3 <= f < 12 else "put the cup down" if 12 <= f < 25 else ""
        for f in frame_index[:29]
    ]
    assert frame_task == expected + [""] * (n - 29)
    rows = data["language_persistent"][0]
    assert [(r["content"], round(r["timestamp"], 4), r["style"], r["role"]) for r in rows] == [
        ("pick up the cup", 0.3, "subtask", "assistant"),
        ("put the cup down", 1.2, "subtask", "assistant"),
        (None, 2.5, "subtask", "assistant"),  # unlabelled play follows: the subtask ends
    ]
    assert (
        all(data["language_persistent"][k] == rows for k in range(29))
        and data["language_persistent"][29] == []
    )


def test_episodes_table_and_videos_locate_every_frame(export: tuple[Path, list[RobotBag]]) -> None:
    root, specs = export
    episodes = pq.read_table(root / "meta/episodes/chunk-000/file-000.parquet").to_pylist()
    assert [e["episode_index"] for e in episodes] == [0, 1]
    assert [e["length"] for e in episodes] == [29, 9]
    assert [(e["dataset_from_index"], e["dataset_to_index"]) for e in episodes] == [(0, 29), (29, 38)]
    assert episodes[0]["tasks"] == ["", "pick up the cup", "put the cup down"] and episodes[1]["tasks"] == [
        ""
    ]
    key = "videos/observation.images.front"
    assert [(e[f"{key}/from_timestamp"], e[f"{key}/to_timestamp"]) for e in episodes] == [
        (0.0, 2.9),
        (2.9, 3.8),
    ]
    assert all(e["data/chunk_index"] == 0 and e["data/file_index"] == 0 for e in episodes)
    assert episodes[0]["stats/action/min"] == [0.0, 0.25, -28.0] and episodes[0]["stats/action/count"] == [29]
    with av.open(str(root / "videos/observation.images.front/chunk-000/file-000.mp4")) as container:
        stream = container.streams.video[0]
        decoded = [
            (float(f.pts * stream.time_base), f.to_ndarray(format="rgb24")) for f in container.decode(stream)
        ]
    sources = source_frames(specs)
    assert len(decoded) == len(sources)
    for k, ((timestamp, image), (_, i)) in enumerate(zip(decoded, sources, strict=True)):
        assert timestamp == pytest.approx(k / FPS, abs=1e-4)
        error = np.abs(image.astype(np.int16) - frame(i).astype(np.int16))
        # lossy h264 with 4:2:0 chroma: close everywhere, and the red channel (the frame number) tells
        # which frame it is
        assert error.mean() < 4.0, (k, error.mean())
        assert abs(float(image[..., 0].mean()) - i) < 2.0, (k, i)


def test_stats_json_has_every_feature(export: tuple[Path, list[RobotBag]]) -> None:
    root, _ = export
    stats = json.loads((root / "meta/stats.json").read_text())
    for name in (
        "observation.state",
        "action",
        "timestamp",
        "frame_index",
        "episode_index",
        "index",
        "task_index",
    ):
        assert set(stats[name]) == {
            "min",
            "max",
            "mean",
            "std",
            "count",
            "q01",
            "q10",
            "q50",
            "q90",
            "q99",
        }, name
    assert stats["action"]["min"] == [0.0, 0.25, -28.0] and stats["action"]["max"] == [28.0, 0.25, 0.0]
    assert stats["index"]["count"] == [38]
    camera = stats["observation.images.front"]
    assert (
        np.asarray(camera["mean"]).shape == (3, 1, 1)
        and 0.0 <= np.min(camera["min"]) <= np.max(camera["max"]) <= 1.0
    )


def test_a_rerun_keeps_the_export_and_a_foreign_directory_is_refused(
    export: tuple[Path, list[RobotBag]], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    root, _ = export
    before = (root / "meta/info.json").stat().st_mtime_ns
    bags, mapping = root.parent / "bags", root.parent / "map.yaml"
    args = [
        "convert",
        str(bags),
        "--out",
        str(root),
        "--mapping",
        str(mapping),
        "--format",
        "lerobot",
        "--quiet",
    ]
    assert main(args) == 0
    assert "2 skipped" in capsys.readouterr().out
    assert (root / "meta/info.json").stat().st_mtime_ns == before  # nothing new: not exported again
    (tmp_path / "other").mkdir()
    other = [
        "convert",
        str(bags),
        "--out",
        str(tmp_path / "other"),
        "--mapping",
        str(mapping),
        "--format",
        "lerobot",
    ]
    assert main(other) == 1
    assert "is not a LeRobot dataset" in capsys.readouterr().err
