"""`playseg convert`: many bags, a process pool, one dataset; resumable.

Each bag is converted on its own (in a worker process) into a *part*: a complete playseg dataset under
``.<OUT>.convert/`` next to ``OUT``, written through a staging directory and renamed when finished, so an
unfinished part never looks finished. When the bags are done, the parts (and the bags an earlier run put
into ``OUT``) are merged into ``OUT``, again through a staging directory; merged parts are removed.

Resuming: ``OUT``'s meta/info.json lists the bags it holds (path and a fingerprint of their files) and the
mapping's digest; a rerun skips those bags, and bags whose part is finished, and converts the rest. A bag
that fails is reported in one line and skipped; the others convert and are merged, and the run exits
non-zero. Episodes with annotations land in the ``train`` split (with their segments), the others in
``play`` (with ``--segment MODEL``, with the model's segments: segmenting.py). ``--format lerobot`` keeps that dataset as ``.<OUT>.playseg`` and exports it to ``OUT`` as a
LeRobot v3.0 dataset (lerobot.py).

Validation split: parts hold their annotated episodes in ``train``; the merge, which sees every episode of
``OUT`` (earlier runs' and new ones), moves ``val_share`` of them to ``val`` by
`playseg_core.data.splits.held_out_ids` over their final ids, so the split depends on the set of annotated
episodes only (not on workers, engine or order). ``OUT``'s meta records the share; a rerun with another
share merges again (rewrites ``OUT`` with the new split) even when no bag is new.
"""

from __future__ import annotations

import hashlib
import multiprocessing
import os
import shutil
import sys
import time
from collections.abc import Callable, Sequence
from concurrent.futures import Future, ProcessPoolExecutor, as_completed
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Literal, NotRequired, TypedDict

from playseg_core.data.dataset import DatasetWriter, PlayDataset, check_out_apart, is_dataset
from playseg_core.data.episode import Episode
from playseg_core.data.features import Features
from playseg_core.data.splits import ANNOTATED_SPLITS, DEFAULT_VAL_SHARE, annotated_splits
from playseg_core.errors import PlaysegError
from playseg_ros.convert.build import convert_bag
from playseg_ros.convert.errors import ConvertError
from playseg_ros.convert.mapping import ConvertMapping
from playseg_ros.convert.segmenting import SegmentationSpec, segment_unannotated
from playseg_ros.convert.source import bag_size, find_bags, fingerprint, is_play_bag

OutputFormat = Literal["playseg", "lerobot"]
OUTPUT_FORMATS: tuple[OutputFormat, ...] = ("playseg", "lerobot")
Engine = Literal["local", "ray"]
ENGINES: tuple[Engine, ...] = ("local", "ray")
CONVERT_META = "convert"
"""The key of meta/info.json's ``meta`` that records what a conversion put into a dataset."""


class BagRecordJson(TypedDict):
    """One converted bag as a dataset's ``meta.convert.bags`` records it."""

    fingerprint: str
    episodes: int
    name: str


class ConvertMetaJson(TypedDict):
    mapping_digest: str | None
    mapping: NotRequired[str | None]
    segmentation: NotRequired[dict[str, Any] | None]  # SegmentationSpec.describe() and the label threshold
    val_share: NotRequired[float]  # the share of annotated episodes in ``val`` (absent: written before it)
    bags: dict[str, BagRecordJson]  # by the bag's absolute path


@dataclass(frozen=True)
class BagTask:
    bag: Path
    fingerprint: str
    part: Path
    mapping: ConvertMapping | None
    segmentation: SegmentationSpec | None = None


@dataclass
class BagReport:
    """What became of one bag."""

    bag: Path
    status: str  # "converted", "skipped" (in OUT already), "finished" (a part from an earlier run), "failed"
    error: str | None = None
    episodes: int = 0
    steps: int = 0
    segments: int = 0
    model_segments: int = 0  # of ``segments``: given by the --segment model (the rest are human labels)
    dropped_steps: int = 0
    notes: list[str] = field(default_factory=list)
    bytes: int = 0


@dataclass
class ConvertSummary:
    out: Path
    reports: list[BagReport]
    seconds: float = 0.0
    val_share: float = DEFAULT_VAL_SHARE
    annotated: int = 0  # annotated episodes in the dataset (train + val)
    val: int = 0  # of them, in ``val``
    resplit_from: float | None = None  # the share an earlier run split with, when this run re-split

    def count(self, status: str) -> int:
        return sum(r.status == status for r in self.reports)

    @property
    def failed(self) -> list[BagReport]:
        return [r for r in self.reports if r.status == "failed"]

    def totals(self) -> dict[str, int]:
        done = [r for r in self.reports if r.status in ("converted", "finished")]
        return {
            key: sum(getattr(r, key) for r in done)
            for key in ("episodes", "steps", "segments", "model_segments", "dropped_steps")
        }

    def text(self) -> str:
        totals = self.totals()
        return (
            f"{self.out}: {len(self.reports)} bags: {self.count('converted') + self.count('finished')} converted, "
            f"{self.count('skipped')} skipped (already in the dataset), {self.count('failed')} failed; "
            f"{totals['episodes']} episodes, {totals['steps']} steps, {totals['segments']} segments"
            + (f" ({totals['model_segments']} by the model)" if totals["model_segments"] else "")
            + f", {totals['dropped_steps']} dropped steps"
        )

    def val_text(self) -> str:
        """How many annotated episodes are held out for validation, e.g. "val: 2 of 10 annotated episodes
        (--val-share 0.2)"."""
        was = f"; re-split, was {self.resplit_from:g}" if self.resplit_from is not None else ""
        return f"val: {self.val} of {self.annotated} annotated episodes (--val-share {self.val_share:g}{was})"


def playseg_copy(lerobot_out: Path) -> Path:
    """Where the playseg dataset behind a LeRobot export is kept (what a rerun resumes from)."""
    return lerobot_out.with_name(f".{lerobot_out.name}.playseg")


def parts_dir(out: Path) -> Path:
    return out.with_name(f".{out.name}.convert")


def part_path(out: Path, bag: Path) -> Path:
    digest = hashlib.sha256(str(bag).encode()).hexdigest()[:12]
    return parts_dir(out) / f"{bag.name}-{digest}"


def convert_meta(dataset: PlayDataset) -> ConvertMetaJson | None:
    meta = dataset.info.get("meta", {}).get(CONVERT_META)
    return meta if isinstance(meta, dict) and isinstance(meta.get("bags"), dict) else None


def split_of(episode: Episode) -> str:
    """An episode's split in its bag's part: annotated ones in ``train`` (the merge moves a share of them to
    ``val``), the others in ``play``."""
    return "train" if episode.segments else "play"


def convert_one(task: BagTask) -> BagReport:
    """Convert one bag into its part (a worker's job). Bad input is reported, never raised."""
    report = BagReport(task.bag, "converted", bytes=bag_size(task.bag))
    try:
        if task.mapping is None or is_play_bag(task.bag):
            episodes, features, notes, dropped = _play_bag_episodes(task)
        else:
            converted = convert_bag(task.bag, task.mapping)
            episodes, features, notes, dropped = (
                converted.episodes,
                converted.features,
                converted.notes,
                converted.dropped_steps,
            )
        report.notes, report.dropped_steps = notes, dropped
        if not episodes:
            raise ConvertError(
                task.bag, f"no episode left ({dropped} steps dropped: {'; '.join(notes) or 'empty'})"
            )
        predicted: set[str] = set()  # ids of the episodes the model segmented
        if task.segmentation is not None:
            annotated = {e.episode_id for e in episodes if e.segments}
            segmented = segment_unannotated(task.bag, episodes, features, task.segmentation)
            episodes, report.model_segments = segmented.episodes, segmented.model_segments
            predicted = {e.episode_id for e in episodes} - annotated
            notes = report.notes = notes + segmented.notes
        instructions = sorted({s.instruction for e in episodes for s in e.segments if s.instruction})
        meta = {CONVERT_META: {"bag": str(task.bag), "fingerprint": task.fingerprint,
                               "mapping_digest": task.mapping.digest if task.mapping else None,
                               "segmentation_digest": _digest(task.segmentation),
                               "model_segments": report.model_segments,
                               "notes": notes, "dropped_steps": dropped}}  # fmt: skip
        with DatasetWriter(task.part, instructions, meta=meta, overwrite=True, features=features) as writer:
            for episode in episodes:
                split = "play" if episode.episode_id in predicted else split_of(episode)
                writer.add(episode, split, extra={"bag": str(task.bag)})
                report.episodes += 1
                report.steps += episode.num_steps
                report.segments += len(episode.segments)
    except (ValueError, OSError) as error:  # BagError, ConvertError, FeatureError, DatasetError, a full disk
        report.status, report.error = "failed", _one_line(error)
    return report


def _play_bag_episodes(task: BagTask) -> tuple[list[Episode], Features | None, list[str], int]:
    from playseg_ros.play_bags import iter_play_bag, read_play_bag_info

    if not is_play_bag(task.bag):
        raise ConvertError(task.bag, "not a playseg play bag: give a mapping (--mapping MAP.yaml)")
    info = read_play_bag_info(task.bag)
    incomplete: list[str] = []
    episodes = list(
        iter_play_bag(task.bag, incomplete="drop", on_incomplete=lambda e, s: incomplete.append(e))
    )
    notes = [f"episode {e!r} cut off before its end; dropped" for e in incomplete]
    return episodes, info.features, notes, 0


def _digest(segmentation: SegmentationSpec | None) -> str | None:
    return segmentation.digest if segmentation is not None else None


def _one_line(error: BaseException) -> str:
    return " ".join((str(error) or type(error).__name__).split())


def convert(
    inputs: Sequence[str | Path],
    out: str | Path,
    mapping: ConvertMapping | None,
    workers: int = 1,
    overwrite: bool = False,
    progress: bool = True,
    on_report: Callable[[BagReport], None] | None = None,
    output_format: OutputFormat = "playseg",
    segmentation: SegmentationSpec | None = None,
    engine: Engine = "local",
    address: str | None = None,
    val_share: float = DEFAULT_VAL_SHARE,
) -> ConvertSummary:
    """Convert the bags named by ``inputs`` into the playseg dataset ``out`` (see the module docstring).

    With ``segmentation`` the unannotated episodes are segmented by its model (segmenting.py). ``engine``
    "ray" runs the bags as Ray tasks (`_run_ray_tasks`; ``address`` joins a cluster), with the same output.
    ``val_share`` of the annotated episodes go to ``val`` (`held_out_ids`: none with fewer than two; 0: all
    in ``train``); a rerun with another share re-splits the whole dataset.

    With ``output_format="lerobot"`` the playseg dataset is kept next to ``out`` as ``.<OUT>.playseg``
    (what a rerun resumes from) and exported to ``out`` as a LeRobot v3.0 dataset (lerobot.py) whenever
    it changed or ``out`` is missing."""
    started = time.perf_counter()
    if workers < 1:
        raise PlaysegError(f"--workers must be >= 1, got {workers}")
    if engine not in ENGINES:
        raise PlaysegError(f"--engine {engine!r}: expected one of {', '.join(ENGINES)}")
    if address is not None and engine != "ray":
        raise PlaysegError("--address is the Ray cluster to join: give --engine ray")
    if output_format not in OUTPUT_FORMATS:
        raise PlaysegError(f"--format {output_format!r}: expected one of {', '.join(OUTPUT_FORMATS)}")
    if not 0.0 <= val_share < 1.0:  # also NaN
        raise PlaysegError(f"--val-share must be in [0, 1), got {val_share}")
    from playseg_ros.convert.lerobot import export_lerobot, is_lerobot_dataset  # PyAV, pyarrow: only here

    export_to = Path(out).resolve() if output_format == "lerobot" else None
    if export_to is not None and export_to.exists() and not is_lerobot_dataset(export_to):
        raise FileExistsError(f"{export_to}: exists and is not a LeRobot dataset; refusing to write into it")
    out = playseg_copy(export_to) if export_to is not None else Path(out).resolve()
    bags = find_bags(inputs)
    if not bags:
        raise PlaysegError(f"{', '.join(map(str, inputs))}: no bags found")
    written = [out] if export_to is None else [out, export_to]
    for bag in bags:  # writing (or --overwrite replacing) the output would delete a bag inside it
        for directory in written:
            check_out_apart(directory, bag)
    if segmentation is not None and workers > 1 and segmentation.threads is None:
        segmentation = replace(segmentation, threads=max(1, (os.cpu_count() or 1) // workers))
    if segmentation is not None:
        from playseg_ros.convert.segmenting import calibration_warning, keep_rule

        keep_rule(segmentation)  # a checkpoint without the rule's calibration fails before any bag is read
        warning = calibration_warning(segmentation)
        if warning:
            print(warning, file=sys.stderr)
    previous = _previous_dataset(out, mapping, overwrite, segmentation)
    done = {} if previous is None else convert_meta(previous)["bags"]  # type: ignore[index]
    earlier_share = None if previous is None else convert_meta(previous).get("val_share")  # type: ignore[union-attr]
    resplit = previous is not None and earlier_share != val_share
    reports: dict[Path, BagReport] = {}
    tasks: list[BagTask] = []
    for bag in bags:
        stamp = fingerprint(bag)
        if done.get(str(bag), {}).get("fingerprint") == stamp:
            reports[bag] = BagReport(bag, "skipped")
            continue
        task = BagTask(bag, stamp, part_path(out, bag), mapping, segmentation)
        if _finished_part(task) is not None:
            reports[bag] = _report_of_part(task)
            continue
        tasks.append(task)
    for report in _run_tasks(tasks, workers, progress, engine, address):
        reports[report.bag] = report
        if on_report is not None:
            on_report(report)
    ordered = [reports[bag] for bag in bags]
    merged = [r for r in ordered if r.status in ("converted", "finished")]
    if merged or resplit:
        _merge(out, previous, [(r, part_path(out, r.bag)) for r in merged], mapping, segmentation, val_share)
    if parts_dir(out).is_dir() and not any(parts_dir(out).iterdir()):
        parts_dir(out).rmdir()  # every part merged: nothing left to resume from
    if (
        export_to is not None
        and is_dataset(out)
        and (any(r.status != "failed" for r in merged) or not export_to.exists())
    ):
        export_lerobot(PlayDataset.open(out), export_to, overwrite=True)  # every split: val changes nothing
    summary = ConvertSummary(export_to or out, ordered, time.perf_counter() - started, val_share)
    if is_dataset(out):
        splits = [r.split for r in PlayDataset.open(out).records]
        summary.annotated = sum(split in ANNOTATED_SPLITS for split in splits)
        summary.val = splits.count("val")
        if resplit and earlier_share is not None:
            summary.resplit_from = float(earlier_share)
    return summary


def _previous_dataset(
    out: Path, mapping: ConvertMapping | None, overwrite: bool, segmentation: SegmentationSpec | None = None
) -> PlayDataset | None:
    """The dataset an earlier run left at ``out`` (None with ``overwrite`` or when there is none)."""
    if not out.exists():
        return None
    if not is_dataset(out):
        raise FileExistsError(f"{out}: exists and is not a playseg dataset; refusing to write into it")
    if overwrite:
        shutil.rmtree(parts_dir(out), ignore_errors=True)
        return None
    dataset = PlayDataset.open(out)
    meta = convert_meta(dataset)
    if meta is None:
        raise FileExistsError(
            f"{out}: a playseg dataset not written by `playseg convert`; use --overwrite or another --out"
        )
    digest = mapping.digest if mapping else None
    if meta.get("mapping_digest") != digest:
        raise PlaysegError(
            f"{out}: converted with another mapping ({meta.get('mapping')}); convert again with --overwrite, "
            "or choose another --out"
        )
    earlier = (meta.get("segmentation") or {}).get("digest")
    if earlier != _digest(segmentation):
        what = f"segmented by {meta['segmentation']['model']}" if earlier else "not segmented by a model"
        raise PlaysegError(
            f"{out}: {what} ({'--segment differs' if segmentation else 'no --segment given'}); convert "
            "again with --overwrite, or choose another --out"
        )
    return dataset


def _finished_part(task: BagTask) -> PlayDataset | None:
    if not is_dataset(task.part):
        return None
    try:
        part = PlayDataset.open(task.part)
    except (ValueError, OSError):
        return None
    meta = part.info.get("meta", {}).get(CONVERT_META, {})
    digest = task.mapping.digest if task.mapping else None
    if meta.get("fingerprint") != task.fingerprint or meta.get("mapping_digest") != digest:
        return None
    if meta.get("segmentation_digest") != _digest(task.segmentation):
        return None
    return part


def _report_of_part(task: BagTask) -> BagReport:
    part = PlayDataset.open(task.part)
    meta = part.info["meta"][CONVERT_META]
    counts = part.info["counts"]
    return BagReport(
        task.bag, "finished", episodes=counts["episodes"], steps=counts["steps"], segments=counts["segments"],
        model_segments=int(meta.get("model_segments", 0)), dropped_steps=int(meta.get("dropped_steps", 0)),
        notes=list(meta.get("notes", [])),
    )  # fmt: skip


def _run_ray_tasks(
    tasks: list[BagTask], workers: int, address: str | None, on_done: Callable[[BagReport], None]
) -> list[BagReport]:
    """Convert each task's bag as a Ray task, one CPU each (Ray started or joined as
    playseg_ros/ray_session.py says, imported only now); ``on_done`` is called per finished bag. Each task
    writes its bag's part under ``.<OUT>.convert/``, merged as the local engine's are, so the dataset is
    the same. On a cluster the bags and ``--out``'s directory must be on storage every node sees at the
    same path."""
    from playseg_ros.ray_session import ray_session

    with ray_session(workers, address) as ray:
        remote = ray.remote(num_cpus=1, max_retries=0)(convert_one)
        pending = {remote.remote(task): task for task in tasks}
        reports: list[BagReport] = []
        while pending:
            (done,), _ = ray.wait(list(pending), num_returns=1)
            task = pending.pop(done)
            try:
                report = ray.get(done)
            except Exception as error:  # noqa: BLE001 -- a worker that died: its bag failed, the rest go on
                reason = " ".join(str(error).split())[:300]
                report = BagReport(
                    task.bag, "failed", error=f"bag {str(task.bag)!r}: ray task failed: {reason}"
                )
            reports.append(report)
            on_done(report)
        return reports


def _run_tasks(
    tasks: list[BagTask], workers: int, progress: bool, engine: Engine = "local", address: str | None = None
) -> list[BagReport]:
    from tqdm import tqdm

    reports: list[BagReport] = []
    total_bytes = sum(bag_size(t.bag) for t in tasks)
    bar = tqdm(total=total_bytes, unit="B", unit_scale=True, desc="convert", disable=not progress or not tasks,
               file=sys.stderr)  # fmt: skip
    try:
        if engine == "ray" and tasks:

            def done(report: BagReport) -> None:
                reports.append(report)
                bar.update(report.bytes)
                bar.set_postfix(failed=sum(r.status == "failed" for r in reports))

            return _run_ray_tasks(tasks, workers, address, done)
        if workers == 1 or len(tasks) <= 1:
            for task in tasks:
                reports.append(convert_one(task))
                bar.update(reports[-1].bytes)
            return reports
        # forkserver: workers start clean (no inherited threads or locks) and, forked from a server that
        # imported the conversion once, without each paying the imports
        if "forkserver" in multiprocessing.get_all_start_methods():
            context = multiprocessing.get_context("forkserver")
            context.set_forkserver_preload(["playseg_ros.convert.build", "playseg_ros.convert.run"])
        else:
            context = multiprocessing.get_context("spawn")
        with ProcessPoolExecutor(max_workers=min(workers, len(tasks)), mp_context=context) as pool:
            futures: list[Future[BagReport]] = [pool.submit(convert_one, task) for task in tasks]
            try:
                for future in as_completed(futures):
                    reports.append(future.result())
                    bar.update(reports[-1].bytes)
                    bar.set_postfix(failed=sum(r.status == "failed" for r in reports))
            except BaseException:
                pool.shutdown(wait=True, cancel_futures=True)
                raise
        return reports
    finally:
        bar.close()


def _merge(
    out: Path,
    previous: PlayDataset | None,
    parts: list[tuple[BagReport, Path]],
    mapping: ConvertMapping | None,
    segmentation: SegmentationSpec | None = None,
    val_share: float = DEFAULT_VAL_SHARE,
) -> None:
    """Write ``out`` from the previous dataset's bags (those not converted again) and the new parts; a part
    whose features differ from the dataset's fails its bag (reported), the rest are merged. The annotated
    episodes (``train`` or ``val`` in their source) are split again over all of them: `annotated_splits`
    of their final ids with ``val_share``. With ``previous`` and no part, ``out`` is rewritten as it is,
    split with ``val_share``."""
    sources: list[tuple[PlayDataset, BagReport | None]] = []
    features: Features | None = previous.features if previous is not None else None
    for report, path in parts:
        part = PlayDataset.open(path)
        if features is None:
            features = part.features
        if part.features != features:
            report.status = "failed"
            report.error = (
                f"bag {str(report.bag)!r}: its features differ from the dataset's "
                f"({_difference(features, part.features)}); not merged"
            )
            shutil.rmtree(path, ignore_errors=True)
            continue
        sources.append((part, report))
    if not sources and (previous is None or convert_meta(previous).get("val_share") == val_share):  # type: ignore[union-attr]
        return  # nothing to add, nothing to split again
    renewed = {str(report.bag) for _, report in sources if report is not None}
    bags: dict[str, BagRecordJson] = {}
    if previous is not None:
        bags = {k: v for k, v in convert_meta(previous)["bags"].items() if k not in renewed}  # type: ignore[index]
    instructions: set[str] = set()
    for dataset, _ in ([(previous, None)] if previous is not None else []) + sources:
        instructions.update(dataset.instructions)
    meta: dict[str, Any] = {
        CONVERT_META: {
            "mapping_digest": mapping.digest if mapping else None,
            "mapping": str(mapping.path) if mapping else None,
            "segmentation": _segmentation_meta(segmentation),
            "val_share": val_share,
            "bags": bags,
        }  # fmt: skip
    }
    for part, report in sources:
        assert report is not None
        bags[str(report.bag)] = {"fingerprint": part.info["meta"][CONVERT_META]["fingerprint"],
                                 "episodes": len(part.records), "name": report.bag.name}  # fmt: skip
    # every episode's final id first: the annotated ones are split by the whole set of their ids
    plan: list[tuple[PlayDataset, int, str]] = []  # source, index in it, id in ``out``
    used: set[str] = set()
    if previous is not None:
        for index, record in enumerate(previous.records):
            if record.extra.get("bag") not in renewed:
                plan.append((previous, index, record.episode_id))
                used.add(record.episode_id)
    for part, _ in sources:
        for index, record in enumerate(part.records):
            plan.append((part, index, _unique_id(record.episode_id, str(record.extra.get("bag")), used)))
    annotated = [eid for source, index, eid in plan if source.records[index].split in ANNOTATED_SPLITS]
    splits = annotated_splits(annotated, val_share)
    domain = mapping.domain if mapping else None
    with DatasetWriter(
        out, sorted(instructions), meta=meta, overwrite=True, features=features, domain=domain
    ) as writer:
        for source, index, episode_id in plan:
            record, episode = source.records[index], source.episode(index, truth=True)
            if episode.episode_id != episode_id:
                episode = replace(episode, episode_id=episode_id)
            writer.add(episode, splits.get(episode_id, record.split), record.extra)
    for _, report in sources:
        assert report is not None
        shutil.rmtree(part_path(out, report.bag), ignore_errors=True)


def _segmentation_meta(segmentation: SegmentationSpec | None) -> dict[str, Any] | None:
    if segmentation is None:
        return None
    from playseg_core.ps.labelling import threshold_json
    from playseg_ros.convert.segmenting import load_segmenter

    segmenter = load_segmenter(segmentation)
    rule = segmenter.keep_rule(segmentation.keep)
    return {
        **segmentation.describe(),
        "keep": rule.to_json(),
        "label_threshold": threshold_json(segmenter.label_threshold),
    }


def _unique_id(episode_id: str, bag: str, used: set[str]) -> str:
    """Episode ids are ``<bag name>:<k>``; two bags of one name (in different directories) are told apart
    by a digest of their path."""
    if episode_id in used:
        name, _, k = episode_id.rpartition(":")
        episode_id = f"{name}~{hashlib.sha256(bag.encode()).hexdigest()[:6]}:{k}"
    used.add(episode_id)
    return episode_id


def _difference(ours: Features | None, theirs: Features) -> str:
    if ours is None:
        return "no features"
    for name in sorted(set(ours.by_name) | set(theirs.by_name)):
        a, b = ours.by_name.get(name), theirs.by_name.get(name)
        if a != b:
            return f"{name}: {a.describe() if a else 'absent'} vs {b.describe() if b else 'absent'}" + (
                " (names differ)" if a and b and a.describe() == b.describe() else ""
            )
    return f"fps {ours.fps} vs {theirs.fps}"


def default_workers() -> int:
    return max(1, min(4, (os.cpu_count() or 1)))
