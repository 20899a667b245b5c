"""`playseg convert --segment MODEL`: a PS model labels the unannotated episodes of rosbags-written robot
bags; the stored segments are `segment_episode`'s, filtered by the checkpoint's label threshold; annotated
episodes keep their human labels."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from test_convert import RobotBag, write_mapping, write_rosbag2

from playseg_core.data.dataset import PlayDataset
from playseg_core.data.episode import Episode
from playseg_core.data.features import Features
from playseg_core.ps.model import PSModel, load_model, save_model
from playseg_core.ps.segmentation import segment_episode
from playseg_core.ps.training import model_config_for
from playseg_ros.cli import main

MODEL_INSTRUCTIONS = ["reach", "push", "wave"]


def untrained_model(
    path: Path, features: Features, episode, threshold: float | None = None, own_cuts: float | None = None
) -> Path:
    """An untrained PS model over the converted features (it cuts arbitrarily, which is all equality
    needs); ``threshold`` is stored as its calibrated label threshold, ``own_cuts`` as its own-cut one."""
    torch.manual_seed(0)
    config = model_config_for(
        features, None, len(MODEL_INSTRUCTIONS), max_len=8, episodes=[episode], min_len=2
    )
    model = PSModel(config, MODEL_INSTRUCTIONS)
    meta = {"calibration": {"threshold": threshold} if threshold is not None else {}}
    if own_cuts is not None:
        meta["own_cuts_calibration"] = {"threshold": own_cuts}
    save_model(path, model, meta)
    return path


def convert_cli(bags: list[Path], out: Path, mapping: Path, *extra: str) -> int:
    args = ["convert", *map(str, bags), "--out", str(out), "--mapping", str(mapping), "--quiet", *extra]
    return main(args)


def converted_play(bags: dict[str, Path], tmp_path: Path) -> tuple[PlayDataset, Episode]:
    """The play bag converted without a model, and its episode: what the model will be given."""
    assert convert_cli([bags["play"]], tmp_path / "plain", bags["mapping"]) == 0
    plain = PlayDataset.open(tmp_path / "plain")
    return plain, plain.episode(0, truth=True)


@pytest.fixture(scope="module")
def bags(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("bags")
    return {
        "play": write_rosbag2(root / "bags" / "play", RobotBag(seconds=4.0, labels=[])),
        "annotated": write_rosbag2(root / "bags" / "annotated", RobotBag(seconds=3.0)),
        "mapping": write_mapping(root / "map.yaml"),
        "root": root,
    }


def test_unannotated_episodes_get_the_models_segments_above_its_threshold(
    bags: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    plain, episode = converted_play(bags, tmp_path)
    assert plain.records[0].split == "play" and episode.segments == []
    probe = untrained_model(tmp_path / "probe.pt", plain.features, episode)
    model, _ = load_model(probe)
    expected_all = segment_episode(model, episode, min_len=model.cfg.min_len)
    assert len(expected_all) >= 4
    # A threshold between the confidences: some segments are stored, some are not.
    confidences = sorted(s.confidence for s in expected_all)
    threshold = float(np.median(confidences))
    model_path = untrained_model(tmp_path / "ps.pt", plain.features, episode, threshold)
    expected = [s for s in expected_all if s.confidence >= threshold]
    assert 0 < len(expected) < len(expected_all)

    code = convert_cli(
        [bags["play"], bags["annotated"]], tmp_path / "data", bags["mapping"], "--segment", str(model_path)
    )
    captured = capsys.readouterr()
    assert code == 0, captured.err
    dataset = PlayDataset.open(tmp_path / "data")
    by_id = {r.episode_id: i for i, r in enumerate(dataset.records)}
    played = by_id["play:0"]
    assert dataset.records[played].split == "play"  # predictions, not ground truth
    stored = dataset.segments(played, truth=True)
    assert [(s.start, s.end, s.instruction) for s in stored] == [
        (s.start, s.end, s.instruction) for s in expected
    ]
    np.testing.assert_allclose([s.confidence for s in stored], [s.confidence for s in expected], rtol=1e-5)
    np.testing.assert_allclose([s.log_prob for s in stored], [s.log_prob for s in expected], rtol=1e-4)
    np.testing.assert_array_equal(
        dataset.episode(played).images["observation.images.front"], episode.images["observation.images.front"]
    )
    # The annotated bag keeps its two human labels (confidence 1) and is not segmented by the model.
    annotated = by_id["annotated:0"]
    assert dataset.records[annotated].split == "train"
    assert [(s.start, s.end, s.instruction, s.confidence) for s in dataset.segments(annotated)] == [
        (3, 12, "pick up the cup", 1.0),
        (12, 25, "put the cup down", 1.0),
    ]
    assert "annotated:0" in captured.err and "kept its human labels, not segmented" in captured.err
    assert f"not stored (kept: label confidence >= {threshold:.3f})" in captured.err
    assert f"{len(expected) + 2} segments ({len(expected)} by the model)" in captured.out
    meta = dataset.info["meta"]["convert"]["segmentation"]
    assert meta["method"] == "ps" and meta["label_threshold"] == pytest.approx(threshold)
    assert meta["keep"]["rule"] == "label" and meta["keep"]["threshold"] == pytest.approx(threshold)

    # Resuming: the same model skips both bags; another model is refused (not mixed into the dataset).
    args = ([bags["play"], bags["annotated"]], tmp_path / "data", bags["mapping"])
    assert convert_cli(*args, "--segment", str(model_path)) == 0
    assert "2 skipped" in capsys.readouterr().out
    assert convert_cli(*args, "--segment", str(probe)) == 1
    assert "segmented by" in capsys.readouterr().err
    assert convert_cli(*args) == 1
    assert "no --segment given" in capsys.readouterr().err


def test_a_model_that_cannot_read_the_bag_fails_that_bag_in_one_line(
    bags: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert convert_cli([bags["play"]], tmp_path / "plain", bags["mapping"]) == 0
    plain = PlayDataset.open(tmp_path / "plain")
    # A model for a larger camera than the bag's 32x24 frames.
    from playseg_core.data.features import Feature

    camera = "observation.images.front"
    other = Feature(camera, "image", "uint8", (48, 64, 3))
    features = Features.of(
        [plain.features[n] if n != camera else other for n in plain.features.by_name], plain.features.fps
    )
    model_path = untrained_model(tmp_path / "other.pt", features, plain.episode(0))
    capsys.readouterr()
    assert convert_cli([bags["play"]], tmp_path / "data", bags["mapping"], "--segment", str(model_path)) == 1
    err = capsys.readouterr().err
    failures = [line for line in err.splitlines() if "failed:" in line]
    assert len(failures) == 1 and "bag '" in failures[0] and camera in failures[0], err
    assert "Traceback" not in err and not (tmp_path / "data").exists()
    # Bad options before any bag is read: a missing checkpoint; --method without --segment.
    assert convert_cli([bags["play"]], tmp_path / "x", bags["mapping"], "--segment", "nope.pt") == 1
    assert "--segment nope.pt: no such checkpoint file" in capsys.readouterr().err
    assert convert_cli([bags["play"]], tmp_path / "x", bags["mapping"], "--method", "ps") == 1
    assert "give --segment MODEL" in capsys.readouterr().err


def test_keep_own_cuts_stores_the_segments_the_own_cut_threshold_keeps(
    bags: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from playseg_core.ps.labelling import segment_probability

    plain, episode = converted_play(bags, tmp_path)
    label_only = untrained_model(tmp_path / "label.pt", plain.features, episode, threshold=0.0)
    model, _ = load_model(label_only)
    found = segment_episode(model, episode, min_len=model.cfg.min_len)
    scores = sorted(segment_probability(s) for s in found)
    own = float(np.median(scores))
    expected = [s for s in found if segment_probability(s) >= own]
    assert 0 < len(expected) < len(found)
    # A checkpoint with a label calibration only: one line, before any bag is read.
    capsys.readouterr()
    args = ([bags["play"]], tmp_path / "data", bags["mapping"])
    assert convert_cli(*args, "--segment", str(label_only), "--keep", "own_cuts") == 1
    err = capsys.readouterr().err
    assert f"checkpoint {label_only}: records no own-cut calibration" in err and "Traceback" not in err
    assert not (tmp_path / "data").exists()
    assert convert_cli(*args, "--keep", "own_cuts") == 1
    assert "give --segment MODEL" in capsys.readouterr().err

    model_path = untrained_model(tmp_path / "ps.pt", plain.features, episode, threshold=0.0, own_cuts=own)
    assert convert_cli(*args, "--segment", str(model_path), "--keep", "own_cuts") == 0
    dataset = PlayDataset.open(tmp_path / "data")
    stored = dataset.segments(0, truth=True)
    assert [(s.start, s.end, s.instruction) for s in stored] == [
        (s.start, s.end, s.instruction) for s in expected
    ]
    meta = dataset.info["meta"]["convert"]["segmentation"]
    assert meta["keep"] == {"rule": "own_cuts", "threshold": own, "score": "label x cut probability"}
    # The same model kept by another rule is another segmentation: not mixed into this dataset.
    assert convert_cli(*args, "--segment", str(model_path)) == 1
    assert "segmented by" in capsys.readouterr().err


def test_the_default_keep_rule_leaves_the_segmentation_digest_as_before_rules_existed(tmp_path: Path) -> None:
    """A dataset converted with --segment before keep rules existed resumes: its digest is the same."""
    import hashlib

    from playseg_ros.convert import SegmentationSpec

    path = tmp_path / "ps.pt"
    path.write_bytes(b"checkpoint bytes")  # the digest is of the file; the model is loaded later
    assert SegmentationSpec.of(path).digest == hashlib.sha256(b"checkpoint bytes|ps|0").hexdigest()
    own = SegmentationSpec.of(path, keep="own_cuts")
    assert own.digest == hashlib.sha256(b"checkpoint bytes|ps|0|own_cuts").hexdigest()
    with pytest.raises(ValueError, match="--keep: keep rule must be one of label, own_cuts, all"):
        SegmentationSpec.of(path, keep="confident")
