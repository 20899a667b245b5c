"""Offline Play Segmentation commands: `playseg train`, `playseg segment`, `playseg evaluate`.

No ROS graph is needed: datasets are read with playseg_core.data.dataset, bags with playseg_ros.play_bags.
"""

from __future__ import annotations

import json
import resource
import sys
import time
from collections.abc import Iterator
from dataclasses import asdict, replace
from pathlib import Path

from playseg_core.data.episode import Episode, Segment, SegmentClip
from playseg_core.data.features import ACTION, Feature, Features
from playseg_ros.play_bags import DataInfo


def _is_bag(path: Path) -> bool:
    return path.is_dir() and (path / "metadata.yaml").is_file()


def _peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # Linux reports KiB


def _action_features(choice: str, features: Features) -> tuple[Features, bool]:
    """`playseg train --actions`: "auto" (read the action the data declares, if it is discrete), "none"
    (observations only), or a count N (the actions are discrete indices 0..N-1, checked on every step).

    Returns the features to build the model for and whether it reads the action.
    """
    if choice == "none":
        return features, False
    if choice == "auto":
        return features, features.action.is_discrete
    try:
        count = int(choice)
    except ValueError:
        raise ValueError(f"--actions must be a count, 'none' or 'auto', got {choice!r}") from None
    if count < 1:
        raise ValueError(f"--actions must be >= 1, got {count}")
    return features.with_action(Feature(ACTION, "action", "float32", (1,), num_values=count)), True


def _print_calibration(calibrated: dict[str, dict]) -> None:
    bias, labels = calibrated["end_bias"], calibrated["calibration"]
    print(
        f"end bias {bias['bias']:+.2f}: val boundary P {bias['precision']:.3f} R {bias['recall']:.3f} "
        f"F1 {bias['f1']:.3f} (best F1 {bias['best_f1']:.3f} +- {bias['f1_standard_error']:.3f}; "
        f"{bias['f1_without_bias']:.3f} without a bias)"
    )
    print(
        f"label threshold {labels['threshold']:.3f} for {labels['target_accuracy']:.2f} accuracy "
        f"keeps {labels['coverage']:.1%} of {labels['num_segments']} val segments"
    )


def calibrate(model_path: str, data: str, out: str | None) -> int:
    """Re-calibrate a PS checkpoint's end bias and label threshold on a dataset's annotated val split."""
    from playseg_core.data.dataset import PlayDataset
    from playseg_core.ps.calibration import calibrate_ps_model
    from playseg_core.ps.model import load_model, save_model

    model, extra = load_model(model_path, kinds=("ps",))
    dataset = PlayDataset.open(data)
    model.cfg.check_features(dataset.features, f"model {model_path}")
    val_eps = list(dataset.episodes("val"))
    if not any(episode.segments for episode in val_eps):
        raise ValueError(f"{data}: the val split has no annotated segments to calibrate on")
    calibrated = calibrate_ps_model(model, val_eps, 0.95)
    save_model(out or model_path, model, {**extra, **calibrated, "calibrated_on": str(Path(data).resolve())})
    print(f"{out or model_path}: calibrated on {len(val_eps)} val episodes of {data}")
    _print_calibration(calibrated)
    return 0


def train(
    data: str,
    out: str,
    epochs: int | None,
    lr: float | None,
    batch_segments: int | None,
    seed: int,
    labeller: str | None,
    actions: str = "auto",
) -> int:
    """Train the PS model (and optionally the stand-alone labeller) on a dataset's train/val splits."""
    from playseg_core.data.dataset import PlayDataset
    from playseg_core.ps.calibration import calibrate_ps_model
    from playseg_core.ps.model import save_model
    from playseg_core.ps.training import TrainConfig, model_config_for, train_labeller, train_ps

    dataset = PlayDataset.open(data)
    train_eps = list(dataset.episodes("train"))
    val_eps = list(dataset.episodes("val"))
    given = {"epochs": epochs, "lr": lr, "segments_per_batch": batch_segments}
    cfg = TrainConfig(seed=seed, **{key: value for key, value in given.items() if value is not None})
    if epochs is not None:  # asked for exactly this many epochs
        cfg = replace(cfg, min_steps=0)
    features, read_actions = _action_features(actions, dataset.features)
    model_cfg = model_config_for(
        features, dataset.domain, len(dataset.instructions), read_actions=read_actions
    )
    read = ", ".join(f"{spec.feature} ({spec.kind})" for spec in model_cfg.encoders)
    unread = "" if read_actions else f"; not the action ({features.action.describe()})"
    print(f"model reads {read}{unread}", flush=True)
    result = train_ps(train_eps, val_eps, dataset.instructions, cfg, model_cfg)
    calibrated = calibrate_ps_model(result.model, val_eps, 0.95) if val_eps else {}
    extra = {
        "train": asdict(cfg),
        "history": result.history,
        "seconds": result.seconds,
        "dataset": str(Path(data).resolve()),
        "calibration": {},
        **calibrated,
    }
    save_model(out, result.model, extra)
    last = result.history[-1]
    print(
        f"{out}: PS model trained in {result.seconds:.0f} s on {len(train_eps)} episodes; "
        f"val label accuracy {last.get('val', last['train'])['label_accuracy']:.3f}; "
        f"peak RSS {_peak_rss_mb():.0f} MB"
    )
    if calibrated:
        _print_calibration(calibrated)
    if labeller:
        lab = train_labeller(train_eps, val_eps, dataset.instructions, cfg, model_cfg)
        save_model(labeller, lab.model, {"train": asdict(cfg), "history": lab.history})
        final = lab.history[-1].get("val", lab.history[-1]["train"])
        print(f"{labeller}: labeller, val accuracy {final['label_accuracy']:.3f}, {lab.seconds:.0f} s")
    return 0


def _input_episodes(
    path: Path, splits: list[str], camera: str | None
) -> tuple[Iterator[Episode], DataInfo, str]:
    """Episodes to segment: a dataset's `splits` (annotations hidden), or every episode of a play bag
    (its image as ``camera`` when the bag declares no features, as the live segmenter reads it)."""
    if _is_bag(path):
        from playseg_ros.play_bags import iter_play_bag, read_play_bag_info

        return iter_play_bag(path, camera=camera), read_play_bag_info(path), "bag"
    from playseg_core.data.dataset import PlayDataset

    dataset = PlayDataset.open(path)

    def episodes() -> Iterator[Episode]:
        for split in splits:
            yield from dataset.episodes(split)

    return episodes(), DataInfo.of_dataset(dataset), "dataset"


def segment(
    model_path: str, input_path: str, out: str, splits: list[str], min_len: int, overwrite: bool
) -> int:
    """Segment every episode of the input; write a dataset of labelled segments (and a bag for bags)."""
    from playseg_core.data.dataset import DatasetWriter
    from playseg_core.ps.model import load_model
    from playseg_core.ps.segmentation import segment_episode

    model, extra = load_model(model_path, kinds=("ps",))
    source = Path(input_path)
    cameras = model.cfg.features.cameras
    episodes, info, kind = _input_episodes(source, splits, cameras[0] if len(cameras) == 1 else None)
    if info.features is not None:
        model.cfg.check_features(info.features, f"model {model_path}")
    threshold = float(extra.get("calibration", {}).get("threshold", 0.0))
    meta = {"segmented_by": str(model_path), "source": str(source), "label_threshold": threshold}
    instructions = info.instructions or tuple(model.instructions)
    unknown = sorted(set(model.instructions) - set(instructions))
    if unknown:
        raise ValueError(
            f"{source}: model {model_path} labels instructions the data does not list: {unknown[:3]}"
        )
    started, steps, count, results = time.perf_counter(), 0, 0, []
    with DatasetWriter(
        out, instructions, meta, overwrite=overwrite, features=info.features, domain=info.domain
    ) as writer:
        for episode in episodes:
            segments = segment_episode(model, episode, min_len=min_len)
            labelled = episode.with_segments(segments)
            writer.add(labelled, "play", extra={"source": kind})
            steps += episode.num_steps
            count += len(segments)
            if kind == "bag":
                results.append((labelled, segments))
    seconds = time.perf_counter() - started
    print(
        f"{out}: {count} segments from {writer.num_episodes} episodes ({steps} steps) in {seconds:.1f} s "
        f"({steps / max(seconds, 1e-9):.0f} steps/s)"
    )
    if kind == "bag":
        from playseg_ros.play_bags import write_segment_bag

        model_id = Path(model_path).name
        clips = (
            SegmentClip.from_episode(ep, seg, model_id)
            for ep, segs in results
            for seg in segs
            if seg.confidence >= threshold
        )
        bag = write_segment_bag(Path(out) / "segments_bag", clips, info=info)
        print(f"{Path(out) / 'segments_bag'}: {bag.message_count} LabelledSegment messages")
    return 0


def evaluate(pred: str, truth: str, out_json: str | None, plot: str | None, num_plot: int) -> int:
    """Compare a segmented dataset with the ground truth of the dataset it came from."""
    from playseg_core.data.dataset import PlayDataset
    from playseg_core.ps.metrics import evaluate as evaluate_metrics
    from playseg_core.ps.metrics import format_metrics_table

    predicted = PlayDataset.open(pred)
    reference = PlayDataset.open(truth)
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
        print(f"playseg evaluate: no episode of {pred} is in {truth}", file=sys.stderr)
        return 1
    results = evaluate_metrics(pred_by_id, truth_by_id, steps_by_id)
    print(format_metrics_table(results))
    json_path = Path(out_json) if out_json else Path(pred) / "metrics.json"
    json_path.write_text(json.dumps(results, indent=2, sort_keys=True))
    print(f"metrics: {json_path}")
    if num_plot > 0:
        from playseg_core.ps.timeline import plot_timeline

        png = Path(plot) if plot else Path(pred) / "timeline.png"
        plot_timeline(png, plotted, pred_by_id)
        print(f"timeline: {png}")
    return 0
