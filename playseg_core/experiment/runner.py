"""Runs the augmentation experiment for one domain and scale, caching every stage under ``out``:

    out/data/                 the domain's generated dataset: train (= the annotated start split), val,
                              play (the rest of the pool, ground truth kept for the gt_* conditions), test
    out/models/<method>.pt    each segmentation method trained on the start split (baselines/registry.py)
    out/found/<method>.json   every segment that method cut from play (the conditions filter these)
    out/added/<cond>.json     the segments each condition adds from play
    out/runs/<cond>-seed<s>.json   one policy trained and evaluated: success, segments, time
    out/results.md, out/*.png the table next to the paper's figures and the plots (report.py)

A stage whose file exists is not run again, and every file appears only when complete, so an
interrupted run resumes where it stopped. What a stage made from another stage's file records that
file's digest (found and added segments: the checkpoints they come from; a policy run: its added
segments), so a file made from one that has since been replaced (a segmenter trained again) is reported
as stale, never reported under the new one. Policy runs of different conditions and seeds are independent
and run in a process pool (``workers``); each uses one torch thread, so a run's result depends on its
seed only, not on the number of workers.
"""

from __future__ import annotations

import json
import os
import time
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor
from contextlib import nullcontext
from dataclasses import MISSING, asdict, dataclass, fields
from multiprocessing import get_context
from pathlib import Path
from typing import Any

from playseg_core.augment.policies import load_policy_learner
from playseg_core.augment.policy import torch_threads
from playseg_core.augment.retraining import annotated_clips
from playseg_core.checkpoint import file_digest
from playseg_core.data.dataset import is_dataset
from playseg_core.domains import load_domain
from playseg_core.errors import PlaysegError
from playseg_core.experiment.conditions import (
    BALANCED,
    CONDITIONS,
    KNOWN_CONDITIONS,
    OWN_CUTS,
    SEGMENTER_CONDITIONS,
    AddedSegments,
    balance_labels,
    check_conditions,
    ground_truth_added,
    pool_percent,
    pool_share_segments,
)
from playseg_core.experiment.spec import NEW_CONDITIONS_ONLY, ExperimentData, ExperimentScale, ExperimentSpec

EVAL_SEED = 1_000_000
"""First seed of the fixed evaluation episodes (disjoint from play generation), the same for every run."""
RUN_THREADS = 1
"""Torch threads of one policy run or segmenter training, whatever the number of workers: a result
depends on its seed only."""


@dataclass(frozen=True)
class RunSettings:
    """Everything one policy run needs (picklable, for the process pool)."""

    out: str
    condition: str
    seed: int
    policy: str
    policy_config: dict[str, Any]
    eval_episodes: int
    threads: int
    device: str = "auto"  # training/device.py

    @property
    def result_path(self) -> Path:
        """Where this run's row is cached."""
        return Path(self.out) / "runs" / f"{self.condition}-seed{self.seed}.json"


def run_experiment(
    domain: str,
    scale_name: str,
    seeds: int,
    out: str | Path,
    workers: int = 1,
    conditions: Sequence[str] = CONDITIONS,
    log: Callable[[str], None] = print,
    device: str = "auto",
) -> list[dict[str, Any]]:
    """Every condition x seed of the experiment (cached stages skipped), segmenters and policies trained
    and run on ``device`` (training/device.py; not part of the cache key); returns the run rows and
    writes the report."""
    from playseg_core.experiment.report import write_report
    from playseg_core.training.device import resolve_device

    resolve_device(device)  # DeviceError (one line) before any work

    if seeds < 1 or workers < 1:
        raise PlaysegError(f"--seeds and --workers must be >= 1, got {seeds} and {workers}")
    spec = ExperimentSpec.of_domain(domain)
    scale = spec.scale(scale_name)
    conditions = check_conditions(conditions)
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise FileExistsError(f"--out {out}: is a file, expected the experiment's directory")
    began = time.perf_counter()
    _check_same_experiment(
        out, {"domain": domain, "scale": scale_name, "spec": asdict(scale), "policy": spec.policy}
    )
    data_dir = _ensure_data(out, domain, scale, workers, log)
    data = ExperimentData.open(data_dir)
    conditions = [c for c in conditions if not _repeats_start_split(c, data)]
    log(
        f"data {data_dir}: start split {len(data.start)} episodes ({data.start_segments} segments), "
        f"play {len(data.play)} episodes ({sum(len(e.segments) for e in data.play)} ground-truth segments)"
    )
    _train_segmenters(out, segmenter_methods(conditions), scale, workers, log, device)
    added = {condition: _ensure_added(out, condition, data, scale, log, device) for condition in conditions}
    added |= _check_cached_runs(out, added)  # every cached run, asked for this time or only reported
    runs = [
        RunSettings(
            str(out), condition, seed, spec.policy, scale.policy, scale.eval_episodes, RUN_THREADS, device
        )
        for seed in range(seeds)  # every condition's seed 0 first: an interrupted run has whole rows
        for condition in conditions
    ]
    rows = _run_policies(runs, workers, log)
    reported = cached_rows(out)  # what earlier invocations ran too (other conditions, more seeds)
    for condition in {row["condition"] for row in reported} - added.keys():  # a run without its added file
        added[condition] = load_cached_segments(out, out / "added" / f"{condition}.json")
    added = dict(sorted(added.items(), key=lambda item: table_position(item[0])))
    write_report(out, spec, scale_name, reported, data, added)
    log(f"experiment done in {time.perf_counter() - began:.0f} s: {out / 'results.md'}")
    return rows


def cached_rows(out: Path) -> list[dict[str, Any]]:
    """Every finished policy run under out/runs, in table order (the known conditions' order, then
    seed)."""
    rows = [json.loads(path.read_text()) for path in (out / "runs").glob("*-seed*.json")]
    return sorted(rows, key=lambda row: (table_position(row["condition"]), row["seed"]))


def table_position(condition: str) -> int:
    """Where a condition's rows go in the report: the known conditions' order, unknown ones last."""
    return KNOWN_CONDITIONS.index(condition) if condition in KNOWN_CONDITIONS else len(KNOWN_CONDITIONS)


def _repeats_start_split(condition: str, data: ExperimentData) -> bool:
    """A point of the ground-truth curve that trains on exactly the start split: gt_start again."""
    percent = pool_percent(condition)
    if percent is None:
        return False
    return pool_share_segments(percent, data.play, data.start_segments) == data.start_segments


def _check_same_experiment(out: Path, settings: dict[str, Any]) -> None:
    """Record what ``out`` caches (out/experiment.json); ValueError when it holds another experiment, so
    cached results are never reported under another scale or budget, FileExistsError when it is a
    non-empty directory without that record."""
    path = out / "experiment.json"
    recorded = json.loads(json.dumps(settings))  # as it reads back (tuples become lists)
    if not path.exists() and out.is_dir() and any(out.iterdir()):
        # its files would be taken for cached stages (a models/ps.pt trusted as this run's segmenter)
        raise FileExistsError(
            f"--out {out}: a non-empty directory that holds no experiment (no experiment.json); "
            "give a new or empty directory"
        )
    if path.exists():
        held = json.loads(path.read_text())
        # A scale field added after ``out`` was written, at its default, is what that experiment ran
        # (one that only new conditions read: whatever it is now).
        defaults = {f.name: f.default for f in fields(ExperimentScale) if f.default is not MISSING}
        defaults |= {k: v for k, v in recorded.get("spec", {}).items() if k in NEW_CONDITIONS_ONLY}
        held_spec = held.get("spec")
        if isinstance(held_spec, dict):
            held["spec"] = {k: defaults[k] for k in defaults.keys() - held_spec.keys()} | held_spec
        if held != recorded:
            changed = sorted(k for k in recorded if held.get(k) != recorded[k])
            raise PlaysegError(
                f"--out {out}: holds another experiment ({', '.join(changed)} differ); use a new --out"
            )
        return
    out.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(recorded, indent=2))


def _ensure_data(out: Path, domain: str, scale: ExperimentScale, workers: int, log) -> Path:
    path = out / "data"
    if is_dataset(path):
        return path
    if path.exists():  # not ours to replace (the dataset writer's refusal names an option we lack)
        raise FileExistsError(f"--out {out}: {path} exists and is not a playseg dataset; move it away")
    log(f"generating {domain} play, preset {scale.preset!r}, start split {scale.start_share:.0%} ...")
    out.mkdir(parents=True, exist_ok=True)
    load_domain(domain).generate_dataset(
        path, scale.preset, seed=0, workers=workers, progress=False, annotated_share=scale.start_share
    )
    return path


def segmenter_method(condition: str) -> str:
    """The segmentation method whose cuts of play a (not balanced) segmenter condition filters."""
    return OWN_CUTS.get(condition) or SEGMENTER_CONDITIONS.get(condition, condition)


def segmenter_methods(conditions: Sequence[str]) -> list[str]:
    """The segmentation methods (baselines/registry.py) the conditions need trained on the start split."""
    methods = [segmenter_method(BALANCED.get(c, c)) for c in conditions if not c.startswith("gt_")]
    return list(dict.fromkeys("random" if m == "oracle_relabel" else m for m in methods))


def _models_digest(out: Path, methods: Sequence[str]) -> dict[str, str]:
    """What segments made by ``methods`` record they were made from: models/<method>.pt -> digest."""
    return {f"models/{method}.pt": file_digest(out / "models" / f"{method}.pt") for method in methods}


def _check_made_from(out: Path, path: Path, made_from: dict[str, str] | None, redo: str) -> None:
    """ValueError when a file the cached ``path`` was made from (``made_from``: path under ``out`` ->
    digest) is missing or no longer what it was, saying what to delete (``redo``); a file without the
    record is trusted (there is nothing to check it against)."""
    for name, digest in (made_from or {}).items():
        source = out / name
        if not source.exists():
            raise PlaysegError(f"{path}: made from {source}, which is missing; {redo}")
        if file_digest(source) != digest:
            raise PlaysegError(f"{path}: made from another {source} than the one there now; {redo}")


def load_cached_segments(out: Path, path: Path) -> AddedSegments:
    """A cached file of segments (out/found or out/added), checked against the checkpoints it was made
    from: ValueError when one has been replaced since (a segmenter trained again)."""
    segments = AddedSegments.load(path)
    redo = "delete it and the out/added and out/runs files of the conditions made from it to redo them"
    _check_made_from(out, path, segments.made_from, redo)
    return segments


def _check_cached_runs(out: Path, loaded: dict[str, AddedSegments]) -> dict[str, AddedSegments]:
    """ValueError when a cached policy run trained on other added segments than out/added holds now
    (made again since), or those were made from a checkpoint replaced since: before anything runs or is
    reported. Returns the added segments of the runs' conditions not in ``loaded`` (for the report)."""
    rows = [(path, json.loads(path.read_text())) for path in sorted((out / "runs").glob("*-seed*.json"))]
    more = {}
    for condition in sorted({row["condition"] for _, row in rows} - loaded.keys()):
        if (out / "added" / f"{condition}.json").exists():
            more[condition] = load_cached_segments(out, out / "added" / f"{condition}.json")
    for path, row in rows:
        if row.get("added_digest") is not None:
            added = {f"added/{row['condition']}.json": row["added_digest"]}
            _check_made_from(out, path, added, "delete it to train that run again")
    return more


def train_on_start_split(
    data: ExperimentData, method: str, scale: ExperimentScale, threads: int, device: str = "auto"
) -> Any:
    """``method`` trained on ``data``'s start split with the scale's segmenter settings (its trained
    segmenter: ``save``, ``report``)."""
    from playseg_core.baselines.common import TrainingData, TrainOptions
    from playseg_core.baselines.registry import get_method

    training = TrainingData(
        data.start,
        data.val,
        data.instructions,
        data.features,
        data.domain,
        read_actions=scale.segmenter_reads_actions,
        augment=scale.segmenter_augment,
    )
    options = TrainOptions(
        seed=0,
        max_steps=scale.segmenter_steps,
        num_threads=threads,
        label_accuracy=scale.segmenter_label_accuracy,
        device=device,
    )
    with torch_threads(threads):
        return get_method(method).train(training, options)


def train_segmenter(out: str, method: str, scale: ExperimentScale, threads: int, device: str = "auto") -> str:
    """Train ``method`` on the start split of out/data into out/models/<method>.pt (skipped when there),
    with the scale's segmenter settings; its one-line report. A top-level function so that a process
    pool can run it."""
    path = Path(out) / "models" / f"{method}.pt"
    if path.exists():
        return f"{method}: cached in {path}"
    data = ExperimentData.open(Path(out) / "data")
    trained = train_on_start_split(data, method, scale, threads, device)
    path.parent.mkdir(parents=True, exist_ok=True)
    partial = path.with_name(f".{path.name}.partial")
    trained.save(partial, {"experiment": {"start_segments": data.start_segments}})
    os.replace(partial, path)
    return f"{trained.report} -> {path}"


def _train_segmenters(
    out: Path, methods: list[str], scale: ExperimentScale, workers: int, log, device: str
) -> None:
    """Every missing segmenter, in parallel when there are workers for it; one torch thread each, so a
    model does not depend on the number of workers."""
    missing = [m for m in methods if not (out / "models" / f"{m}.pt").exists()]
    if not missing:
        return
    log(f"training {', '.join(missing)} on the start split ({min(workers, len(missing))} at a time) ...")
    jobs = [(str(out), m, scale, RUN_THREADS, device) for m in missing]
    if workers > 1 and len(missing) > 1:
        with ProcessPoolExecutor(min(workers, len(missing)), mp_context=get_context("spawn")) as pool:
            reports = list(pool.map(train_segmenter, *zip(*jobs, strict=True)))
    else:
        reports = [train_segmenter(*job) for job in jobs]
    for report in reports:
        log(f"  {report}")


def ensure_segmenter(
    out: Path, method: str, data: ExperimentData, scale: ExperimentScale, log, device: str = "auto"
) -> Any:
    """The segmentation method trained on the start split (cached in out/models), loaded back."""
    from playseg_core.baselines.common import SegmentOptions
    from playseg_core.baselines.registry import load_segmenter

    if not (out / "models" / f"{method}.pt").exists():
        log(f"  {train_segmenter(str(out), method, scale, RUN_THREADS, device)}")
    return load_segmenter(method, out / "models" / f"{method}.pt", SegmentOptions(seed=0, device=device))


def _ensure_added(
    out: Path, condition: str, data: ExperimentData, scale: ExperimentScale, log, device: str = "auto"
) -> AddedSegments:
    path = out / "added" / f"{condition}.json"
    if path.exists():
        return load_cached_segments(out, path)
    if condition.startswith("gt_"):
        added = ground_truth_added(condition, data.play, data.start_segments)
    elif condition in BALANCED:
        base = _ensure_added(out, BALANCED[condition], data, scale, log, device)
        added = balance_labels(base, condition, data.start)
        log(f"  {condition}: {added.count} of {base.count} segments kept, each instruction capped")
    elif condition == "oracle_relabel":
        from playseg_core.baselines.labelled_pieces import label_pieces

        labeller = ensure_segmenter(out, "random", data, scale, log, device).model  # random windows' labeller
        added = AddedSegments(
            condition,
            {
                episode.episode_id: label_pieces(
                    labeller, episode, [(s.start, s.end) for s in episode.segments]
                )
                for episode in data.play
            },
            made_from=_models_digest(out, ["random"]),
        )
    else:
        method = segmenter_method(condition)
        segmenter = ensure_segmenter(out, method, data, scale, log, device)
        found = _found_segments(out, method, segmenter, data, log)
        if condition in OWN_CUTS:
            from playseg_core.ps.calibration import calibrate_on_own_cuts
            from playseg_core.ps.labelling import KeepRule

            target = scale.own_cuts_accuracy or scale.segmenter_label_accuracy
            calibration = calibrate_on_own_cuts(segmenter.model, data.val, target)
            rule = KeepRule("own_cuts", calibration.threshold)
            how = (
                f"{rule.describe()} for {target:.0%}: {calibration.coverage:.0%} of the "
                f"{calibration.num_segments} val cuts kept, {calibration.accuracy_kept:.0%} right"
            )
        else:
            rule = segmenter.keep_rule("label")
            how = rule.describe()
        added = AddedSegments(
            condition,
            {
                episode_id: [s for s in segments if rule.keeps(s)]
                for episode_id, segments in found.by_episode.items()
            },
            made_from=found.made_from,
        )
        log(f"  {condition}: {added.count} of {found.count} segments kept from play ({how})")
    path.parent.mkdir(parents=True, exist_ok=True)
    added.save(path)
    return added


def _found_segments(out: Path, method: str, segmenter: Any, data: ExperimentData, log) -> AddedSegments:
    """Every segment ``segmenter`` cuts from play, unfiltered (cached in out/found/<method>.json: the
    conditions that keep different ones of them segment play once)."""
    path = out / "found" / f"{method}.json"
    if path.exists():
        return load_cached_segments(out, path)
    began = time.perf_counter()
    found = AddedSegments(
        method,  # the segmenter never sees the truth
        {episode.episode_id: segmenter.segment(episode.with_segments([])) for episode in data.play},
        made_from=_models_digest(out, [method]),
    )
    log(f"  {method}: play segmented in {time.perf_counter() - began:.0f} s ({found.count} segments)")
    path.parent.mkdir(parents=True, exist_ok=True)
    found.save(path)
    return found


def training_clips(data: ExperimentData, added: AddedSegments) -> list:
    """The start split's annotated clips (the first ``added.start_kept`` of them when set), then the added
    segments' clips in play order."""
    clips = annotated_clips(data.start)[: added.start_kept]
    for episode in data.play:
        segments = added.by_episode.get(episode.episode_id)
        if segments:
            clips += annotated_clips([episode.with_segments(segments)])
    return clips


def run_policy(settings: RunSettings) -> dict[str, Any]:
    """Train and evaluate one policy (cached in out/runs); the row of the results table."""
    out = Path(settings.out)
    path = settings.result_path
    if path.exists():
        return json.loads(path.read_text())
    data = ExperimentData.open(out / "data")
    added_path = out / "added" / f"{settings.condition}.json"
    added = AddedSegments.load(added_path)
    clips = training_clips(data, added)
    config = {**settings.policy_config, "seed": settings.seed, "device": settings.device}
    learner = load_policy_learner(settings.policy, config, features=data.features)
    began = time.perf_counter()
    with torch_threads(settings.threads):
        model, report = learner.train(clips)
        evaluation = learner.evaluate(model, settings.eval_episodes, EVAL_SEED)
    row = {
        "condition": settings.condition,
        "seed": settings.seed,
        "segments": len(clips),
        "added_segments": added.count,
        "added_digest": file_digest(added_path),  # what it trained on: a stale run is found by it
        "success": None if evaluation is None else evaluation.success_rate,
        "eval_episodes": 0 if evaluation is None else evaluation.num_episodes,
        # episode by episode ("1" = success), for paired comparisons of conditions on the same episodes
        "episode_success": ""
        if evaluation is None
        else "".join("01"[ok] for ok in evaluation.episode_success),
        "per_instruction": {} if evaluation is None else per_instruction_success(evaluation),
        "val_loss": report.val_loss,
        "val_accuracy": report.val_accuracy,
        "train_loss": report.final_loss,
        "seconds": time.perf_counter() - began,
    }
    path.parent.mkdir(parents=True, exist_ok=True)
    partial = path.with_name(f".{path.name}.partial")
    partial.write_text(json.dumps(row, indent=2))
    os.replace(partial, path)
    return row


def per_instruction_success(evaluation: Any) -> dict[str, list[int]]:
    """instruction -> [successes, episodes] of an evaluation (empty when it names no instructions)."""
    counts: dict[str, list[int]] = {}
    for instruction, ok in zip(evaluation.episode_instructions, evaluation.episode_success, strict=False):
        entry = counts.setdefault(instruction, [0, 0])
        entry[0] += int(ok)
        entry[1] += 1
    return dict(sorted(counts.items()))


def _run_policies(runs: list[RunSettings], workers: int, log) -> list[dict[str, Any]]:
    cached = [run for run in runs if run.result_path.exists()]
    log(f"policy runs: {len(runs)} ({len(cached)} cached), {workers} worker(s)")
    # spawn: a fresh interpreter per worker (forking a process that already ran torch can deadlock)
    pool = ProcessPoolExecutor(workers, mp_context=get_context("spawn")) if workers > 1 else nullcontext()
    rows = []
    with pool:
        for row in (pool.map if workers > 1 else map)(run_policy, runs):
            rows.append(row)
            _log_row(row, log)
    return rows


def _log_row(row: dict[str, Any], log) -> None:
    figure = "no simulator" if row["success"] is None else f"success {row['success']:.3f}"
    log(
        f"  {row['condition']} seed {row['seed']}: {row['segments']} segments, {figure} ({row['seconds']:.0f} s)"
    )
