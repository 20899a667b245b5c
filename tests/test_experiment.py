"""`playseg experiment` at the tiny scale: every condition gives a row and the plots exist; a rerun
computes nothing again; a policy run depends on its seed only."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from playseg_core.checkpoint import file_digest
from playseg_core.experiment.conditions import (
    AddedSegments,
    balance_labels,
    check_conditions,
    ground_truth_added,
)
from playseg_core.experiment.runner import ExperimentData
from playseg_ros.cli import main as cli_main

pytestmark = pytest.mark.slow  # every test reads a small experiment that trains segmenters and policies

CONDITIONS = "gt_start,gt_2x,gt_100,oracle_relabel,random_relabel,gt_5pct,gt_50pct"


@pytest.fixture(scope="module")
def experiment(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("experiment")
    argv = ["experiment", "babyai", "--scale", "tiny", "--seeds", "2", "--out", str(out)]
    assert cli_main([*argv, "--workers", "2", "--conditions", CONDITIONS]) == 0
    return out


def test_every_condition_and_seed_gives_a_row_and_the_report_has_table_and_plots(experiment: Path) -> None:
    table = (experiment / "results.md").read_text()
    for condition in CONDITIONS.split(","):
        assert f"| {condition} |" in table
        for seed in (0, 1):
            row = json.loads((experiment / "runs" / f"{condition}-seed{seed}.json").read_text())
            assert row["condition"] == condition and row["seed"] == seed
            assert 0.0 <= row["success"] <= 1.0 and row["eval_episodes"] == 8
            assert len(row["episode_success"]) == 8
            assert row["episode_success"].count("1") == round(8 * row["success"])
            per_instruction = row["per_instruction"].values()
            assert sum(given for _, given in per_instruction) == 8
            assert sum(done for done, _ in per_instruction) == row["episode_success"].count("1")
    assert "0.544 +- 0.009" in table  # the paper's start split, next to ours
    assert "| gap recovered |" in table and "gap from gt_start to gt_100" in table  # recovered, or none
    for plot in ("success.png", "curve.png", "lengths.png", "labels.png", "gain.png"):
        assert (experiment / plot).stat().st_size > 1000


def test_conditions_add_what_they_say(experiment: Path) -> None:
    data = ExperimentData.open(experiment / "data")
    start = data.start_segments
    truth = {(e.episode_id, s.start, s.end) for e in data.play for s in e.segments}
    rows = {
        c: json.loads((experiment / "runs" / f"{c}-seed0.json").read_text()) for c in CONDITIONS.split(",")
    }
    assert rows["gt_start"]["segments"] == start and rows["gt_start"]["added_segments"] == 0
    assert rows["gt_2x"]["segments"] == 2 * start
    assert rows["gt_100"]["added_segments"] == len(truth)
    pool = start + len(truth)
    assert rows["gt_5pct"]["segments"] == round(0.05 * pool) < start  # part of the start split only
    assert rows["gt_5pct"]["added_segments"] == 0
    assert rows["gt_50pct"]["segments"] == round(0.5 * pool) > start  # the start split, then play's
    table = (experiment / "results.md").read_text()
    assert f"| gt_100 | {len(truth)} | 1.000 | 1.000 |" in table  # what it adds is the truth itself
    assert f"| oracle_relabel | {len(truth)} | 1.000 |" in table  # the true cuts, labels of a model
    oracle = AddedSegments.load(experiment / "added" / "oracle_relabel.json")
    spans = {(episode, s.start, s.end) for episode, found in oracle.by_episode.items() for s in found}
    assert spans == truth  # the true cuts, labels from the labelling model
    random = AddedSegments.load(experiment / "added" / "random_relabel.json")
    assert random.count > 0 and {s.instruction for f in random.by_episode.values() for s in f} <= set(
        data.instructions
    )


def test_a_rerun_computes_nothing_again_and_a_run_depends_on_its_seed_only(experiment: Path, capsys) -> None:
    runs = experiment / "runs"
    before = {p.name: p.stat().st_mtime_ns for p in runs.iterdir()}
    models = {p.name: p.stat().st_mtime_ns for p in (experiment / "models").iterdir()}
    first = json.loads((runs / "gt_2x-seed1.json").read_text())
    (runs / "gt_2x-seed1.json").unlink()  # computed again, in one worker this time
    argv = ["experiment", "babyai", "--scale", "tiny", "--seeds", "2", "--out", str(experiment)]
    assert cli_main([*argv, "--workers", "1", "--conditions", CONDITIONS]) == 0
    assert f"policy runs: {2 * len(CONDITIONS.split(','))} ({2 * len(CONDITIONS.split(',')) - 1} cached)" in (
        capsys.readouterr().out
    )
    after = {p.name: p.stat().st_mtime_ns for p in runs.iterdir()}
    assert {k: v for k, v in after.items() if k != "gt_2x-seed1.json"} == {
        k: v for k, v in before.items() if k != "gt_2x-seed1.json"
    }
    assert {p.name: p.stat().st_mtime_ns for p in (experiment / "models").iterdir()} == models
    again = json.loads((runs / "gt_2x-seed1.json").read_text())
    for key in ("success", "train_loss", "segments"):
        assert again[key] == first[key], key


def test_a_cache_made_from_a_file_replaced_since_is_refused_as_stale(
    experiment: Path, tmp_path: Path, capsys
) -> None:
    import shutil

    import torch

    out = tmp_path / "out"
    shutil.copytree(experiment, out, ignore=shutil.ignore_patterns("data"))
    (out / "data").symlink_to(experiment / "data")
    added = AddedSegments.load(out / "added" / "oracle_relabel.json")
    assert added.made_from == {"models/random.pt": file_digest(out / "models" / "random.pt")}
    assert json.loads((out / "runs" / "gt_2x-seed0.json").read_text())["added_digest"] == file_digest(
        out / "added" / "gt_2x.json"
    )
    argv = ["experiment", "babyai", "--scale", "tiny", "--seeds", "1", "--out", str(out)]
    assert cli_main([*argv, "--conditions", "gt_2x,oracle_relabel"]) == 0  # all cached, all current
    capsys.readouterr()
    found = AddedSegments.load(out / "found" / "random.json")  # random_relabel's windows, cut once
    assert found.made_from == added.made_from
    # A segmenter trained again: what its segments were made from is no longer there. Refused for the
    # conditions asked for and for those only reported (their cached runs are in the table too).
    checkpoint = torch.load(out / "models" / "random.pt", weights_only=True)
    checkpoint["meta"]["retrained"] = True
    torch.save(checkpoint, out / "models" / "random.pt")
    for asked in ("oracle_relabel", "gt_2x"):
        assert cli_main([*argv, "--conditions", asked]) == 1
        err = capsys.readouterr().err
        assert f"added/oracle_relabel.json: made from another {out / 'models' / 'random.pt'}" in err
        assert "Traceback" not in err
    # Their added segments and runs deleted, as the message says: cutting them again from the cached
    # cuts of play is refused too (cut by the old checkpoint).
    for condition in ("oracle_relabel", "random_relabel"):
        (out / "added" / f"{condition}.json").unlink()
        for seed in (0, 1):
            (out / "runs" / f"{condition}-seed{seed}.json").unlink()
    assert cli_main([*argv, "--conditions", "random_relabel"]) == 1
    assert f"found/random.json: made from another {out / 'models' / 'random.pt'}" in capsys.readouterr().err
    (out / "found" / "random.json").unlink()
    # Added segments made again, or gone: the policy runs trained on them are stale, asked for or not.
    gt_2x = AddedSegments.load(out / "added" / "gt_2x.json")
    AddedSegments("gt_2x", dict(list(gt_2x.by_episode.items())[1:])).save(out / "added" / "gt_2x.json")
    assert cli_main([*argv, "--conditions", "gt_start"]) == 1
    err = capsys.readouterr().err
    assert "runs/gt_2x-seed0.json: made from another" in err and "delete it to train that run again" in err
    (out / "added" / "gt_2x.json").unlink()
    assert cli_main([*argv, "--conditions", "gt_start"]) == 1
    assert f"made from {out / 'added' / 'gt_2x.json'}, which is missing" in capsys.readouterr().err


def test_the_report_covers_every_cached_run_whatever_was_asked_this_time(experiment: Path) -> None:
    argv = ["experiment", "babyai", "--scale", "tiny", "--seeds", "1", "--out", str(experiment)]
    assert cli_main([*argv, "--conditions", "gt_start"]) == 0  # cached: computes nothing
    table = (experiment / "results.md").read_text()
    for condition in CONDITIONS.split(","):
        row = next(line for line in table.splitlines() if line.startswith(f"| {condition} |"))
        assert "(2) |" in row  # both seeds of the first invocation


def test_ground_truth_conditions_and_unknown_names() -> None:
    from playseg_core.data.episode import Episode, Segment

    play = [
        Episode(f"e{i}", np.zeros((6, 1), np.float32), segments=[Segment(0, 2, "a"), Segment(2, 6, "b")])
        for i in range(3)
    ]  # 6 segments
    assert ground_truth_added("gt_start", play, 2).count == 0
    assert ground_truth_added("gt_2x", play, 2).count == 2
    assert ground_truth_added("gt_4x", play, 2).count == 6
    assert ground_truth_added("gt_4x", play, 3).count == 6  # no more than play holds
    assert ground_truth_added("gt_100", play, 1).count == 6
    assert ground_truth_added("gt_50pct", play, 2).count == 2  # (2 + 6) / 2 = 4 = 2 start + 2 added
    assert ground_truth_added("gt_25pct", play, 3).start_kept == 2  # 9 / 4 -> 2 of the 3 start segments
    with pytest.raises(ValueError, match=r"unknown conditions \['gt_3x'\]"):
        check_conditions(["ps", "gt_3x"])
    assert check_conditions(["curve", "gt_start", "ps"]) == [
        "gt_start", "gt_100", "gt_1pct", "gt_2pct", "gt_5pct", "gt_10pct", "gt_25pct", "gt_50pct", "ps"
    ]  # fmt: skip
    from playseg_core.experiment.runner import segmenter_methods

    # what must be trained first: PS for every filter of its cuts, the labelling model of both relabels
    conditions = ["ps_own_cuts_balanced", "gt_2x", "oracle_relabel", "ps_balanced", "random_relabel", "unloc"]
    assert segmenter_methods(conditions) == ["ps", "random", "unloc"]


def test_an_output_directory_of_another_experiment_is_refused(experiment: Path, capsys) -> None:
    argv = ["experiment", "babyai", "--scale", "small", "--seeds", "1", "--out", str(experiment)]
    assert cli_main(argv) == 1  # tiny results must never be reported as the small scale's
    error = capsys.readouterr().err.strip()
    assert "holds another experiment (scale, spec differ); use a new --out" in error and "\n" not in error
    a_file = experiment.parent / "notes.txt"
    a_file.write_text("kept")
    assert cli_main([*argv[:-1], str(a_file)]) == 1
    error = capsys.readouterr().err.strip()
    assert f"--out {a_file}: is a file" in error and "\n" not in error and a_file.read_text() == "kept"


def test_a_scale_s_segmenter_settings_reach_training(experiment: Path, tmp_path: Path) -> None:
    from dataclasses import replace

    from playseg_core.experiment.runner import ExperimentSpec, train_segmenter
    from playseg_core.ps.model import load_model

    (tmp_path / "data").symlink_to(experiment / "data")
    tiny = ExperimentSpec.of_domain("babyai").scale("tiny")
    rotated = replace(tiny, segmenter_reads_actions=False, segmenter_augment=True)
    for method, name in (("ps", "ps"), ("random", "random")):
        train_segmenter(str(tmp_path), method, rotated, 1)
        model, meta = load_model(tmp_path / "models" / f"{name}.pt")
        assert meta["train"]["augment"] is True
        assert not model.encoders.reads_actions  # only the observations are read
    default_model, default_meta = load_model(experiment / "models" / "random.pt")
    assert default_model.encoders.reads_actions and default_meta["train"]["augment"] is False


def test_an_experiment_recorded_before_a_scale_field_existed_still_resumes(experiment: Path) -> None:
    record = experiment / "experiment.json"
    written = record.read_text()
    held = json.loads(written)
    for name in ("segmenter_reads_actions", "segmenter_augment"):  # at their defaults in every scale
        del held["spec"][name]
    record.write_text(json.dumps(held))
    try:
        argv = ["experiment", "babyai", "--scale", "tiny", "--seeds", "1", "--out", str(experiment)]
        assert cli_main([*argv, "--conditions", "gt_start"]) == 0  # cached: nothing runs again
    finally:
        record.write_text(written)


def test_a_field_only_new_conditions_read_does_not_refuse_an_older_experiment(tmp_path: Path) -> None:
    from playseg_core.experiment.runner import ExperimentSpec, _check_same_experiment

    medium = ExperimentSpec.of_domain("tabletop").scale("medium")
    assert medium.own_cuts_accuracy is not None  # not the default: the case that was refused
    settings = {"domain": "tabletop", "scale": "medium", "spec": dataclasses.asdict(medium), "policy": "p"}
    older = json.loads(json.dumps(settings))
    del older["spec"]["own_cuts_accuracy"]  # written before the field existed
    (tmp_path / "experiment.json").write_text(json.dumps(older))
    _check_same_experiment(tmp_path, settings)  # resumes
    other = {**settings, "spec": {**settings["spec"], "segmenter_label_accuracy": 0.5}}
    with pytest.raises(ValueError, match="holds another experiment"):
        _check_same_experiment(tmp_path, other)  # a field the cached conditions read still counts


def test_balancing_caps_each_instruction_at_its_start_split_share() -> None:
    from playseg_core.data.episode import Episode, Segment

    def episode(name: str, labels: list[str], confidences: list[float] | None = None) -> Episode:
        confidences = confidences or [1.0] * len(labels)
        segments = [
            Segment(2 * i, 2 * i + 2, label, c)
            for i, (label, c) in enumerate(zip(labels, confidences, strict=True))
        ]
        return Episode(name, np.zeros((2 * len(labels), 1), np.float32), segments=segments)

    start = [episode("s", ["a", "a", "a", "b"])]  # a: 3/4, b: 1/4
    found = episode("p", ["b"] * 7 + ["a"] * 2 + ["c"], [0.1, 0.9, 0.2, 0.8, 0.3, 0.7, 0.5, 0.6, 0.4, 1.0])
    added = AddedSegments("ps", {"p": found.segments})
    balanced = balance_labels(added, "ps_balanced", start)  # of 10: a <= 8, b <= ceil(2.5) = 3, c 0
    kept = balanced.by_episode["p"]
    assert balanced.condition == "ps_balanced" and balanced.count == 5
    assert [(s.instruction, s.confidence) for s in kept] == [
        ("b", 0.9),
        ("b", 0.8),
        ("b", 0.7),
        ("a", 0.6),
        ("a", 0.4),
    ]
    even = AddedSegments("ps", {"p": found.segments[:1] + found.segments[7:9]})  # b, a, a: within the caps
    assert balance_labels(even, "ps_balanced", start).by_episode == even.by_episode
    with pytest.raises(ValueError, match="start split with annotated segments"):
        balance_labels(added, "ps_balanced", [episode("s", [])])


def test_the_balanced_condition_caps_what_ps_kept(experiment: Path, tmp_path: Path) -> None:
    from playseg_core.data.episode import Segment
    from playseg_core.experiment.runner import ExperimentSpec, _ensure_added

    data = ExperimentData.open(experiment / "data")
    start_labels = [s.instruction for e in data.start for s in e.segments]
    most = max(set(start_labels), key=start_labels.count)
    piled = {  # a segmenter that calls every true span of play the start split's commonest instruction
        e.episode_id: [Segment(s.start, s.end, most, 1.0) for s in e.segments] for e in data.play
    }
    (tmp_path / "added").mkdir()
    AddedSegments("ps", piled).save(tmp_path / "added" / "ps.json")
    tiny = ExperimentSpec.of_domain("babyai").scale("tiny")
    balanced = _ensure_added(tmp_path, "ps_balanced", data, tiny, lambda line: None)
    kept = sum(len(group) for group in piled.values())
    cap = -(-start_labels.count(most) * kept // len(start_labels))  # ceil(share of the start split x kept)
    assert balanced.count == cap < kept
    assert AddedSegments.load(tmp_path / "added" / "ps_balanced.json").count == balanced.count


def test_ps_conditions_filter_the_cuts_found_once(experiment: Path, tmp_path: Path) -> None:
    """``ps`` keeps cached cuts by the true-cut label threshold, ``ps_own_cuts`` by the own-cut one on
    the label's probability times the cut's; play is segmented once for both (out/found)."""
    from playseg_core.data.episode import Segment
    from playseg_core.experiment.runner import ExperimentSpec, _ensure_added, ensure_segmenter
    from playseg_core.ps.segmentation import segment_episode

    (tmp_path / "data").symlink_to(experiment / "data")
    data = ExperimentData.open(tmp_path / "data")
    tiny = ExperimentSpec.of_domain("babyai").scale("tiny")
    lines: list[str] = []
    segmenter = ensure_segmenter(tmp_path, "ps", data, tiny, lines.append)
    # val annotated as the model cuts and labels it: every own cut right, so the own-cut threshold keeps
    # down to the lowest val cut's score
    model = segmenter.model
    val = [e.with_segments(segment_episode(model, e.with_segments([]), model.cfg.min_len)) for e in data.val]
    data = dataclasses.replace(data, val=val)
    label = data.instructions[0]
    found = {  # per true span: sure of its cut and label / sure of its label, never of its cut
        e.episode_id: [
            Segment(s.start, s.end, label, 1.0, 0.0) if i % 2 else Segment(s.start, s.end, label, 1.0, -800.0)
            for i, s in enumerate(e.segments)
        ]
        for e in data.play
    }
    (tmp_path / "found").mkdir()
    AddedSegments("ps", found).save(tmp_path / "found" / "ps.json")
    assert AddedSegments.load(tmp_path / "found" / "ps.json").by_episode == found  # log_prob kept
    written_before = {"condition": "ps", "segments": {"e": [[0, 3, label, 0.5]]}, "start_kept": None}
    (tmp_path / "old.json").write_text(json.dumps(written_before))  # before log_prob was kept
    assert AddedSegments.load(tmp_path / "old.json").by_episode == {"e": [Segment(0, 3, label, 0.5, 0.0)]}
    own = _ensure_added(tmp_path, "ps_own_cuts", data, tiny, lines.append)
    assert {k: [(s.start, s.end) for s in v] for k, v in own.by_episode.items()} == {
        k: [(s.start, s.end) for s in v if s.log_prob == 0.0] for k, v in found.items()
    }
    assert own.count > 0 and ", 100% right)" in lines[-1]
    ps = _ensure_added(tmp_path, "ps", data, tiny, lines.append)  # by the checkpoint's threshold
    everything = sum(map(len, found.values()))
    assert ps.count == (everything if segmenter.label_threshold <= 1.0 else 0)
    assert f"{ps.count} of {everything} segments kept from play" in lines[-1]
