"""`playseg train`'s budget, device, held-out calibration and resume, end to end on a tiny BabyAI dataset."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from playseg_core.checkpoint import read_checkpoint
from playseg_core.data.dataset import DatasetWriter, PlayDataset
from playseg_ros.cli import main as cli_main
from playseg_ros.offline import train_state_path

pytestmark = pytest.mark.slow  # every test trains through `playseg train`, most in subprocesses


@pytest.fixture(scope="module")
def tiny_data(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("train-cli") / "tiny"
    assert cli_main(["generate", "--preset", "tiny", "--seed", "3", "--out", str(out), "--quiet"]) == 0
    return out


def _without_val(source: Path, out: Path, annotated: int | None = None) -> Path:
    """``source`` with no val split (and only ``annotated`` annotated training episodes), as `convert`
    writes a dataset whose annotated episodes are all in train."""
    dataset = PlayDataset.open(source)
    with DatasetWriter(out, dataset.instructions, features=dataset.features, domain=dataset.domain) as writer:
        for number, episode in enumerate(dataset.episodes("train")):
            if annotated is None or number < annotated:
                writer.add(episode, "train")
        for episode in dataset.episodes("play", truth=True):
            writer.add(episode, "play")
    return out


def test_without_a_val_split_it_holds_out_annotated_episodes_and_calibrates(
    tiny_data: Path, tmp_path: Path, capsys
) -> None:
    data = _without_val(tiny_data, tmp_path / "no-val")
    model = tmp_path / "ps.pt"
    assert cli_main(["train", "--data", str(data), "--out", str(model), "--max-steps", "30"]) == 0
    out = capsys.readouterr().out
    assert "2 of 8 annotated episodes held out (--val-share 0.2)" in out
    assert "30 of at most 30 steps" in out and "label threshold" in out
    meta = read_checkpoint(model).meta
    assert meta["held_out"] is True and len(meta["val_episodes"]) == 2
    assert "threshold" in meta["calibration"]
    # the same episodes every time: a second run holds out the same two
    assert cli_main(["train", "--data", str(data), "--out", str(tmp_path / "b.pt"), "--max-steps", "1"]) == 0
    assert read_checkpoint(tmp_path / "b.pt").meta["val_episodes"] == meta["val_episodes"]


def test_too_few_episodes_to_hold_out_marks_the_model_uncalibrated_and_segment_warns(
    tiny_data: Path, tmp_path: Path, capsys
) -> None:
    data = _without_val(tiny_data, tmp_path / "one", annotated=1)
    model = tmp_path / "ps.pt"
    assert cli_main(["train", "--data", str(data), "--out", str(model), "--max-steps", "5"]) == 0
    out = capsys.readouterr().out
    assert "uncalibrated:" in out and "marked uncalibrated" in out
    assert "threshold" not in read_checkpoint(model).meta["calibration"]
    argv = [
        "segment",
        "--model",
        str(model),
        "--input",
        str(data),
        "--out",
        str(tmp_path / "seg"),
        "--splits",
        "play",
    ]
    assert cli_main(argv) == 0
    err = capsys.readouterr().err
    assert err.count("not calibrated (trained without held-out annotated episodes)") == 1


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the message of a machine without CUDA")
@pytest.mark.parametrize("command", ["train", "calibrate", "segment", "convert", "experiment"])
def test_asking_for_cuda_without_one_is_one_line(
    command: str, tiny_data: Path, tmp_path: Path, capsys
) -> None:
    model, out = tmp_path / "ps.pt", tmp_path / "out"
    if command != "train":  # the commands that run a model get one (its first steps are enough here)
        assert cli_main(["train", "--data", str(tiny_data), "--out", str(model), "--max-steps", "1"]) == 0
        capsys.readouterr()
    argv = {
        "train": ["train", "--data", str(tiny_data), "--out", str(model)],
        "calibrate": ["calibrate", "--model", str(model), "--data", str(tiny_data), "--out", str(out)],
        "segment": ["segment", "--model", str(model), "--input", str(tiny_data), "--out", str(out)],
        "convert": ["convert", str(tiny_data), "--out", str(out), "--segment", str(model)],
        "experiment": ["experiment", "babyai", "--scale", "tiny", "--out", str(out)],
    }[command]
    assert cli_main([*argv, "--device", "cuda"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [
        f"playseg {command}: device 'cuda': torch sees no CUDA device here (use --device cpu or auto)"
    ]
    assert not out.exists() and (command != "train" or not model.exists())


def test_labeller_and_model_cannot_be_one_file(tiny_data: Path, tmp_path: Path, capsys) -> None:
    model = tmp_path / "ps.pt"
    assert cli_main(["train", "--data", str(tiny_data), "--out", str(model), "--labeller", str(model)]) == 1
    assert "the same file as --out" in capsys.readouterr().err


def _sigterm_once_written(
    argv: list[str], state: Path, env: dict[str, str] | None = None, stdout: int | None = None
) -> tuple[int, str]:
    """Run ``argv`` until ``state`` (a training state, written at an evaluation) exists, then SIGTERM it:
    (exit code, stderr)."""
    process = subprocess.Popen(argv, env=env, stdout=stdout, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 300
    while not state.exists() and process.poll() is None and time.monotonic() < deadline:
        time.sleep(0.05)
    process.send_signal(signal.SIGTERM)
    _, err = process.communicate(timeout=120)
    return process.returncode, err


def _train_argv(data: Path, out: Path, method: str = "ps") -> list[str]:
    return [sys.executable, "-m", "playseg_ros.cli", "train", "--data", str(data), "--out", str(out),
            "--max-steps", "50", "--patience", "100", "--method", method,
            *(["--batch-segments", "2"] if method != "ps" else [])]  # fmt: skip


@pytest.mark.parametrize("method", ["ps", "unloc"])
def test_a_run_killed_by_sigterm_resumes_to_the_whole_runs_result(
    method: str, tiny_data: Path, tmp_path: Path
) -> None:
    # MKL picks its kernels by the memory alignment of the operands unless told to be strict, so two
    # processes can differ in the last bits; strict, a resumed run is the whole run exactly.
    env = {**os.environ, "PYTHONUNBUFFERED": "1", "MKL_CBWR": "AUTO,STRICT"}
    whole = tmp_path / "whole.pt"
    subprocess.run(_train_argv(tiny_data, whole, method), check=True, env=env, capture_output=True)
    killed = tmp_path / "killed.pt"
    state = train_state_path(killed)
    code, err = _sigterm_once_written(_train_argv(tiny_data, killed, method), state, env)  # at step 25
    assert code == 130, err
    assert state.exists() and not killed.exists()
    assert "--resume continues it" in err
    resumed = subprocess.run(
        [*_train_argv(tiny_data, killed, method), "--resume"], env=env, capture_output=True, text=True
    )
    assert resumed.returncode == 0, resumed.stderr
    assert "resumed at step" in resumed.stderr and not state.exists()
    whole_run, killed_run = read_checkpoint(whole), read_checkpoint(killed)
    assert killed_run.meta["history"] == whole_run.meta["history"]
    assert [entry["step"] for entry in whole_run.meta["history"]] == [25.0, 50.0]
    a, b = whole_run.state_dict, killed_run.state_dict
    assert a.keys() == b.keys() and all(torch.equal(a[key], b[key]) for key in a)


def test_a_run_killed_while_training_the_labeller_resumes_the_labeller(
    tiny_data: Path, tmp_path: Path
) -> None:
    model, labeller = tmp_path / "ps.pt", tmp_path / "labeller.pt"
    argv = [*_train_argv(tiny_data, model), "--labeller", str(labeller)]
    state = train_state_path(labeller)
    code, err = _sigterm_once_written(argv, state)  # the labeller's state: written after PS is saved
    assert code == 130, err
    assert model.is_file() and state.exists() and not labeller.exists()
    written = model.read_bytes()
    resumed = subprocess.run([*argv, "--resume"], capture_output=True, text=True, timeout=300)
    assert resumed.returncode == 0, resumed.stderr
    assert "resuming the labeller" in resumed.stdout and "[labeller] resumed at step 25" in resumed.stderr
    assert labeller.is_file() and not state.exists()
    assert model.read_bytes() == written  # the PS model is not trained again


def test_nproc_2_trains_data_parallel_and_process_0_alone_writes(tiny_data: Path, tmp_path: Path) -> None:
    model, labeller = tmp_path / "ps.pt", tmp_path / "labeller.pt"
    argv = [*_train_argv(tiny_data, model), "--nproc", "2", "--labeller", str(labeller)]
    done = subprocess.run(argv, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    assert (
        done.stdout.count("PS model trained") == 1 and "50 of at most 50 steps (2 processes)" in done.stdout
    )
    assert "labeller, 50 of at most 50 steps (2 processes)" in done.stdout
    meta = read_checkpoint(model).meta
    assert [entry["step"] for entry in meta["history"]] == [26.0, 50.0]  # the first evaluation past 25
    assert "threshold" in meta["calibration"] and labeller.exists()
    assert not train_state_path(model).exists()
    bad = subprocess.run([*argv[:-2], "--lr", "-1"], capture_output=True, text=True, timeout=120)
    assert bad.returncode == 2  # argparse refuses before any process starts
    missing = [*_train_argv(tmp_path / "none", tmp_path / "x.pt"), "--nproc", "2"]
    failed = subprocess.run(missing, capture_output=True, text=True, timeout=300)
    assert failed.returncode == 1
    assert failed.stderr.strip().splitlines() == [
        f"playseg train: --data {tmp_path / 'none'}: no such directory"
    ]


def test_sigterm_stops_every_process_of_an_nproc_run(tiny_data: Path, tmp_path: Path) -> None:
    model = tmp_path / "ps.pt"
    argv = [
        *_train_argv(tiny_data, model),
        "--nproc",
        "2",
        "--max-steps",
        "5000",
    ]  # the last --max-steps wins
    state = train_state_path(model)
    code, err = _sigterm_once_written(argv, state, stdout=subprocess.PIPE)  # stops, not trains to its cap
    assert code == 130, err
    assert "interrupted" in err and state.exists() and not model.exists()
