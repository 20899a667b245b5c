"""`playseg train / calibrate / segment / evaluate` end to end on a tiny generated BabyAI dataset."""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from playseg_core.data.dataset import PlayDataset
from playseg_core.data.features import ACTION, Feature
from playseg_core.domains.babyai.spec import CAMERA
from playseg_core.ps.labelling import segment_probability, threshold_json
from playseg_core.ps.model import load_model
from playseg_ros.cli import main as cli_main
from playseg_ros.offline import _action_features


@pytest.fixture(scope="module")
def tiny_data(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("data") / "tiny"
    assert cli_main(["generate", "--preset", "tiny", "--seed", "3", "--out", str(out), "--quiet"]) == 0
    return out


def _refuse(constant: str) -> None:
    raise AssertionError(f"{constant} is not JSON")


def segment_argv(model: Path, data: Path, out: Path) -> list[str]:
    """`playseg segment` of the test split of ``data``, ending with ``--out OUT``."""
    return ["segment", "--model", str(model), "--input", str(data), "--splits", "test", "--out", str(out)]


@pytest.mark.slow
def test_train_calibrate_segment_evaluate(tiny_data: Path, tmp_path: Path, capsys) -> None:
    model = tmp_path / "ps.pt"
    assert cli_main(["train", "--data", str(tiny_data), "--out", str(model), "--epochs", "1"]) == 0
    printed = capsys.readouterr().out
    # BabyAI's camera by the domain's grid-tile encoder; its declared discrete actions, by --actions auto
    assert f"model reads {CAMERA} (babyai.grid_tiles), action (discrete_action)" in printed
    assert "end bias" in printed and "label threshold" in printed
    assert "on its own cuts of the val episodes it keeps" in printed
    raw = torch.load(model, weights_only=True)
    assert raw["meta"]["own_cuts"]["segments"] >= raw["meta"]["own_cuts"]["kept"] >= 0
    own_threshold = raw["meta"]["own_cuts_calibration"]
    assert own_threshold["num_segments"] == raw["meta"]["own_cuts"]["segments"]
    assert f"own-cut threshold {own_threshold['threshold']:.3f} (label x cut probability)" in printed
    assert raw["features"]["features"][ACTION]["num_values"] == 7
    assert [spec["kind"] for spec in raw["config"]["encoders"]] == ["babyai.grid_tiles", "discrete_action"]
    # the bias the checkpoint records is the one its model segments with
    assert raw["state_dict"]["end_bias"].item() == raw["meta"]["end_bias"]["bias"]
    assert len(raw["meta"]["end_bias"]["sweep"]) >= 5

    recalibrated = tmp_path / "ps-recalibrated.pt"
    assert (
        cli_main(["calibrate", "--model", str(model), "--data", str(tiny_data), "--out", str(recalibrated)])
        == 0
    )
    again = torch.load(recalibrated, weights_only=True)
    assert again["meta"]["end_bias"] == raw["meta"]["end_bias"]  # same model, same val split
    assert again["meta"]["calibrated_on"] == str(tiny_data.resolve())
    assert raw["meta"]["calibration"]["target_accuracy"] == 0.95  # LABEL_ACCURACY_TARGET
    lower = tmp_path / "ps-0.5.pt"
    argv = ["calibrate", "--model", str(model), "--data", str(tiny_data), "--out", str(lower)]
    assert cli_main([*argv, "--label-accuracy", "0.5"]) == 0
    calibration = torch.load(lower, weights_only=True)["meta"]["calibration"]
    assert calibration["target_accuracy"] == 0.5
    assert calibration["threshold"] <= raw["meta"]["calibration"]["threshold"]  # never keeps fewer
    assert cli_main([*argv, "--label-accuracy", "1.5"]) == 1
    assert "--label-accuracy must be in (0, 1], got 1.5" in capsys.readouterr().err
    random = ["train", "--data", str(tiny_data), "--out", str(tmp_path / "r.pt"), "--method", "random"]
    assert cli_main([*random, "--label-accuracy", "0.9"]) == 1
    assert "--label-accuracy: only with --method ps" in capsys.readouterr().err

    pred = tmp_path / "pred"
    assert cli_main(segment_argv(model, tiny_data, pred)) == 0
    segmented = PlayDataset.open(pred)
    assert len(segmented) == len(PlayDataset.open(tiny_data).episode_indices("test"))
    assert cli_main(["evaluate", "--pred", str(pred), "--truth", str(tiny_data), "--plot-episodes", "0"]) == 0
    metrics = json.loads((pred / "metrics.json").read_text())
    assert 0.0 <= metrics["boundary_precision_tol0"] <= 1.0 and metrics["episodes"] == len(segmented)
    assert segmented.info["meta"]["keep"]["rule"] == "label"
    # Kept by the own-cut threshold: the dataset holds every segment, the meta says which are kept.
    capsys.readouterr()
    assert cli_main([*segment_argv(model, tiny_data, tmp_path / "own"), "--keep", "own_cuts"]) == 0
    own = PlayDataset.open(tmp_path / "own")
    keep = own.info["meta"]["keep"]
    threshold = own_threshold["threshold"]  # +inf (keeps nothing) where no threshold reached the target
    assert keep["rule"] == "own_cuts" and keep["threshold"] == threshold_json(threshold)
    every = [s for i in range(len(own)) for s in own.segments(i, truth=True)]
    kept = sum(segment_probability(s) >= threshold for s in every)
    assert f"{len(every)} segments from" in (out := capsys.readouterr().out)
    assert f"; {kept} kept by label x cut probability >= {threshold:.3f}" in out
    # A threshold no accuracy target reached (+inf: keeps nothing) is null in the meta's strict JSON.
    unreachable = torch.load(model, weights_only=True)
    unreachable["meta"]["calibration"]["threshold"] = math.inf
    torch.save(unreachable, tmp_path / "ps-inf.pt")
    assert cli_main(segment_argv(tmp_path / "ps-inf.pt", tiny_data, tmp_path / "inf")) == 0
    meta = json.loads((tmp_path / "inf" / "meta" / "info.json").read_text(), parse_constant=_refuse)["meta"]
    assert meta["keep"] == {"rule": "label", "threshold": None, "score": "label confidence"}
    assert meta["label_threshold"] is None


@pytest.mark.slow
def test_end_lookahead_reaches_the_checkpoint_and_segmenting(tiny_data: Path, tmp_path: Path, capsys) -> None:
    model = tmp_path / "ps.pt"
    train = ["train", "--data", str(tiny_data), "--out", str(model), "--epochs", "1"]
    assert cli_main([*train, "--end-lookahead", "2"]) == 0
    assert "the end head reads 2 step(s) past an end" in capsys.readouterr().out
    assert torch.load(model, weights_only=True)["config"]["end_lookahead"] == 2
    loaded, _ = load_model(model)
    assert loaded.lookahead == 2 and loaded.end_head.in_features == 3 * loaded.cfg.trunk.hidden_dim
    pred = tmp_path / "pred"
    assert cli_main(segment_argv(model, tiny_data, pred)) == 0
    segmented = PlayDataset.open(pred)
    for index, record in enumerate(segmented.records):  # every episode cut up to its last step
        assert segmented.segments(index, truth=True)[-1].end == record.num_steps
    assert cli_main([*train, "--overwrite", "--end-lookahead", "9"]) == 1
    assert "--end-lookahead: must be in 0..8, got 9" in capsys.readouterr().err
    assert cli_main([*train, "--overwrite", "--method", "random", "--end-lookahead", "1"]) == 1
    assert "--end-lookahead: only with --method ps" in capsys.readouterr().err


def test_calibrate_refuses_a_dataset_without_annotated_val(tmp_path: Path, capsys) -> None:
    assert cli_main(["calibrate", "--model", str(tmp_path / "none.pt"), "--data", str(tmp_path)]) == 1
    assert "none.pt: no such file" in capsys.readouterr().err


def test_actions_option(tiny_data: Path) -> None:
    features = PlayDataset.open(tiny_data).features
    assert _action_features("auto", features) == (features, True)  # the declared discrete action
    assert _action_features("none", features) == (features, False)
    three, reads = _action_features("3", features)
    assert reads and three.action.num_values == 3
    continuous = features.with_action(Feature(ACTION, "action", "float32", (1,)))
    assert _action_features("auto", continuous) == (continuous, True)  # declared continuous: read as such
    with pytest.raises(ValueError, match="--actions must be a count"):
        _action_features("many", features)


@pytest.mark.slow
def test_augment_trains_on_rotated_clips_and_needs_actions_none(
    tiny_data: Path, tmp_path: Path, capsys
) -> None:
    model = tmp_path / "ps.pt"
    base = ["train", "--data", str(tiny_data), "--out", str(model), "--epochs", "1", "--augment"]
    _fails(capsys, base, "--augment", "--actions none")  # a mirror would swap the turns the model reads
    assert not model.exists()
    _fails(capsys, [*base, "--actions", "none", "--method", "unloc"], "--augment", "not unloc")
    assert cli_main([*base, "--actions", "none"]) == 0
    trained, meta = load_model(model)
    assert meta["train"]["augment"] is True and not trained.encoders.reads_actions


@pytest.mark.slow
def test_segment_refuses_data_with_other_features(tiny_data: Path, tmp_path: Path, capsys) -> None:
    model = tmp_path / "ps.pt"
    assert cli_main(["train", "--data", str(tiny_data), "--out", str(model), "--epochs", "1"]) == 0
    dataset = PlayDataset.open(tiny_data)
    from playseg_core.data.dataset import DatasetWriter

    other = tmp_path / "wrist"
    wrist = "observation.images.wrist"
    with DatasetWriter(other, dataset.instructions) as writer:
        for index in dataset.episode_indices("test")[:2]:
            episode = dataset.episode(index)
            images = {wrist: episode.images[CAMERA]}
            writer.add(type(episode)(episode.episode_id, episode.actions, images, episode.state), "test")
    capsys.readouterr()
    # A bag that declares nothing (as the recorder writes it): its image is the camera the model reads,
    # as in the live segmenter.
    from playseg_ros.play_bags import read_play_bag_info, write_play_bag

    test_episodes = [dataset.episode(i) for i in dataset.episode_indices("test")[:2]]
    write_play_bag(tmp_path / "recorded", test_episodes, annotated=False)
    assert read_play_bag_info(tmp_path / "recorded").features is None
    out = tmp_path / "from-bag"
    assert (
        cli_main(["segment", "--model", str(model), "--input", str(tmp_path / "recorded"), "--out", str(out)])
        == 0
    )
    assert len(PlayDataset.open(out)) == 2 and (out / "segments_bag" / "metadata.yaml").is_file()
    code = cli_main(
        [
            "segment",
            "--model",
            str(model),
            "--input",
            str(other),
            "--splits",
            "test",
            "--out",
            str(tmp_path / "o"),
        ]
    )
    assert code == 1
    assert f"reads feature '{CAMERA}', which the data lacks" in capsys.readouterr().err


def _fails(capsys, argv: list[str], *fragments: str) -> str:
    """The command exits with 1 and prints one line on stderr holding every fragment."""
    capsys.readouterr()
    assert cli_main(argv) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1, err
    for fragment in fragments:
        assert fragment in err, (fragment, err)
    return err


def test_expected_failures_are_one_named_line(tiny_data: Path, tmp_path: Path, capsys) -> None:
    garbage = tmp_path / "garbage.pt"
    garbage.write_bytes(b"\x00 not a model")
    foreign = tmp_path / "notes"
    foreign.mkdir()
    (foreign / "keep.txt").write_text("mine")
    bag = Path(__file__).resolve().parent.parent / "bags" / "test"
    cases = [
        (
            ["train", "--data", str(tmp_path / "missing"), "--out", str(tmp_path / "m.pt")],
            "missing",
            "no such",
        ),
        (
            ["train", "--data", str(foreign), "--out", str(tmp_path / "m.pt")],
            "notes",
            "not a playseg dataset",
        ),
        (["train", "--data", str(bag), "--out", str(tmp_path / "m.pt")], "a bag"),
        (["evaluate", "--pred", str(tmp_path / "nothing"), "--truth", str(tiny_data)], "--pred", "nothing"),
        (
            ["segment", "--model", str(garbage), "--input", str(tiny_data), "--out", str(tmp_path / "o")],
            "garbage.pt",
            "cannot be read safely",
        ),
        (
            ["segment", "--model", str(garbage), "--input", str(tiny_data), "--out", str(tiny_data / "x")],
            "overlaps the input",
        ),
        (
            [
                "segment",
                "--model",
                str(garbage),
                "--input",
                str(tmp_path / "gone"),
                "--out",
                str(tmp_path / "o"),
            ],
            "--input",
            "gone",
        ),
        (["generate", "--preset", "tiny", "--workers", "0", "--out", str(tmp_path / "g")], "--workers"),
        (
            ["generate", "--preset", "tiny", "--annotated-share", "0", "--out", str(tmp_path / "g")],
            "--annotated-share",
        ),
        (["generate", "--preset", "huge", "--out", str(tmp_path / "g")], "--preset 'huge'"),
        (
            ["generate", "--preset", "tiny", "--out", str(foreign), "--overwrite", "--quiet"],
            "notes",
            "not a playseg dataset; refusing to replace it",
        ),
    ]
    for argv, *fragments in cases:
        _fails(capsys, argv, *fragments)
    assert (foreign / "keep.txt").read_text() == "mine"  # --overwrite never replaces a foreign directory
    assert not (tmp_path / "g").exists()


def test_outputs_are_checked_before_training(tiny_data: Path, tmp_path: Path, capsys) -> None:
    existing = tmp_path / "ps.pt"
    existing.write_bytes(b"an earlier model")
    _fails(capsys, ["train", "--data", str(tiny_data), "--out", str(existing)], "ps.pt", "--overwrite")
    argv = ["train", "--data", str(tiny_data), "--out", str(existing), "--overwrite"]
    _fails(capsys, argv, "ps.pt", "not a checkpoint")  # --overwrite replaces checkpoints only
    _fails(capsys, ["calibrate", "--model", str(existing), "--data", str(tiny_data)], "ps.pt")
    assert existing.read_bytes() == b"an earlier model"
    with pytest.raises(SystemExit) as exit_code:  # argparse: its usage and one line naming the option
        cli_main(
            ["train", "--data", str(tiny_data), "--out", str(tmp_path / "m.pt"), "--batch-segments", "0"]
        )
    assert exit_code.value.code == 2 and "argument --batch-segments: must be at least 1, got 0" in (
        capsys.readouterr().err
    )
    locked = tmp_path / "locked"
    locked.mkdir()
    locked.chmod(0o500)
    try:
        if not os.access(locked, os.W_OK):  # root may write anywhere: nothing to check then
            _fails(capsys, ["train", "--data", str(tiny_data), "--out", str(locked / "m.pt")], "not writable")
    finally:
        locked.chmod(0o700)
    captured = capsys.readouterr()
    assert "epoch" not in captured.err  # refused before any training


@pytest.mark.slow
def test_segment_replaces_only_its_own_output_and_never_the_input(
    tiny_data: Path, tmp_path: Path, capsys
) -> None:
    model = tmp_path / "ps.pt"
    assert cli_main(["train", "--data", str(tiny_data), "--out", str(model), "--epochs", "1"]) == 0
    out = tmp_path / "seg"
    argv = segment_argv(model, tiny_data, out)
    assert cli_main(argv) == 0
    _fails(capsys, argv, "seg", "--overwrite")
    assert cli_main([*argv, "--overwrite"]) == 0  # a previous playseg dataset: replaced
    _fails(capsys, [*argv[:-2], "--out", str(tiny_data), "--overwrite"], "overlaps the input")
    assert PlayDataset.open(tiny_data).splits == ("train", "val", "play", "test")  # the input is intact
    _fails(capsys, [*argv[:-4], "--splits", "dev", "--out", str(tmp_path / "x")], "--splits", "'dev'")
    info = (out / "meta" / "info.json").read_bytes()
    evaluate = ["evaluate", "--pred", str(out), "--truth", str(tiny_data), "--plot-episodes", "0"]
    _fails(capsys, [*evaluate, "--json", str(out / "meta" / "info.json")], "--json", "files of the dataset")
    _fails(capsys, [*evaluate, "--json", str(tmp_path / "notes.txt")], "--json", "expected a .json file")
    assert (out / "meta" / "info.json").read_bytes() == info  # the reports never replace a dataset's files
    assert cli_main(evaluate) == 0 and (out / "metrics.json").is_file()  # the default: beside the dataset
    swapped = ["evaluate", "--pred", str(tiny_data), "--truth", str(out), "--plot-episodes", "0"]
    _fails(capsys, [*swapped, "--json", str(tmp_path / "m.json")], "of its episodes are not in --truth")


@pytest.mark.slow
def test_sigterm_removes_partial_outputs(tmp_path: Path) -> None:
    out = tmp_path / "big"
    command = [sys.executable, "-m", "playseg_ros.cli", "generate", "--preset", "paper", "--out", str(out)]
    proc = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 60
    while not list(tmp_path.glob(".big.partial-*")) and time.monotonic() < deadline:
        time.sleep(0.2)
    assert list(tmp_path.glob(".big.partial-*")), "the writer never started"
    time.sleep(1.0)
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130, err
    assert "interrupted; partial outputs removed" in err
    assert list(tmp_path.iterdir()) == []


def test_a_stale_staging_directory_of_a_killed_run_is_removed(tiny_data: Path, tmp_path: Path) -> None:
    from playseg_core.data.dataset import DatasetWriter

    stale = tmp_path / ".ds.partial-999999999"  # no such process
    (stale / "data").mkdir(parents=True)
    dataset = PlayDataset.open(tiny_data)
    with DatasetWriter(tmp_path / "ds", dataset.instructions, features=dataset.features) as writer:
        writer.add(dataset.episode(0), "train")
    assert writer.removed_stale == [stale] and not stale.exists()
