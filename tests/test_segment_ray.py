"""`playseg segment --engine ray`: Ray actors segment the episodes and the output equals the local
engine's (the same segments, confidences to float32 rounding, every other file byte for byte), from a
dataset and from a play bag (a local Ray instance with 2 CPUs)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from playseg_core.data.dataset import PlayDataset
from playseg_ros.cli import main


def files_of(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def assert_same_segments(local: Path, ray: Path) -> None:
    """The same segments (episodes, bounds, labels); confidences equal to float32 rounding: the CPU's
    convolution kernels may differ in the last bits between processes (they are chosen by the operands'
    memory alignment), which moves no cut."""
    a, b = np.load(local), np.load(ray)
    assert a.dtype == b.dtype and a.shape == b.shape
    for field in ("episode", "start", "end", "instruction"):
        np.testing.assert_array_equal(a[field], b[field], err_msg=field)
    for field in ("confidence", "log_prob"):
        np.testing.assert_allclose(a[field], b[field], rtol=1e-5, atol=1e-6, err_msg=field)


@pytest.fixture(scope="module")
def trained(tmp_path_factory) -> tuple[Path, Path]:
    root = tmp_path_factory.mktemp("ray-segment")
    data, model = root / "tiny", root / "ps.pt"
    assert main(["generate", "--preset", "tiny", "--seed", "5", "--out", str(data), "--quiet"]) == 0
    assert main(["train", "--data", str(data), "--out", str(model), "--epochs", "1"]) == 0
    return data, model


@pytest.mark.slow
def test_ray_engine_segments_a_dataset_and_a_bag_as_the_local_engine_does(
    trained: tuple[Path, Path], tmp_path: Path, capsys
) -> None:
    data, model = trained
    from playseg_ros.play_bags import write_play_bag

    dataset = PlayDataset.open(data)
    play = [dataset.episode(i) for i in dataset.episode_indices("play")[:5]]
    write_play_bag(tmp_path / "play-bag", play, annotated=False)
    for name, source in (("dataset", data), ("bag", tmp_path / "play-bag")):
        outputs = {}
        for engine in ("local", "ray"):
            out = tmp_path / f"{name}-{engine}"
            argv = [
                "segment",
                "--model",
                str(model),
                "--input",
                str(source),
                "--out",
                str(out),
                "--keep",
                "all",
            ]
            workers = ["--workers", "2"] if engine == "ray" else []
            assert main([*argv, "--engine", engine, *workers]) == 0, capsys.readouterr().err
            outputs[engine] = files_of(out)
        local, ray = outputs["local"], outputs["ray"]
        assert sorted(local) == sorted(ray) and "data/segments.npy" in local
        for file in local:
            if file == "data/segments.npy":
                assert_same_segments(out.parent / f"{name}-local" / file, out.parent / f"{name}-ray" / file)
            elif "segments_bag" not in file:  # the bag's MCAP records when it was written
                assert local[file] == ray[file], (name, file)
        segmented = PlayDataset.open(tmp_path / f"{name}-ray")
        assert len(segmented) == (
            len(play)
            if name == "bag"
            else len(dataset.episode_indices("play")) + len(dataset.episode_indices("test"))
        )
        assert sum(len(segmented.segments(i, truth=True)) for i in range(len(segmented))) > 0
    bag_local = tmp_path / "bag-local" / "segments_bag"
    bag_ray = tmp_path / "bag-ray" / "segments_bag"
    from playseg_ros.bag.reader import BagReader

    def messages(bag: Path) -> list[tuple[str, int, int]]:
        # the segments' content is compared above (segments.npy); a message's confidence may differ in
        # its last bits (assert_same_segments), its size may not
        return [(m.topic, m.log_time_ns, len(m.data)) for m in BagReader(bag).messages()]

    assert messages(bag_local) == messages(bag_ray) and messages(bag_ray)


@pytest.mark.slow
def test_engine_options_are_checked_and_the_local_engine_never_imports_ray(
    trained: tuple[Path, Path], tmp_path: Path
) -> None:
    data, model = trained
    argv = ["segment", "--model", str(model), "--input", str(data), "--splits", "test"]
    script = (
        "import sys\n"
        "from playseg_ros.cli import main\n"
        f"assert main({[*argv, '--out', str(tmp_path / 'x'), '--address', 'auto']!r}) == 1\n"
        f"assert main({[*argv, '--out', str(tmp_path / 'w'), '--engine', 'ray', '--workers', '0']!r}) == 1\n"
        f"assert main({[*argv, '--out', str(tmp_path / 'v'), '--workers', '2']!r}) == 1\n"
        f"assert main({[*argv, '--out', str(tmp_path / 'y')]!r}) == 0\n"
        "assert 'ray' not in sys.modules, 'ray imported'\n"
    )
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    assert "playseg segment: --address is the Ray cluster to join: give --engine ray" in done.stderr
    assert "playseg segment: --workers must be >= 1, got 0" in done.stderr
    assert "playseg segment: --workers is the number of Ray actors: give --engine ray" in done.stderr


@pytest.mark.slow
def test_an_actor_that_dies_is_one_error_naming_the_episode(
    trained: tuple[Path, Path], tmp_path: Path
) -> None:
    """The actors load the checkpoint themselves (on a cluster, from the nodes' shared storage): one that
    cannot fails the run with a PlaysegError naming the episode, not a Ray traceback."""
    from playseg_core.baselines.common import SegmentOptions
    from playseg_core.errors import PlaysegError
    from playseg_ros.segment_ray import segment_on_ray

    data, _ = trained
    dataset = PlayDataset.open(data)
    episodes = [dataset.episode(i) for i in dataset.episode_indices("test")[:2]]
    missing = tmp_path / "not-there.pt"
    with pytest.raises(PlaysegError, match=r"episode '.+': Ray actor failed: .*not-there\.pt") as raised:
        list(segment_on_ray(episodes, "ps", missing, SegmentOptions(), 1, None))
    assert "\n" not in str(raised.value)
