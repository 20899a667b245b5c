"""`playseg convert --val-share S`: a share of the annotated episodes goes to ``val`` by
`playseg_core.data.splits.held_out_ids` over the whole dataset, whatever the workers and across reruns."""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path

import pytest
from test_convert import RobotBag, write_mapping, write_rosbag2

from playseg_core.data.dataset import PlayDataset
from playseg_core.data.splits import DEFAULT_VAL_SHARE, held_out_ids
from playseg_ros.cli import main
from playseg_ros.convert import SegmentationSpec, convert, load_mapping

LABELLED = RobotBag(seconds=1.0, labels=[(0.2, 0.7, "pick up the cup")])
UNLABELLED = RobotBag(seconds=1.0, labels=[])


def write_bags(root: Path, annotated: Sequence[str], play: Sequence[str] = ()) -> Path:
    for name in annotated:
        write_rosbag2(root / name, LABELLED)
    for name in play:
        write_rosbag2(root / name, UNLABELLED)
    return root


def splits_by_id(out: Path) -> dict[str, str]:
    return {r.episode_id: r.split for r in PlayDataset.open(out).records}


def convert_meta(out: Path) -> dict:
    return json.loads((out / "meta/info.json").read_text())["meta"]["convert"]


@pytest.fixture(scope="module")
def mapping(tmp_path_factory: pytest.TempPathFactory):
    return load_mapping(write_mapping(tmp_path_factory.mktemp("mapping") / "map.yaml"))


ANNOTATED = ["a0", "a1", "a2", "a3", "a4"]


@pytest.mark.slow
def test_val_is_the_held_out_rule_and_the_same_whatever_the_workers(tmp_path: Path, mapping) -> None:
    bags = write_bags(tmp_path / "bags", ANNOTATED, ["p0"])
    one = convert([bags], tmp_path / "one", mapping, workers=1, progress=False, val_share=0.4)
    two = convert([bags], tmp_path / "two", mapping, workers=2, progress=False, val_share=0.4)
    assert one.failed == [] and two.failed == []
    splits = splits_by_id(tmp_path / "one")
    ids = [f"{name}:0" for name in ANNOTATED]
    held = held_out_ids(ids, 0.4)
    assert len(held) == 2  # ceil(0.4 * 5)
    assert splits == {**{i: "val" if i in held else "train" for i in ids}, "p0:0": "play"}
    assert splits_by_id(tmp_path / "two") == splits
    # the same episode table, byte for byte (order, offsets, splits)
    assert (tmp_path / "one/meta/episodes.jsonl").read_bytes() == (
        tmp_path / "two/meta/episodes.jsonl"
    ).read_bytes()
    info = json.loads((tmp_path / "one/meta/info.json").read_text())
    assert info["counts"]["splits"]["val"]["episodes"] == 2
    assert info["counts"]["splits"]["train"]["episodes"] == 3
    assert convert_meta(tmp_path / "one")["val_share"] == 0.4
    assert (one.val, one.annotated) == (2, 5) and (two.val, two.annotated) == (2, 5)
    assert one.val_text() == "val: 2 of 5 annotated episodes (--val-share 0.4)"
    # val episodes keep their segments (an annotated split reveals them)
    dataset = PlayDataset.open(tmp_path / "one")
    for index in dataset.episode_indices("val"):
        assert [s.instruction for s in dataset.segments(index)] == ["pick up the cup"]


def test_share_zero_keeps_every_annotated_episode_in_train(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    bags = write_bags(tmp_path / "bags", ANNOTATED[:3], ["p0"])
    mapping = write_mapping(tmp_path / "map.yaml")
    args = ["convert", str(bags), "--out", str(tmp_path / "data"), "--mapping", str(mapping), "--quiet"]
    assert main([*args, "--val-share", "0"]) == 0
    assert "val: 0 of 3 annotated episodes (--val-share 0)" in capsys.readouterr().out.splitlines()
    assert splits_by_id(tmp_path / "data") == {
        "a0:0": "train",
        "a1:0": "train",
        "a2:0": "train",
        "p0:0": "play",
    }
    assert convert_meta(tmp_path / "data")["val_share"] == 0


def test_fewer_than_two_annotated_episodes_give_no_val(tmp_path: Path, mapping) -> None:
    bags = write_bags(tmp_path / "bags", ["a0"], ["p0", "p1"])
    summary = convert([bags], tmp_path / "data", mapping, progress=False, val_share=0.9)
    assert summary.failed == []
    assert splits_by_id(tmp_path / "data") == {"a0:0": "train", "p0:0": "play", "p1:0": "play"}
    assert (summary.val, summary.annotated) == (0, 1)


@pytest.mark.slow
def test_a_resumed_run_splits_as_a_fresh_one_and_another_share_resplits(tmp_path: Path, mapping) -> None:
    bags = tmp_path / "bags"
    write_bags(bags, ANNOTATED[:2], ["p0"])
    out = tmp_path / "data"
    first = convert([bags], out, mapping, progress=False, val_share=0.5)
    assert (first.val, first.annotated) == (1, 2)
    # three more annotated bags: the earlier episodes are split again with the new ones
    write_bags(bags, ANNOTATED[2:])
    resumed = convert([bags], out, mapping, progress=False, val_share=0.5)
    assert [r.status for r in resumed.reports].count("skipped") == 3
    fresh = convert([bags], tmp_path / "fresh", mapping, workers=2, progress=False, val_share=0.5)
    assert fresh.failed == []
    assert splits_by_id(out) == splits_by_id(tmp_path / "fresh")
    assert sorted(i for i, s in splits_by_id(out).items() if s == "val") == sorted(
        held_out_ids([f"{name}:0" for name in ANNOTATED], 0.5)
    )
    assert (resumed.val, resumed.annotated, resumed.resplit_from) == (3, 5, None)
    # the same share and nothing new: the dataset is left as it is
    inode = (out / "meta/info.json").stat().st_ino
    again = convert([bags], out, mapping, progress=False, val_share=0.5)
    assert {r.status for r in again.reports} == {"skipped"} and again.resplit_from is None
    assert (out / "meta/info.json").stat().st_ino == inode
    # another share: no bag converted again, the annotated episodes split again, the share recorded
    zero = convert([bags], out, mapping, progress=False, val_share=0.0)
    assert {r.status for r in zero.reports} == {"skipped"}
    assert set(splits_by_id(out).values()) == {"train", "play"}
    assert convert_meta(out)["val_share"] == 0.0 and len(convert_meta(out)["bags"]) == 6
    assert zero.val_text() == "val: 0 of 5 annotated episodes (--val-share 0; re-split, was 0.5)"
    back = convert([bags], out, mapping, progress=False, val_share=0.5)
    assert splits_by_id(out) == splits_by_id(tmp_path / "fresh") and back.val == 3


@pytest.mark.slow
def test_a_dataset_converted_before_val_share_gets_its_val_on_rerun(tmp_path: Path, mapping) -> None:
    bags = write_bags(tmp_path / "bags", ANNOTATED[:4])
    out = tmp_path / "data"
    convert([bags], out, mapping, progress=False, val_share=0.0)
    info_file = out / "meta/info.json"
    info = json.loads(info_file.read_text())
    del info["meta"]["convert"]["val_share"]  # as written before --val-share existed: all in train
    info_file.write_text(json.dumps(info))
    summary = convert([bags], out, mapping, progress=False)
    assert (summary.val, summary.annotated) == (1, 4)  # ceil(0.2 * 4)
    assert convert_meta(out)["val_share"] == DEFAULT_VAL_SHARE
    held = held_out_ids([f"{name}:0" for name in ANNOTATED[:4]], DEFAULT_VAL_SHARE)
    assert {i for i, s in splits_by_id(out).items() if s == "val"} == held


@pytest.mark.parametrize("value", ["1", "-0.1", "nan"])
def test_a_share_outside_0_1_is_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], value: str
) -> None:
    bags = write_bags(tmp_path / "bags", ["a0"])
    mapping = write_mapping(tmp_path / "map.yaml")
    args = ["convert", str(bags), "--out", str(tmp_path / "data"), "--mapping", str(mapping), "--quiet"]
    assert main([*args, f"--val-share={value}"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--val-share must be in [0, 1)" in err[0], err
    assert not (tmp_path / "data").exists()


def test_help_names_the_default(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        main(["convert", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "--val-share S" in text and f"(default {DEFAULT_VAL_SHARE};" in text


def test_segment_leaves_model_segmented_episodes_out_of_val(tmp_path: Path, mapping) -> None:
    from test_convert_segment import untrained_model

    bags = write_bags(tmp_path / "bags", ["a0", "a1"], ["p0", "p1", "p2"])
    plain = convert([bags / "p0"], tmp_path / "plain", mapping, progress=False)
    assert plain.failed == []
    dataset = PlayDataset.open(tmp_path / "plain")
    model = untrained_model(tmp_path / "ps.pt", dataset.features, dataset.episode(0, truth=True), 0.0)
    spec = SegmentationSpec.of(str(model), "ps", keep="all")
    summary = convert([bags], tmp_path / "data", mapping, progress=False, segmentation=spec, val_share=0.6)
    assert summary.failed == [] and summary.totals()["model_segments"] > 0
    splits = splits_by_id(tmp_path / "data")
    # 2 annotated candidates: ceil(0.6 * 2) = 2, at most n - 1 = 1 held out; the model's episodes stay play
    assert splits == {
        **{i: "val" if i in held_out_ids(["a0:0", "a1:0"], 0.6) else "train" for i in ("a0:0", "a1:0")},
        "p0:0": "play",
        "p1:0": "play",
        "p2:0": "play",
    }
    assert (summary.val, summary.annotated) == (1, 2)
