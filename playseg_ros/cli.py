"""The `playseg` command line: one entry point, one subcommand per job.

One error policy for every command: an expected failure (a missing, unreadable or unwritable path, the
wrong kind of input, a damaged bag, dataset or checkpoint, a bad option value) prints one line naming
the path, topic, field or option and exits with `EXIT_FAILED`; a traceback only with ``--debug`` or for a
genuine bug. Inputs and outputs are checked before long work starts; SIGINT and SIGTERM remove partial
outputs (the writers' ``with`` blocks abort) and exit with `EXIT_INTERRUPTED`.
"""

from __future__ import annotations

import argparse
import os
import signal
import sys
import time

from playseg_core.errors import PlaysegError

EXIT_FAILED = 1
"""The job could not be done (one line on stderr says why)."""
EXIT_USAGE = 2
"""The command line itself is wrong (argparse's usage message)."""
EXIT_INTERRUPTED = 130
"""Stopped by SIGINT or SIGTERM; partial outputs were removed."""

EXPECTED_ERRORS: tuple[type[BaseException], ...] = (PlaysegError, OSError)
"""What bad input or output raises: PlaysegError (BagError, DatasetError, FeatureError, CheckpointError
and every other check of playseg's) and OSError (a missing, unreadable or unwritable path, a full disk).
Anything else is a bug and keeps its traceback."""

SEGMENTATION_METHODS = ("ps", "unloc", "tridet", "random", "changepoint")
"""`--method` of train and segment: the names of playseg_core.baselines.registry.METHODS (listed here so
`playseg --help` need not import torch; tests/test_baselines_cli.py checks they agree)."""
LABEL_HEADS = ("linear", "text")
"""playseg_core.ps.model.LABEL_HEADS, spelt here so that parsing the command line imports no torch."""
KEEP_RULE_CHOICES = ("label", "own_cuts", "all")
"""playseg_core.ps.labelling.KEEP_RULES' names, spelt here for the same reason."""
KEEP_HELP = (
    "which segments are kept: label (default: label confidence >= the threshold calibrated on the val "
    "split's true cuts, the paper's filter), own_cuts (label x cut probability >= the threshold "
    "calibrated on the model's own cuts of the val episodes; PS; better where its cuts of play are often "
    "pieces of tasks: docs/segmentation.md 'Calibration'), all"
)

DEFAULT_DOMAIN = "babyai"
"""The domain `playseg generate` plays in unless told otherwise (the sample bags' domain)."""


def positive_int(text: str) -> int:
    """argparse type: an integer >= 1 (argparse names the option in its one-line error)."""
    return _int_at_least(text, 1)


def non_negative_int(text: str) -> int:
    """argparse type: an integer >= 0."""
    return _int_at_least(text, 0)


def positive_float(text: str) -> float:
    """argparse type: a finite number > 0."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not 0.0 < value < float("inf"):
        raise argparse.ArgumentTypeError(f"must be a positive number, got {text}")
    return value


def add_device_argument(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--device",
        default="auto",
        help="where models run: auto (CUDA when torch sees one, else the CPU), cpu, cuda or cuda:N",
    )


def _int_at_least(text: str, low: int) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
    if value < low:
        raise argparse.ArgumentTypeError(f"must be at least {low}, got {value}")
    return value


def _cmd_demo(args: argparse.Namespace) -> int:
    from playseg_ros.demo import run_demo, train_sample_models

    return train_sample_models() if args.train_models else run_demo()


def _cmd_bag_info(args: argparse.Namespace) -> int:
    from playseg_ros.bag import bag_info_text

    print(bag_info_text(args.path))
    return 0


def _cmd_bag_recover(args: argparse.Namespace) -> int:
    from playseg_ros.bag import recover_bag

    report = recover_bag(args.path)
    for item in report:
        print(item.summary())
    # a loss beyond the open chunk of a crash: said on stderr too (metadata.yaml keeps a note of it);
    # exit 0 all the same, as everything that could be kept is (docs/bags.md)
    for item in (i for i in report if i.lossy):
        print(
            f"playseg: warning: {item.path}: {item.loss()}; {'; '.join(item.damage)}".rstrip("; "),
            file=sys.stderr,
        )
    return 0


def _cmd_generate(args: argparse.Namespace) -> int:
    from playseg_core.domains import load_domain

    domain = load_domain(args.domain)
    presets = domain.preset_names
    if args.preset not in presets:
        raise PlaysegError(f"--preset {args.preset!r}: domain {args.domain!r} has {', '.join(presets)}")
    if args.workers < 1:
        raise PlaysegError(f"--workers must be >= 1, got {args.workers}")
    if args.annotated_share is not None and not 0.0 < args.annotated_share <= 1.0:
        raise PlaysegError(f"--annotated-share must be in (0, 1], got {args.annotated_share}")
    if args.images and not args.bag:
        raise PlaysegError(f"--images {args.images}: only with --bag (the dataset itself keeps raw frames)")
    summary = domain.generate_dataset(
        args.out,
        args.preset,
        seed=args.seed,
        workers=args.workers,
        progress=not args.quiet,
        overwrite=args.overwrite,
        annotated_share=args.annotated_share,
    )
    splits = ", ".join(
        f"{name} {summary.episodes_per_split[name]} episodes / {summary.segments_per_split[name]} segments"
        for name in summary.segments_per_split
    )
    print(
        f"{summary.path}: preset {summary.preset}, seed {summary.seed}: {summary.episodes} episodes, "
        f"{summary.steps} steps ({splits}); {summary.bytes_on_disk / 1e6:.1f} MB in {summary.seconds:.1f} s "
        f"with {summary.workers} workers"
    )
    if args.bag:
        from playseg_ros.play_bags import write_generated_bags

        started = time.perf_counter()
        lines = write_generated_bags(
            args.domain, summary.path, summary.path / "bags", args.images or "raw", args.workers
        )
        print("\n".join(lines))
        print(f"bags written in {time.perf_counter() - started:.1f} s")
    return 0


def _add_generate_command(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """`playseg generate`: returns its parser so other sources (e.g. a bag option) can add arguments."""
    generate = sub.add_parser(
        "generate", help="generate a play dataset (train/val/play/test splits) with a domain's generator"
    )
    generate.add_argument(
        "--domain", default=DEFAULT_DOMAIN, help=f"the world to play in (default {DEFAULT_DOMAIN})"
    )
    generate.add_argument("--preset", default="small", help="dataset size, one of the domain's presets")
    generate.add_argument("--out", required=True, help="dataset directory to create")
    generate.add_argument("--seed", type=int, default=0, help="base seed; same seed, same bytes")
    generate.add_argument("--workers", type=int, default=1, help="generator (and --bag writer) processes")
    generate.add_argument(
        "--annotated-share",
        type=float,
        default=None,
        help="share of the non-test segments that is annotated (0.1, 0.25, 0.5, 1.0); preset default if unset",
    )
    generate.add_argument(
        "--overwrite", action="store_true", help="replace an existing --out (only a previous playseg dataset)"
    )
    generate.add_argument("--quiet", action="store_true", help="no progress bar")
    generate.add_argument(
        "--bag",
        action="store_true",
        help="also write the episodes as bags, OUT/bags/annotated (train+val, with annotations), play, test: "
        "play bags (PlayStep) unless the domain writes its own (tabletop: one standard-message robot bag "
        "per episode, camera, joint states, commands, with OUT/bags/mapping.yaml for `playseg convert`)",
    )
    generate.add_argument(
        "--images",
        choices=["raw", "jpeg", "both"],
        help="with --bag, robot bags' camera: raw Image (default; converts back exactly), CompressedImage "
        "jpeg (a fraction of the size, lossy) or both; play bags hold raw frames only",
    )
    generate.set_defaults(func=_cmd_generate)
    return generate


def _add_bag_commands(sub: argparse._SubParsersAction) -> None:
    bag = sub.add_parser("bag", help="inspect and repair rosbag2 MCAP bags (no ROS graph needed)")
    bag_sub = bag.add_subparsers(dest="bag_command", required=True, metavar="BAG_COMMAND")
    info = bag_sub.add_parser("info", help="files, duration, topics and message counts of a bag")
    info.add_argument("path", help="bag directory")
    info.set_defaults(func=_cmd_bag_info)
    recover = bag_sub.add_parser(
        "recover", help="finish a bag whose writer died (restores every message up to the last chunk)"
    )
    recover.add_argument("path", help="bag directory the writer was given (or its .partial directory)")
    recover.set_defaults(func=_cmd_bag_recover)


def _cmd_up(args: argparse.Namespace) -> int:
    from playseg_ros.launch import run_graph

    return run_graph(args.config)


def _add_up_command(sub: argparse._SubParsersAction) -> None:
    up = sub.add_parser(
        "up", help="bring up a graph of playseg nodes from a YAML config (Ctrl-C stops all of them)"
    )
    up.add_argument("config", help="graph config, e.g. config/live_play.yaml (see docs/nodes.md)")
    up.set_defaults(func=_cmd_up)


def _train_process(argv: list[str]) -> int:
    """One process of `playseg train --nproc N`: the same command; process 0 alone prints."""
    if os.environ.get("RANK", "0") != "0":
        sys.stdout = sys.stderr = open(os.devnull, "w")  # noqa: SIM115 - for the life of the process
    return main(argv)


def _cmd_train(args: argparse.Namespace) -> int:
    from playseg_core.training import distributed

    if args.nproc > 1 and distributed.requested_world() == 1:
        return distributed.launch(args.nproc, _train_process, args.argv)
    if os.environ.get("RANK", "0") != "0":  # launched by torchrun: process 0 prints
        sys.stdout = open(os.devnull, "w")  # noqa: SIM115 - for the life of the process
    try:
        code = _train_from(args)
    except BaseException:
        distributed.leave(wait_for_peers=False)
        raise
    distributed.leave(wait_for_peers=code == 0)
    return code


def _train_from(args: argparse.Namespace) -> int:
    from playseg_ros.offline import train

    return train(
        args.data,
        args.out,
        args.epochs,
        args.lr,
        args.batch_segments,
        args.seed,
        args.labeller,
        args.actions,
        args.overwrite,
        {"min_len": args.min_len, "max_len": args.max_len, "k_max": args.k_max},
        args.encoder,
        args.method,
        args.encoders_from,
        args.label_head,
        args.augment,
        args.label_accuracy,
        args.end_lookahead,
        {"max_steps": args.max_steps, "max_minutes": args.max_minutes, "patience": args.patience},
        args.device,
        args.val_share,
        args.resume,
    )


def _cmd_calibrate(args: argparse.Namespace) -> int:
    from playseg_ros.offline import calibrate

    return calibrate(args.model, args.data, args.out, args.label_accuracy, args.device)


def _cmd_segment(args: argparse.Namespace) -> int:
    from playseg_ros.offline import segment

    code = segment(
        args.model,
        args.input,
        args.out,
        args.splits.split(","),
        args.min_len,
        args.overwrite,
        args.keep_incomplete,
        args.method,
        args.seed,
        args.keep,
        args.device,
        args.engine,
        args.workers,
        args.address,
    )
    return _labels_out(args.out, args.labels_out, args.model) if code == 0 else code


def _labels_out(dataset: str, labels_out: str | None, model: str | None) -> int:
    """``--labels-out DIR``: the written dataset's segments as sidecar label files (docs/convert.md)."""
    from pathlib import Path

    from playseg_ros.convert.annotations import write_output_labels

    if labels_out:
        files = write_output_labels(Path(dataset), Path(labels_out), model)
        print(f"{labels_out}: {len(files)} label file(s)")
    return 0


def _cmd_evaluate(args: argparse.Namespace) -> int:
    from playseg_ros.offline import evaluate

    return evaluate(args.pred, args.truth, args.json, args.plot, args.plot_episodes)


LABELS_OUT_HELP = (
    "also write the segments as time-based labels, one sidecar file per bag (DIR/<bag name>.yaml), that "
    "`playseg convert` reads back"
)
LABEL_ACCURACY_HELP = (
    "label accuracy on the val split's annotated segments that the confidence threshold for keeping a "
    "segment is chosen for (default 0.95; the paper chose 0.90 for CALVIN)"
)


def _add_segmentation_commands(sub: argparse._SubParsersAction) -> None:
    train = sub.add_parser("train", help="train the Play Segmentation model on a dataset's annotated splits")
    train.add_argument("--data", required=True, help="dataset directory (train + val splits are used)")
    train.add_argument("--out", required=True, help="checkpoint file to write (e.g. models/ps.pt)")
    # Unset options take playseg_core.ps.training.TrainConfig's defaults (the measured best setting).
    train.add_argument(
        "--epochs",
        type=positive_int,
        help="exactly this many epochs, no early stopping (default: until the val loss stops improving, at "
        "most a step cap scaled to the data)",
    )
    train.add_argument(
        "--max-steps",
        type=positive_int,
        help="at most this many optimizer steps (default: scaled to the data)",
    )
    train.add_argument("--max-minutes", type=positive_float, help="stop after this many minutes of training")
    train.add_argument(
        "--patience",
        type=positive_int,
        help="stop when the held-out measure has not improved for this many evaluations (default: the method's)",
    )
    train.add_argument(
        "--val-share",
        type=float,
        help="without an annotated val split, hold out this share of the annotated episodes (at least one) "
        "for early stopping and calibration (default 0.2; 0: none, the model is then uncalibrated)",
    )
    train.add_argument(
        "--resume",
        action="store_true",
        help="continue a killed run from its training state (OUT.train-state, written every evaluation)",
    )
    add_device_argument(train)
    train.add_argument(
        "--nproc",
        type=positive_int,
        default=1,
        help="data-parallel training in N local processes (gloo on the CPU, NCCL on CUDA, one card each); "
        "torchrun can launch the command instead",
    )
    train.add_argument("--lr", type=positive_float, help="peak learning rate (default: TrainConfig)")
    train.add_argument(
        "--batch-segments", type=positive_int, help="annotated segments per batch (default: TrainConfig)"
    )
    train.add_argument("--seed", type=int, default=0)
    train.add_argument("--labeller", help="also train the stand-alone labelling model into this file")
    train.add_argument(
        "--overwrite", action="store_true", help="replace an existing --out (and --labeller) checkpoint"
    )
    train.add_argument(
        "--actions",
        default="auto",
        help="how the model reads the previous action: 'auto' (default: as the data declares it, discrete "
        "or continuous), 'none' (observations only), or a count N (discrete indices 0..N-1)",
    )
    train.add_argument(
        "--max-len", type=int, help="L_max, the longest segment in steps (default: from the data)"
    )
    train.add_argument(
        "--min-len", type=int, help="L_min, the shortest segment in steps (default: from the data)"
    )
    train.add_argument("--k-max", type=int, help="negatives shift by 1..k_max steps (default: from the data)")
    train.add_argument(
        "--encoder",
        action="append",
        metavar="FEATURE=KIND",
        help="step encoder of a feature instead of the default: image_cnn, state_mlp, discrete_action, "
        "continuous_action, a domain's kind (e.g. babyai.grid_tiles), or none (not read); repeatable",
    )
    train.add_argument(
        "--augment",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="each training clip under a random symmetry of the domain's world, its instruction turned with "
        "it (the domain's clip_symmetries; the default for a domain that declares them, --no-augment to "
        "train on the clips as recorded); for a domain without symmetries, rotate/mirror the camera frames "
        "by a random multiple of 90 degrees (with --actions none; only where instructions and ends do not "
        "depend on orientation: a room seen from above, not 'push the block left'); PS and the labelling model",
    )
    train.add_argument(
        "--label-head",
        choices=LABEL_HEADS,
        help="how PS scores an instruction: linear (one weight row per instruction) or text (from its words, "
        "shared between instructions: many compositional instructions, few segments each); default: the "
        "domain's choice, else linear",
    )
    train.add_argument(
        "--method",
        default="ps",
        choices=SEGMENTATION_METHODS,
        help="ps (default), or a baseline (docs/baselines.md): unloc, tridet, random or changepoint "
        "(the last two train the labelling model); --epochs, --lr, --batch-segments apply to each",
    )
    train.add_argument(
        "--encoders-from",
        metavar="CHECKPOINT",
        help="unloc and tridet: read the step encoders of this PS or labeller checkpoint, frozen (the paper "
        "gives its baselines pretrained features); default: their own, trained with them",
    )
    train.add_argument("--label-accuracy", type=float, help=LABEL_ACCURACY_HELP)
    train.add_argument(
        "--end-lookahead",
        type=int,
        help="PS: steps past a candidate end its end head also reads (0 = the paper's model; 1 reads the "
        "first command after the end, where a demonstrator's intent changes; live segmenting then decides "
        "each end that many steps later); default: the domain's choice, else 0",
    )
    train.set_defaults(func=_cmd_train)
    calibrate = sub.add_parser(
        "calibrate", help="re-choose a PS model's end bias and label threshold on a dataset's val split"
    )
    calibrate.add_argument("--model", required=True, help="PS checkpoint (rewritten unless --out is given)")
    calibrate.add_argument("--data", required=True, help="dataset whose annotated val split is used")
    calibrate.add_argument("--out", help="write the calibrated checkpoint here instead")
    calibrate.add_argument("--label-accuracy", type=float, help=LABEL_ACCURACY_HELP)
    add_device_argument(calibrate)
    calibrate.set_defaults(func=_cmd_calibrate)
    segment = sub.add_parser("segment", help="cut play into labelled segments with a trained PS model")
    segment.add_argument("--model", required=True, help="checkpoint from `playseg train` (of --method)")
    segment.add_argument("--input", required=True, help="dataset directory or play bag directory")
    segment.add_argument(
        "--out", required=True, help="output dataset directory (plus OUT/segments_bag for bags)"
    )
    segment.add_argument("--splits", default="play,test", help="dataset splits to segment (comma-separated)")
    segment.add_argument("--min-len", type=int, help="shortest segment in steps (default: the model's L_min)")
    segment.add_argument(
        "--overwrite", action="store_true", help="replace an existing --out (only a previous playseg dataset)"
    )
    segment.add_argument(
        "--keep-incomplete",
        action="store_true",
        help="also segment an episode that a bag cuts off before its end (a recovered recording); by default "
        "it is reported and skipped",
    )
    segment.add_argument(
        "--method",
        default="ps",
        choices=SEGMENTATION_METHODS,
        help="the method --model was trained for with `playseg train --method` (default ps)",
    )
    segment.add_argument("--seed", type=int, default=0, help="seed of the random windows (not ps)")
    segment.add_argument("--keep", default="label", choices=KEEP_RULE_CHOICES, help=KEEP_HELP)
    segment.add_argument("--labels-out", metavar="DIR", help=LABELS_OUT_HELP)
    add_device_argument(segment)
    segment.add_argument(
        "--engine",
        default="local",
        choices=["local", "ray"],
        help="local: this process; ray: episodes segmented by --workers Ray actors (a local Ray instance, "
        "or --address), the same output",
    )
    segment.add_argument("--workers", type=int, default=1, help="with --engine ray: actors (one CPU each)")
    segment.add_argument(
        "--address", help="with --engine ray: the Ray cluster to join (e.g. ray://head:10001)"
    )
    segment.set_defaults(func=_cmd_segment)
    evaluate = sub.add_parser("evaluate", help="metrics of segmented play against the ground truth")
    evaluate.add_argument("--pred", required=True, help="output of `playseg segment`")
    evaluate.add_argument("--truth", required=True, help="the dataset that was segmented")
    evaluate.add_argument("--json", help="metrics JSON path (default PRED/metrics.json)")
    evaluate.add_argument("--plot", help="timeline PNG path (default PRED/timeline.png)")
    evaluate.add_argument(
        "--plot-episodes", type=non_negative_int, default=6, help="episodes in the timeline (0: none)"
    )
    evaluate.set_defaults(func=_cmd_evaluate)


def _cmd_convert(args: argparse.Namespace) -> int:
    from pathlib import Path

    from playseg_ros.convert import SegmentationSpec, convert, inspect_text, load_mapping
    from playseg_ros.convert.run import playseg_copy

    if args.inspect:
        if len(args.bags) != 1 or args.out or args.mapping:
            raise PlaysegError("--inspect takes one bag and no --out or --mapping")
        print(inspect_text(Path(args.bags[0])), end="")
        return 0
    if not args.out:
        raise PlaysegError("--out is required (the dataset directory to write)")
    if (args.method or args.keep) and not args.segment:
        raise PlaysegError("--method and --keep are about the --segment model; give --segment MODEL")
    mapping = load_mapping(args.mapping) if args.mapping else None
    segmentation = (
        SegmentationSpec.of(args.segment, args.method or "ps", keep=args.keep or "label", device=args.device)
        if args.segment
        else None
    )
    summary = convert(
        args.bags, args.out, mapping, args.workers, args.overwrite, not args.quiet, output_format=args.format,
        segmentation=segmentation, engine=args.engine, address=args.address, val_share=args.val_share,
    )  # fmt: skip
    for report in summary.reports:
        for note in report.notes:
            print(f"{report.bag.name}: {note}", file=sys.stderr)
    for report in summary.failed:
        print(f"playseg convert: failed: {report.error}", file=sys.stderr)
    print(summary.text())
    print(summary.val_text())
    if summary.failed:
        return EXIT_FAILED
    dataset = args.out if args.format == "playseg" else str(playseg_copy(Path(args.out)))
    return _labels_out(dataset, args.labels_out, args.segment)


def _add_convert_command(sub: argparse._SubParsersAction) -> None:
    from playseg_core.data.splits import DEFAULT_VAL_SHARE  # the standard library only

    convert = sub.add_parser(
        "convert",
        help="convert robot bags (rosbag2, ROS 1) through a mapping into a dataset (docs/convert.md)",
    )
    convert.add_argument("bags", nargs="+", metavar="BAG_OR_DIR", help="bags, or directories holding bags")
    convert.add_argument("--out", help="dataset directory to write (a rerun skips the bags it holds)")
    convert.add_argument("--mapping", help="mapping YAML (not needed for playseg play bags)")
    convert.add_argument(
        "--format",
        default="playseg",
        choices=["playseg", "lerobot"],
        help="a playseg dataset or LeRobot v3.0",
    )
    convert.add_argument(
        "--segment",
        metavar="MODEL",
        help="segment the unannotated episodes with this checkpoint (kept: segments whose label confidence "
        "reaches its calibrated threshold, or as --keep says); annotated episodes keep their human labels",
    )
    convert.add_argument(
        "--method", choices=SEGMENTATION_METHODS, help="the --segment checkpoint's method (default: ps)"
    )
    convert.add_argument("--keep", choices=KEEP_RULE_CHOICES, help=f"with --segment: {KEEP_HELP}")
    convert.add_argument("--labels-out", metavar="DIR", help=LABELS_OUT_HELP)
    add_device_argument(convert)
    convert.add_argument("--workers", type=int, default=1, help="bags converted in parallel (processes)")
    convert.add_argument(
        "--val-share",
        type=float,
        default=DEFAULT_VAL_SHARE,
        metavar="S",
        help=f"share of the annotated episodes put in the val split, in [0, 1) (default {DEFAULT_VAL_SHARE}; "
        "0: all in train): the lowest by a hash of their id, at least one, none with fewer than 2; the same "
        "whatever --workers; a rerun with another share re-splits the dataset",
    )
    convert.add_argument(
        "--engine",
        default="local",
        choices=["local", "ray"],
        help="local: a process pool; ray: each bag a Ray task (a local Ray instance with --workers CPUs)",
    )
    convert.add_argument(
        "--address", help="with --engine ray: the Ray cluster to join (e.g. ray://head:10001)"
    )
    convert.add_argument("--overwrite", action="store_true", help="convert every bag again into a new --out")
    convert.add_argument(
        "--inspect", action="store_true", help="list BAG's topics and print a proposed mapping"
    )
    convert.add_argument("--quiet", action="store_true", help="no progress bar")
    convert.set_defaults(func=_cmd_convert)


def _cmd_experiment(args: argparse.Namespace) -> int:
    from playseg_core.experiment.runner import run_experiment

    conditions = [c for c in args.conditions.split(",") if c] if args.conditions else None
    kwargs = {"conditions": conditions} if conditions else {}
    run_experiment(args.domain, args.scale, args.seeds, args.out, args.workers, device=args.device, **kwargs)
    return 0


def _add_experiment_command(sub: argparse._SubParsersAction) -> None:
    experiment = sub.add_parser(
        "experiment",
        help="the paper's augmentation experiment: policies on the start split plus what each condition adds",
    )
    experiment.add_argument("domain", help="a domain with an experiment (e.g. babyai)")
    experiment.add_argument(
        "--scale", default="small", help="the domain's experiment size (e.g. tiny, small, paper)"
    )
    experiment.add_argument("--seeds", type=int, default=3, help="policy seeds per condition (default 3)")
    experiment.add_argument("--out", required=True, help="output directory; rerunning it resumes")
    experiment.add_argument("--workers", type=int, default=2, help="parallel generation and policy runs")
    experiment.add_argument(
        "--conditions",
        help="comma-separated conditions or groups, in table order (default: the group 'default' = "
        "gt_start,gt_2x,gt_4x,gt_100,oracle_relabel,random_relabel,ps; 'curve' = the ground-truth curve "
        "gt_1pct..gt_50pct with gt_start and gt_100; 'baselines' = unloc,tridet,changepoint; ps_balanced = "
        "what ps keeps, each instruction capped at its share of the start split; ps_own_cuts = PS's cuts "
        "kept by a threshold calibrated on its own val cuts; ps_own_cuts_balanced = those, capped)",
    )
    add_device_argument(experiment)
    experiment.set_defaults(func=_cmd_experiment)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="playseg",
        description="Play Segmentation for ROS 2 play recordings (see README.md).",
        epilog=f"exit codes: 0 done, {EXIT_FAILED} failed (one line on stderr says why), {EXIT_USAGE} bad "
        f"command line, {EXIT_INTERRUPTED} interrupted (partial outputs removed)",
    )
    parser.add_argument("--debug", action="store_true", help="print a traceback for every failure")
    from playseg_ros.review.command import add_review_command

    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    demo = sub.add_parser("demo", help="run the main job on the sample bags in bags/")
    demo.add_argument(
        "--train-models",
        action="store_true",
        help="instead: train the sample PS models the demo uses into bags/models (`make models`; about 90 minutes here)",
    )
    demo.set_defaults(func=_cmd_demo)
    _add_bag_commands(sub)
    _add_generate_command(sub)
    _add_up_command(sub)
    _add_segmentation_commands(sub)
    _add_convert_command(sub)
    _add_experiment_command(sub)
    add_review_command(sub)
    return parser


def _terminate(signum: int, frame: object) -> None:
    """SIGTERM unwinds like Ctrl-C, so every writer's ``with`` block removes its partial output."""
    raise KeyboardInterrupt


def _one_line(error: BaseException) -> str:
    text = str(error) or type(error).__name__
    return " ".join(text.split())


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    args.argv = list(sys.argv[1:] if argv is None else argv)
    command = " ".join(filter(None, ["playseg", args.command, getattr(args, "bag_command", None)]))
    previous = signal.signal(signal.SIGTERM, _terminate) if args.command != "up" else None
    try:
        return int(args.func(args) or 0)
    except KeyboardInterrupt:
        print(f"{command}: interrupted; partial outputs removed", file=sys.stderr)
        return EXIT_INTERRUPTED
    except EXPECTED_ERRORS as error:
        if args.debug:
            raise
        print(f"{command}: {_one_line(error)}", file=sys.stderr)
        return EXIT_FAILED
    except ModuleNotFoundError as error:
        # a third-party package missing is the environment's fault, not a bug: e.g. the I/O part installed
        # alone (requirements-io.txt) running a command that needs torch or ROS 2
        package = (error.name or "").split(".")[0]
        if args.debug or package in ("", "playseg_core", "playseg_ros"):
            raise
        print(f"{command}: needs {package}, which this environment lacks (docs/setup.md)", file=sys.stderr)
        return EXIT_FAILED
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)


if __name__ == "__main__":
    sys.exit(main())
