"""`playseg convert --engine ray`: the bags as Ray tasks on a local Ray instance give the same dataset files,
byte for byte, as the local engine (a bad bag fails alone in both; --segment runs inside the tasks)."""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

import pytest
from test_convert import RobotBag, write_mapping, write_rosbag2
from test_convert_segment import untrained_model

from playseg_core.data.dataset import PlayDataset
from playseg_ros.cli import main


def files_of(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


@pytest.mark.slow
def test_ray_engine_writes_the_same_dataset_as_the_local_engine(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    bags = tmp_path / "bags"
    write_rosbag2(bags / "a", RobotBag(seconds=2.0, labels=[]))
    write_rosbag2(bags / "b", RobotBag(seconds=3.0), "sqlite3")
    write_rosbag2(bags / "c", RobotBag(seconds=1.5, labels=[], joint_gap=(0.5, 0.8)))
    truncated = write_rosbag2(bags / "d_truncated", RobotBag(seconds=1.0))
    (mcap,) = truncated.glob("*.mcap")
    mcap.write_bytes(mcap.read_bytes()[: mcap.stat().st_size // 2])
    mapping = write_mapping(tmp_path / "map.yaml")
    common = [str(bags), "--mapping", str(mapping), "--workers", "2", "--quiet"]
    assert main(["convert", str(bags / "a"), "--out", str(tmp_path / "plain"), *common[1:]]) == 0
    plain = PlayDataset.open(tmp_path / "plain")
    model = untrained_model(tmp_path / "ps.pt", plain.features, plain.episode(0), threshold=0.3)
    common += ["--segment", str(model)]

    seconds = {}
    for engine in ("local", "ray"):
        began = time.perf_counter()
        code = main(["convert", *common, "--out", str(tmp_path / engine), "--engine", engine])
        seconds[engine] = time.perf_counter() - began
        captured = capsys.readouterr()
        assert code == 1, captured.err  # the truncated bag
        failures = [line for line in captured.err.splitlines() if "failed:" in line]
        assert len(failures) == 1 and "d_truncated" in failures[0] and "truncated" in failures[0], (
            captured.err
        )
        assert "3 converted" in captured.out and "1 failed" in captured.out
    local, ray = files_of(tmp_path / "local"), files_of(tmp_path / "ray")
    assert sorted(local) == sorted(ray) and "data/segments.npy" in local
    for name in local:
        assert local[name] == ray[name], name
    dataset = PlayDataset.open(tmp_path / "ray")
    assert [r.episode_id for r in dataset.records] == ["a:0", "b:0", "c:0"]
    assert dataset.segments(0, truth=True) and dataset.segments(2, truth=True)  # the model's, in the tasks
    print(f"local {seconds['local']:.1f} s, ray {seconds['ray']:.1f} s")


@pytest.mark.slow
def test_address_needs_the_ray_engine_and_the_local_engine_never_imports_ray(tmp_path: Path) -> None:
    bag = write_rosbag2(tmp_path / "a", RobotBag(seconds=0.5))
    args = ["convert", str(bag), "--mapping", str(write_mapping(tmp_path / "m.yaml")), "--quiet"]
    script = (
        "import sys\n"
        "from playseg_ros.cli import main\n"
        f"assert main({[*args, '--out', str(tmp_path / 'x'), '--address', 'auto']!r}) == 1\n"
        f"assert main({[*args, '--out', str(tmp_path / 'y')]!r}) == 0\n"
        "assert 'ray' not in sys.modules, 'ray imported'\n"
    )
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-3000:]
    assert "playseg convert: --address is the Ray cluster to join: give --engine ray" in done.stderr
