"""Offline Play Segmentation commands: `playseg train`, `playseg segment`, `playseg evaluate`.

No ROS graph is needed: datasets are read with playseg_core.data.dataset, bags with playseg_ros.play_bags.
"""

from __future__ import annotations

import json
import os
import resource
import sys
import time
import zipfile
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import asdict, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

from playseg_core.data.dataset import INFO_FILE, SEGMENTS_FILE, check_out_apart
from playseg_core.data.episode import Episode, Segment, SegmentClip
from playseg_core.data.features import ACTION, Feature, Features
from playseg_core.errors import PlaysegError
from playseg_ros.play_bags import DataInfo

if TYPE_CHECKING:
    from playseg_core.data.dataset import PlayDataset


def _is_bag(path: Path) -> bool:
    return path.is_dir() and (path / "metadata.yaml").is_file()


def _peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # Linux reports KiB


def _encoder_overrides(items: list[str]) -> dict[str, str]:
    """`--encoder FEATURE=KIND` options -> {feature: kind}."""
    from playseg_core.ps.encoders import ENCODER_CHOICES

    overrides = {}
    for item in items:
        feature, sep, kind = item.partition("=")
        if not sep or not feature or (kind not in ENCODER_CHOICES and "." not in kind):
            raise PlaysegError(
                f"--encoder {item!r}: expected FEATURE=KIND, KIND one of {', '.join(ENCODER_CHOICES)}"
            )
        overrides[feature] = kind
    return overrides


def _action_features(choice: str, features: Features) -> tuple[Features, bool]:
    """`playseg train --actions`: "auto" (read the action as the data declares it, discrete or
    continuous), "none" (observations only), or a count N (the actions are discrete indices 0..N-1,
    checked on every step).

    Returns the features to build the model for and whether it reads the action.
    """
    if choice == "none":
        return features, False
    if choice == "auto":
        return features, True
    try:
        count = int(choice)
    except ValueError:
        raise PlaysegError(f"--actions must be a count, 'none' or 'auto', got {choice!r}") from None
    if count < 1:
        raise PlaysegError(f"--actions must be >= 1, got {count}")
    return features.with_action(Feature(ACTION, "action", "float32", (1,), num_values=count)), True


def _open_dataset(path: str, option: str = "--data") -> PlayDataset:
    """The playseg dataset at ``path``; one clear line for a bag, a missing path or anything else."""
    from playseg_core.data.dataset import PlayDataset

    if _is_bag(Path(path)):
        raise PlaysegError(
            f"{option} {path}: a bag; this command reads a playseg dataset (written by `playseg generate`, "
            "`playseg segment` and the trainer's SaveBuffer)"
        )
    if not (Path(path) / "meta" / "info.json").is_file():
        what = "no such directory" if not Path(path).exists() else "not a playseg dataset (no meta/info.json)"
        raise FileNotFoundError(f"{option} {path}: {what}")
    return PlayDataset.open(path)


def _print_calibration(calibrated: dict[str, dict]) -> None:
    bias, labels = calibrated["end_bias"], calibrated["calibration"]
    print(
        f"end bias {bias['bias']:+.2f}: val boundary P {bias['precision']:.3f} R {bias['recall']:.3f} "
        f"F1 {bias['f1']:.3f} within +-{bias['tolerance']} steps ({bias['num_boundaries']} boundaries; "
        f"F1 {bias['f1_without_bias']:.3f} without a bias)"
    )
    print(
        f"label threshold {labels['threshold']:.3f} for {labels['target_accuracy']:.2f} accuracy "
        f"keeps {labels['coverage']:.1%} of {labels['num_segments']} val segments"
    )
    own = calibrated.get("own_cuts")
    if own:  # what the threshold keeps of the model's own cuts, as it will on play
        right = (
            f", {own['step_accuracy_kept']:.1%} of their steps labelled as the truth" if own["kept"] else ""
        )
        print(
            f"on its own cuts of the val episodes it keeps {own['kept']} of {own['segments']} segments"
            f"{right} ({own['step_accuracy_all']:.1%} of all cut steps)"
        )
    own_threshold = calibrated.get("own_cuts_calibration")
    if own_threshold:  # the threshold chosen on those cuts instead, on label x cut probability
        print(
            f"own-cut threshold {own_threshold['threshold']:.3f} (label x cut probability) for "
            f"{own_threshold['target_accuracy']:.2f} of them labelled right keeps "
            f"{own_threshold['coverage']:.1%} of them ({own_threshold['accuracy_all']:.1%} right in all)"
        )


def calibrate(
    model_path: str, data: str, out: str | None, label_accuracy: float | None = None, device: str = "auto"
) -> int:
    """Re-calibrate a PS checkpoint's end bias and label threshold (for ``label_accuracy`` on held-out
    segments; None: ps/calibration.py's LABEL_ACCURACY_TARGET) on a dataset's annotated val split, the
    model run on ``device``."""
    from playseg_core.ps.calibration import calibrate_ps_model
    from playseg_core.ps.model import load_model, save_model
    from playseg_core.training.device import resolve_device

    label_accuracy = checked_label_accuracy(label_accuracy)
    resolved = resolve_device(device)
    model, extra = load_model(model_path, kinds=("ps",))
    model.to(resolved)
    dataset = _open_dataset(data)
    check_output_file(out or model_path, overwrite=True, option="--out")  # in place unless --out
    model.cfg.check_features(dataset.features, f"model {model_path}")
    val_eps = list(dataset.episodes("val"))
    if not any(episode.segments for episode in val_eps):
        raise PlaysegError(f"{data}: the val split has no annotated segments to calibrate on")
    calibrated = calibrate_ps_model(model, val_eps, label_accuracy)
    model.to("cpu")
    save_model(out or model_path, model, {**extra, **calibrated, "calibrated_on": str(Path(data).resolve())})
    print(f"{out or model_path}: calibrated on {len(val_eps)} val episodes of {data}")
    _print_calibration(calibrated)
    return 0


def _training_fingerprint(data: str, cfg: Any | None, model_cfg: Any, val_ids: list[str]) -> str:
    """What a run's resume file must match: the dataset, the settings that change what is trained (the
    step cap and patience too: the cap sets the learning-rate schedule; not ``max_minutes``, the device
    nor how progress is shown), the model (or another method's settings) and the held-out episodes."""
    import hashlib

    settings = {
        key: value
        for key, value in (asdict(cfg) if cfg is not None else {}).items()
        if key
        not in ("progress", "log_epochs", "state_path", "resume", "fingerprint", "max_minutes", "device")
    }
    text = repr((str(Path(data).resolve()), sorted(settings.items()), repr(model_cfg), val_ids))
    return hashlib.sha256(text.encode()).hexdigest()


@contextmanager
def _state_kept_on_interrupt(state: Path) -> Iterator[None]:
    """An interrupted run says where its resume state is (the loop writes it every evaluation)."""
    try:
        yield
    except KeyboardInterrupt:
        if state.exists():
            print(
                f"training state kept in {state}: the same command with --resume continues it",
                file=sys.stderr,
            )
        raise


def train_state_path(out: str | Path) -> Path:
    """Where a training run keeps its resume state: beside its checkpoint (removed when it finishes)."""
    out = Path(out)
    return out.with_name(out.name + ".train-state")


def train(
    data: str,
    out: str,
    epochs: int | None,
    lr: float | None,
    batch_segments: int | None,
    seed: int,
    labeller: str | None,
    actions: str = "auto",
    overwrite: bool = False,
    bounds: dict[str, int | None] | None = None,
    encoders: list[str] | None = None,
    method: str = "ps",
    encoders_from: str | None = None,
    label_head: str | None = None,
    augment: bool | None = None,
    label_accuracy: float | None = None,
    end_lookahead: int | None = None,
    budget: dict[str, Any] | None = None,
    device: str = "auto",
    val_share: float | None = None,
    resume: bool = False,
) -> int:
    """Train the PS model (and optionally the stand-alone labeller) on a dataset's train/val splits,
    or another segmentation method (``method``, playseg_core/baselines/registry.py).

    ``bounds`` (min_len, max_len, k_max; None = derived, see `segment_bounds`) and ``encoders``
    (``FEATURE=KIND`` overrides of the step encoders) and ``label_head`` (None: the domain's, else
    linear) and ``augment`` (training clips under the domain's symmetries, or rotated/mirrored frames;
    None: under the domain's symmetries where it declares them and the method augments, else not)
    and ``end_lookahead`` (None: the domain's, else 0) come from the command line;
    ``budget`` (max_steps, max_minutes, patience; None = the method's default) bounds the run on
    ``device``. Without annotated val episodes, ``val_share`` of the annotated training episodes are
    held out for early stopping and calibration (`hold_out_for_validation`); with too few to hold any
    out, the model is saved uncalibrated, and said so. ``resume`` continues a killed run from its state
    file (`train_state_path`).

    The outputs are checked before training starts (a model is never trained only to be lost).
    """
    from playseg_core.baselines.registry import get_method
    from playseg_core.data.splits import DEFAULT_VAL_SHARE
    from playseg_core.ps.model import MAX_END_LOOKAHEAD, save_model
    from playseg_core.ps.training import (
        TrainConfig,
        clip_symmetries_of,
        hold_out_for_validation,
        model_config_for,
        segment_bounds,
        train_labeller,
        train_ps,
    )
    from playseg_core.training import distributed
    from playseg_core.training.device import resolve_device

    resolved = resolve_device(device)  # no CUDA where it was asked for: one line before anything is read
    budget = {key: value for key, value in (budget or {}).items() if value is not None}
    get_method(method)  # an unknown method fails before anything is read
    if labeller and method != "ps":
        raise PlaysegError(
            f"--labeller: only with --method ps (method {method} writes what it needs to --out)"
        )
    if label_accuracy is not None and method != "ps":
        raise PlaysegError(
            f"--label-accuracy: only with --method ps (method {method} keeps no calibrated threshold)"
        )
    label_accuracy = checked_label_accuracy(label_accuracy)
    if label_head and method != "ps":
        raise PlaysegError(f"--label-head: only with --method ps, not {method}")
    if end_lookahead is not None and method != "ps":
        raise PlaysegError(f"--end-lookahead: only with --method ps, not {method}")
    if end_lookahead is not None and not 0 <= end_lookahead <= MAX_END_LOOKAHEAD:
        raise PlaysegError(f"--end-lookahead: must be in 0..{MAX_END_LOOKAHEAD}, got {end_lookahead}")
    if encoders_from and method not in ("unloc", "tridet"):
        raise PlaysegError(f"--encoders-from: only with --method unloc or tridet, not {method}")
    if val_share is not None and not 0.0 <= val_share < 1.0:
        raise PlaysegError(f"--val-share: must be in [0, 1), got {val_share}")
    dataset = _open_dataset(data)
    if labeller and Path(labeller).resolve() == Path(out).resolve():
        raise PlaysegError(
            f"--labeller {labeller}: the same file as --out (the labeller would replace the PS model)"
        )
    # A run killed while training the labeller resumes there: its PS model is already written.
    ps_done = bool(
        resume
        and labeller
        and Path(out).is_file()
        and not train_state_path(out).exists()
        and train_state_path(labeller).exists()
    )
    if not ps_done:
        check_output_file(out, overwrite)
    if labeller:
        check_output_file(labeller, overwrite, "--labeller")
    train_eps = list(dataset.episodes("train"))
    val_eps = list(dataset.episodes("val"))
    if not any(episode.segments for episode in train_eps):
        raise PlaysegError(f"--data {data}: the train split has no annotated segments to learn from")
    share = DEFAULT_VAL_SHARE if val_share is None else val_share
    train_eps, val_eps, held = hold_out_for_validation(train_eps, val_eps, share)
    annotated_val = [episode for episode in val_eps if episode.segments]
    if held:
        total = len(held) + sum(1 for episode in train_eps if episode.segments)
        print(
            f"no annotated val split in {data}: {len(held)} of {total} annotated episodes held out "
            f"(--val-share {share:g}) for early stopping and calibration"
        )
    elif not annotated_val:
        print(
            f"uncalibrated: {data} has no annotated val split and too few annotated episodes to hold one "
            "out (two or more, --val-share > 0); training runs to its step cap and the model is marked "
            "uncalibrated"
        )
    chosen = segment_bounds(train_eps, dataset.domain, **(bounds or {}))
    given = {"epochs": epochs, "lr": lr, "segments_per_batch": batch_segments}
    cfg = TrainConfig(
        seed=seed, k_max=chosen.k_max, **{key: value for key, value in given.items() if value is not None}
    )
    features, read_actions = _action_features(actions, dataset.features)
    symmetries = clip_symmetries_of(dataset.domain)
    if augment is None:  # a world's declared symmetries are free data: train on them unless told not to
        augment = get_method(method).augments and symmetries is not None
    if augment and read_actions and symmetries is None:
        raise PlaysegError(
            "--augment: only with --actions none (a mirror would swap left and right turns), or for a "
            "domain whose symmetries turn the actions too (its clip_symmetries)"
        )
    if augment and not get_method(method).augments:
        raise PlaysegError(f"--augment: only for PS and the labelling model, not {method}")
    # In a process group (--nproc, torchrun) each process trains on its own device, and on the CPU on
    # its share of the cores; process 0 writes the outputs.
    resolved = distributed.join(resolved)
    processes = distributed.world()[0]
    if processes > 1 and resolved.type == "cpu":
        budget = {"num_threads": max(1, (os.cpu_count() or 1) // processes), **budget}
    cfg = replace(cfg, augment=augment, domain=dataset.domain, device=str(resolved), **budget)
    if method != "ps":
        given = {
            "seed": seed,
            "epochs": epochs,
            "lr": lr,
            "batch_size": batch_segments,
            "device": str(resolved),
            "progress": True,  # step / cap, loss, ETA on stderr, as PS shows them
        }
        given |= {
            key: value
            for key, value in budget.items()
            if key in ("max_steps", "max_minutes", "patience", "num_threads")
        }
        val_ids = sorted(episode.episode_id for episode in annotated_val)
        what = (
            method,
            sorted((k, v) for k, v in given.items() if k not in ("device", "max_minutes", "progress")),
        )
        what += (bounds, encoders, encoders_from, augment, read_actions)
        given |= {
            "state_path": str(train_state_path(out)),
            "resume": resume,
            "fingerprint": _training_fingerprint(data, None, what, val_ids),
        }
        training = (dataset, train_eps, val_eps, features, read_actions, bounds, encoders, encoders_from)
        with _state_kept_on_interrupt(train_state_path(out)):
            return _train_method(method, data, out, training, given, augment)
    model_cfg = model_config_for(
        features,
        dataset.domain,
        len(dataset.instructions),
        max_len=chosen.max_len,
        read_actions=read_actions,
        episodes=train_eps,
        overrides=_encoder_overrides(encoders or []),
        min_len=chosen.min_len,
        label_head=label_head,
        end_lookahead=end_lookahead,
    )
    read = ", ".join(f"{spec.feature} ({spec.kind})" for spec in model_cfg.encoders)
    unread = (
        ""
        if any(s.feature == ACTION for s in model_cfg.encoders)
        else f"; not the action ({features.action.describe()})"
    )
    ahead = (
        f"; the end head reads {model_cfg.end_lookahead} step(s) past an end"
        if model_cfg.end_lookahead
        else ""
    )
    turned = ""
    if augment:
        turned = (
            f"; clips under the domain's {symmetries.count} symmetries"
            if symmetries
            else "; clips rotated/mirrored"
        )
    print(
        f"model reads {read}{unread}; {model_cfg.label_head} label head{ahead}; {chosen.describe()}{turned}; "
        f"device {resolved}",
        flush=True,
    )
    val_ids = sorted(episode.episode_id for episode in annotated_val)
    state = train_state_path(out)
    cfg = replace(
        cfg,
        state_path=str(state),
        resume=resume,
        fingerprint=_training_fingerprint(data, cfg, model_cfg, val_ids),
    )
    if ps_done:
        print(f"{out}: written before the run was stopped; resuming the labeller")
    else:
        with _state_kept_on_interrupt(state):
            result = train_ps(train_eps, val_eps, dataset.instructions, cfg, model_cfg)
        if distributed.is_main():
            _save_ps_model(out, result, cfg, resolved, annotated_val, label_accuracy, data, val_ids, held)
            print(
                f"{out}: PS model trained on {len(train_eps)} episodes, {result.summary()}; "
                f"val label accuracy {result.label_accuracy:.3f}; peak RSS {_peak_rss_mb():.0f} MB"
            )
    if labeller:  # every process of a group trains it too
        lab_state = train_state_path(labeller)
        lab_cfg = replace(
            cfg,
            state_path=str(lab_state),
            # a run killed while training PS has no labeller state yet: the labeller starts afresh
            resume=resume and lab_state.exists(),
            fingerprint=cfg.fingerprint + "-labeller",
        )
        with _state_kept_on_interrupt(lab_state):
            lab = train_labeller(train_eps, val_eps, dataset.instructions, lab_cfg, model_cfg)
        if distributed.is_main():
            save_model(labeller, lab.model, {"train": asdict(lab_cfg), "history": lab.history})
            print(f"{labeller}: labeller, {lab.summary()}; val accuracy {lab.label_accuracy:.3f}")
    return 0


def _save_ps_model(
    out: str,
    result: Any,
    cfg: Any,
    device: Any,
    annotated_val: list[Episode],
    label_accuracy: float,
    data: str,
    val_ids: list[str],
    held: list,
) -> None:
    """Calibrate the trained PS model on the annotated val episodes (none: uncalibrated, said so) and
    write it with its training record."""
    from playseg_core.ps.calibration import calibrate_ps_model
    from playseg_core.ps.model import save_model

    result.model.to(device)  # calibration segments the val episodes: on the training device
    calibrated = calibrate_ps_model(result.model, annotated_val, label_accuracy) if annotated_val else {}
    result.model.to("cpu")
    extra = {
        "train": asdict(cfg),
        "history": result.history,
        "seconds": result.seconds,
        "dataset": str(Path(data).resolve()),
        "val_episodes": val_ids,
        "held_out": bool(held),
        "calibration": {},
        **calibrated,
    }
    save_model(out, result.model, extra)
    if calibrated:
        _print_calibration(calibrated)
    else:
        print(f"{out}: uncalibrated (no annotated val episodes): confidences are not calibrated")


def _train_method(method: str, data: str, out: str, training: tuple, given: dict, augment: bool) -> int:
    """`playseg train --method` for a method other than PS: the same data, options and output."""
    from playseg_core.baselines.common import TrainingData, TrainOptions
    from playseg_core.baselines.registry import train_segmenter
    from playseg_core.training import distributed

    dataset, train_eps, val_eps, features, read_actions, bounds, encoders, encoders_from = training
    overrides = _encoder_overrides(encoders or [])
    inputs = TrainingData(
        train_eps, val_eps, list(dataset.instructions), features, dataset.domain, read_actions, overrides,
        dict(bounds or {}), encoders_from, augment,
    )  # fmt: skip
    trained = train_segmenter(method, inputs, TrainOptions(**given))  # unset options: the method's defaults
    if not distributed.is_main():
        return 0
    trained.save(Path(out), {"method": method, "dataset": str(Path(data).resolve())})
    print(f"{out}: {trained.report}; peak RSS {_peak_rss_mb():.0f} MB")
    return 0


def _input_episodes(
    path: Path, splits: list[str], camera: str | None, keep_incomplete: bool
) -> tuple[Iterator[Episode], DataInfo, str]:
    """Episodes to segment: a dataset's `splits` (annotations hidden), or every episode of a play bag
    (its image as ``camera`` when the bag declares no features, as the live segmenter reads it). An
    episode a bag cuts off before its end is reported, and segmented too with ``keep_incomplete``."""
    if _is_bag(path):
        from playseg_ros.play_bags import iter_play_bag, read_play_bag_info

        def report(episode_id: str, last_step: int) -> None:
            action = (
                "segmenting the steps it has" if keep_incomplete else "skipped (--keep-incomplete keeps it)"
            )
            print(f"{path}: episode {episode_id!r} ends at step {last_step} without episode_end: {action}")

        incomplete = "keep" if keep_incomplete else "drop"
        episodes = iter_play_bag(path, camera=camera, incomplete=incomplete, on_incomplete=report)
        return episodes, read_play_bag_info(path), "bag"
    from playseg_core.data.dataset import PlayDataset
    from playseg_core.data.splits import SPLITS

    unknown = [split for split in splits if split not in SPLITS]
    if unknown:
        raise PlaysegError(f"--splits: unknown split {unknown[0]!r} (expected some of {', '.join(SPLITS)})")
    dataset = PlayDataset.open(path)

    def episodes() -> Iterator[Episode]:
        for split in splits:
            yield from dataset.episodes(split)

    return episodes(), DataInfo.of_dataset(dataset), "dataset"


def checked_label_accuracy(label_accuracy: float | None) -> float:
    """``--label-accuracy`` (None: ps/calibration.py's LABEL_ACCURACY_TARGET); ValueError unless in (0, 1]."""
    from playseg_core.ps.calibration import LABEL_ACCURACY_TARGET, check_target_accuracy

    if label_accuracy is None:
        return LABEL_ACCURACY_TARGET
    return check_target_accuracy(label_accuracy, "--label-accuracy")


def check_output_file(path: str | Path, overwrite: bool, option: str = "--out") -> Path:
    """Before long work: ``path`` can be written (its directory is created), and an existing file is only
    replaced with ``--overwrite`` and only when it is a checkpoint (a torch archive): a mistyped path never
    destroys another file. Checkpoints are then written atomically (playseg_core/checkpoint.py)."""
    path = Path(path)
    if path.is_dir():
        raise IsADirectoryError(f"{option} {path}: is a directory, expected a file")
    if path.exists() and not overwrite:
        raise FileExistsError(f"{option} {path}: exists (pass --overwrite to replace it)")
    if path.exists() and not zipfile.is_zipfile(path):  # every checkpoint is a torch zip archive
        raise FileExistsError(f"{option} {path}: exists and is not a checkpoint; refusing to replace it")
    path.parent.mkdir(parents=True, exist_ok=True)
    if not os.access(path.parent, os.W_OK):
        raise PermissionError(f"{option} {path}: directory {path.parent} is not writable")
    return path


def segment(
    model_path: str,
    input_path: str,
    out: str,
    splits: list[str],
    min_len: int | None,
    overwrite: bool,
    keep_incomplete: bool = False,
    method: str = "ps",
    seed: int = 0,
    keep: str = "label",
    device: str = "auto",
    engine: str = "local",
    workers: int = 1,
    address: str | None = None,
) -> int:
    """Segment every episode of the input; write a dataset of labelled segments (and a bag for bags).

    ``method`` is the segmentation method the checkpoint is for (playseg_core/baselines/registry.py);
    ``seed`` draws the random windows of the methods that use them. The dataset holds every segment (with
    its label confidence and log-score, for `evaluate`); the segment bag only those the ``keep`` rule
    (ps/labelling.py `KEEP_RULES`) keeps, which the dataset's meta records.
    Streams: one episode in memory at a time, the segment bag written as the segments come. ``engine``
    "ray" segments the episodes on ``workers`` Ray actors (``address``: a cluster to join;
    playseg_ros/segment_ray.py), with the same output; a few episodes per actor are then in memory.
    """
    from playseg_core.baselines.common import SegmentOptions
    from playseg_core.baselines.registry import load_segmenter
    from playseg_core.data.dataset import DatasetWriter
    from playseg_core.ps.labelling import is_calibrated, threshold_json, uncalibrated_warning
    from playseg_core.training.device import resolve_device

    if min_len is not None and min_len < 1:
        raise PlaysegError(f"--min-len must be >= 1, got {min_len}")
    if engine not in ("local", "ray"):
        raise PlaysegError(f"--engine {engine!r}: expected local or ray")
    if address is not None and engine != "ray":
        raise PlaysegError("--address is the Ray cluster to join: give --engine ray")
    if workers < 1:
        raise PlaysegError(f"--workers must be >= 1, got {workers}")
    if workers > 1 and engine != "ray":
        raise PlaysegError(
            "--workers is the number of Ray actors: give --engine ray (local runs in this process)"
        )
    source = Path(input_path)
    if not source.exists():
        raise FileNotFoundError(f"--input {source}: no such bag or dataset")
    check_out_apart(out, source)
    resolved = resolve_device(device)
    options = SegmentOptions(min_len=min_len, seed=seed, device=str(resolved))
    model = load_segmenter(method, model_path, options)
    rule = model.keep_rule(keep)
    if method == "ps" and not is_calibrated(model.checkpoint_meta):
        print(uncalibrated_warning(f"model {model_path}"), file=sys.stderr)
    cameras = model.features.cameras
    camera = cameras[0] if len(cameras) == 1 else None
    episodes, info, kind = _input_episodes(source, splits, camera, keep_incomplete)
    if info.features is not None:
        model.check_features(info.features, f"model {model_path}")
    meta = {
        "segmented_by": str(model_path),
        "source": str(source),
        "keep": rule.to_json(),
        "label_threshold": threshold_json(model.label_threshold),
        "method": method,
        "tiles": model.tiles,  # evaluate: only precision and label accuracy if not
    }
    instructions = info.instructions or tuple(model.instructions)
    unknown = sorted(set(model.instructions) - set(instructions))
    if unknown:
        raise PlaysegError(
            f"{source}: model {model_path} labels instructions the data does not list: {unknown[:3]}"
        )
    model_id = Path(model_path).name
    started, steps, count, kept = time.perf_counter(), 0, 0, 0
    with DatasetWriter(
        out, instructions, meta, overwrite=overwrite, features=info.features, domain=info.domain
    ) as writer:
        for stale in writer.removed_stale:
            print(f"{stale}: removed (left behind by a killed run)")

        def kept_clips() -> Iterator[SegmentClip]:
            """Segment episode by episode, writing each to the dataset; yield the clips the rule keeps."""
            nonlocal steps, count, kept
            if engine == "ray":
                from playseg_ros.segment_ray import segment_on_ray  # Ray: only with this engine

                segmented = segment_on_ray(episodes, method, model_path, options, workers, address)
            else:
                segmented = ((episode, model.segment(episode)) for episode in episodes)
            for episode, segments in segmented:
                writer.add(episode.with_segments(segments), "play", extra={"source": kind})
                steps += episode.num_steps
                count += len(segments)
                chosen = [s for s in segments if rule.keeps(s)]
                kept += len(chosen)
                yield from (SegmentClip.from_episode(episode, s, model_id) for s in chosen)

        if kind == "bag":
            from playseg_ros.play_bags import write_segment_bag

            # Inside the dataset's staging directory: it appears with the dataset or not at all.
            bag = write_segment_bag(writer.staging_dir / "segments_bag", kept_clips(), info=info)
        else:
            for _ in kept_clips():
                pass
    seconds = time.perf_counter() - started
    print(
        f"{out}: {count} segments from {writer.num_episodes} episodes ({steps} steps) in {seconds:.1f} s "
        f"({steps / max(seconds, 1e-9):.0f} steps/s); {kept} kept by {rule.describe()}"
    )
    if kind == "bag":
        print(f"{Path(out) / 'segments_bag'}: {bag.message_count} LabelledSegment messages")
    return 0


def _check_report_path(path: Path, option: str, suffixes: tuple[str, ...], datasets: tuple[str, ...]) -> None:
    """Before any work: a report file ``path`` is a file of one of ``suffixes`` and none of the datasets'
    own files (replacing their meta/ or data/ would make them unreadable)."""
    if path.is_dir():
        raise IsADirectoryError(f"{option} {path}: is a directory, expected a file")
    if path.suffix.lower() not in suffixes:
        raise PlaysegError(f"{option} {path}: expected a {' or '.join(suffixes)} file")
    resolved = path.resolve()
    for root in datasets:
        own_directories = {(Path(root).resolve() / file).parent for file in (INFO_FILE, SEGMENTS_FILE)}
        if any(directory in resolved.parents for directory in own_directories):
            raise PlaysegError(
                f"{option} {path}: lies among the files of the dataset {root}; choose another path"
            )


def evaluate(pred: str, truth: str, out_json: str | None, plot: str | None, num_plot: int) -> int:
    """Compare a segmented dataset with the ground truth of the dataset it came from."""
    from playseg_core.ps.metrics import evaluate as evaluate_metrics
    from playseg_core.ps.metrics import format_metrics_table

    json_path = Path(out_json) if out_json else Path(pred) / "metrics.json"
    png = Path(plot) if plot else Path(pred) / "timeline.png"
    _check_report_path(json_path, "--json", (".json",), (pred, truth))
    if num_plot > 0:
        _check_report_path(png, "--plot", (".png", ".pdf", ".svg"), (pred, truth))
    predicted = _open_dataset(pred, "--pred")
    reference = _open_dataset(truth, "--truth")
    pred_by_id: dict[str, list[Segment]] = {}
    for index, record in enumerate(predicted.records):
        pred_by_id[record.episode_id] = predicted.segments(index, truth=True)
    truth_by_id, steps_by_id, plotted = {}, {}, []
    for index, record in enumerate(reference.records):
        if record.episode_id not in pred_by_id:
            continue
        truth_by_id[record.episode_id] = reference.segments(index, truth=True)
        steps_by_id[record.episode_id] = record.num_steps
        if len(plotted) < num_plot:
            plotted.append(reference.episode(index, truth=True))
    if not truth_by_id:
        raise PlaysegError(f"--pred {pred}: none of its episodes is in --truth {truth}")
    unknown = sorted(set(pred_by_id) - set(truth_by_id))
    if unknown:  # e.g. --pred and --truth swapped: the truth holds more episodes than were segmented
        raise PlaysegError(
            f"--pred {pred}: {len(unknown)} of its episodes are not in --truth {truth} (first {unknown[0]!r}); "
            "give as --truth the dataset it was segmented from"
        )
    results = evaluate_metrics(pred_by_id, truth_by_id, steps_by_id)
    print(format_metrics_table(results))
    segmented_by = predicted.info.get("meta", {})
    if segmented_by.get("tiles") is False:  # a window method (unloc, tridet): its segments leave gaps
        from playseg_core.baselines.common import covered_metrics

        results |= covered_metrics(pred_by_id, truth_by_id, steps_by_id)
        print(
            f"method {segmented_by.get('method')} cuts single segments out of windows: read segment precision "
            f"and label accuracy on the {results['covered_steps']} steps its segments cover, "
            f"{results['covered_label_accuracy']:.3f} (recall and the label accuracy above count the gaps)"
        )
    json_path.write_text(json.dumps(results, indent=2, sort_keys=True))
    print(f"metrics: {json_path}")
    if num_plot > 0:
        from playseg_core.ps.timeline import plot_timeline

        plot_timeline(png, plotted, pred_by_id)
        print(f"timeline: {png}")
    return 0
