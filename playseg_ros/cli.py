"""The `playseg` command line: one entry point, one subcommand per job."""

from __future__ import annotations

import argparse
import sys

DEFAULT_DOMAIN = "babyai"
"""The domain `playseg generate` plays in unless told otherwise (the sample bags' domain)."""


def _cmd_demo(args: argparse.Namespace) -> int:
    from playseg_ros.demo import run_demo

    return run_demo()


def _cmd_bag_info(args: argparse.Namespace) -> int:
    from playseg_ros.bag import BagError, bag_info_text

    try:
        print(bag_info_text(args.path))
    except BagError as error:
        print(f"playseg bag info: {error}", file=sys.stderr)
        return 1
    return 0


def _cmd_bag_recover(args: argparse.Namespace) -> int:
    from playseg_ros.bag import BagError, recover_bag

    try:
        report = recover_bag(args.path)
    except BagError as error:
        print(f"playseg bag recover: {error}", file=sys.stderr)
        return 1
    for item in report:
        action = f"rebuilt, {item.dropped_bytes} trailing bytes dropped" if item.rebuilt else "finished, kept"
        print(f"{item.path}: {item.messages} messages ({action})")
    return 0


def _cmd_generate(args: argparse.Namespace) -> int:
    from playseg_core.domains import load_domain

    try:
        domain = load_domain(args.domain)
        presets = getattr(domain, "PRESET_NAMES", ())
        if args.preset not in presets:
            raise ValueError(f"domain {args.domain!r} has presets {list(presets)}, not {args.preset!r}")
        summary = domain.generate_dataset(
            args.out,
            args.preset,
            seed=args.seed,
            workers=args.workers,
            progress=not args.quiet,
            overwrite=args.overwrite,
            annotated_share=args.annotated_share,
        )
    except (FileExistsError, ValueError) as error:
        print(f"playseg generate: {error}", file=sys.stderr)
        return 1
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
        from playseg_ros.bag import BagError
        from playseg_ros.play_bags import write_dataset_bags

        bag_dir = summary.path / "bags"
        try:
            bags = write_dataset_bags(summary.path, bag_dir)
        except (BagError, FileExistsError) as error:
            print(f"playseg generate --bag: {error}", file=sys.stderr)
            return 1
        for name, bag in bags.items():
            size = sum(f.stat().st_size for f in bag.path.rglob("*") if f.is_file())
            print(f"{bag.path}: {name} bag, {bag.message_count} messages, {size / 1e6:.2f} MB")
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
    generate.add_argument("--workers", type=int, default=1, help="generator processes")
    generate.add_argument(
        "--annotated-share",
        type=float,
        default=None,
        help="share of the non-test segments that is annotated (0.1, 0.25, 0.5, 1.0); preset default if unset",
    )
    generate.add_argument("--overwrite", action="store_true", help="replace an existing dataset at --out")
    generate.add_argument("--quiet", action="store_true", help="no progress bar")
    generate.add_argument(
        "--bag",
        action="store_true",
        help="also write the episodes as play bags: OUT/bags/annotated (train+val), play, test",
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

    try:
        return run_graph(args.config)
    except ValueError as error:
        print(f"playseg up: {error}", file=sys.stderr)
        return 2


def _add_up_command(sub: argparse._SubParsersAction) -> None:
    up = sub.add_parser(
        "up", help="bring up a graph of playseg nodes from a YAML config (Ctrl-C stops all of them)"
    )
    up.add_argument("config", help="graph config, e.g. config/live_play.yaml (see docs/nodes.md)")
    up.set_defaults(func=_cmd_up)


def _cmd_train(args: argparse.Namespace) -> int:
    from playseg_ros.offline import train

    try:
        return train(
            args.data,
            args.out,
            args.epochs,
            args.lr,
            args.batch_segments,
            args.seed,
            args.labeller,
            args.actions,
        )
    except ValueError as error:
        print(f"playseg train: {error}", file=sys.stderr)
        return 1


def _cmd_calibrate(args: argparse.Namespace) -> int:
    from playseg_ros.offline import calibrate

    try:
        return calibrate(args.model, args.data, args.out)
    except (ValueError, FileNotFoundError) as error:
        print(f"playseg calibrate: {error}", file=sys.stderr)
        return 1


def _cmd_segment(args: argparse.Namespace) -> int:
    from playseg_ros.offline import segment

    try:
        return segment(args.model, args.input, args.out, args.splits.split(","), args.min_len, args.overwrite)
    except (ValueError, FileExistsError, FileNotFoundError) as error:
        print(f"playseg segment: {error}", file=sys.stderr)
        return 1


def _cmd_evaluate(args: argparse.Namespace) -> int:
    from playseg_ros.offline import evaluate

    return evaluate(args.pred, args.truth, args.json, args.plot, args.plot_episodes)


def _add_segmentation_commands(sub: argparse._SubParsersAction) -> None:
    train = sub.add_parser("train", help="train the Play Segmentation model on a dataset's annotated splits")
    train.add_argument("--data", required=True, help="dataset directory (train + val splits are used)")
    train.add_argument("--out", required=True, help="checkpoint file to write (e.g. models/ps.pt)")
    # Unset options take playseg_core.ps.training.TrainConfig's defaults (the measured best setting).
    train.add_argument(
        "--epochs", type=int, help="exactly this many epochs (default: TrainConfig's, more on small data)"
    )
    train.add_argument("--lr", type=float, help="peak learning rate (default: TrainConfig)")
    train.add_argument(
        "--batch-segments", type=int, help="annotated segments per batch (default: TrainConfig)"
    )
    train.add_argument("--seed", type=int, default=0)
    train.add_argument("--labeller", help="also train the stand-alone labelling model into this file")
    train.add_argument(
        "--actions",
        default="auto",
        help="how the model reads the previous action: 'auto' (default: the action the data declares, "
        "if discrete), 'none' (observations only), or a count N (discrete indices 0..N-1)",
    )
    train.set_defaults(func=_cmd_train)
    calibrate = sub.add_parser(
        "calibrate", help="re-choose a PS model's end bias and label threshold on a dataset's val split"
    )
    calibrate.add_argument("--model", required=True, help="PS checkpoint (rewritten unless --out is given)")
    calibrate.add_argument("--data", required=True, help="dataset whose annotated val split is used")
    calibrate.add_argument("--out", help="write the calibrated checkpoint here instead")
    calibrate.set_defaults(func=_cmd_calibrate)
    segment = sub.add_parser("segment", help="cut play into labelled segments with a trained PS model")
    segment.add_argument("--model", required=True, help="PS checkpoint from `playseg train`")
    segment.add_argument("--input", required=True, help="dataset directory or play bag directory")
    segment.add_argument(
        "--out", required=True, help="output dataset directory (plus OUT/segments_bag for bags)"
    )
    segment.add_argument("--splits", default="play,test", help="dataset splits to segment (comma-separated)")
    segment.add_argument("--min-len", type=int, default=1, help="shortest segment in steps")
    segment.add_argument("--overwrite", action="store_true", help="replace an existing --out")
    segment.set_defaults(func=_cmd_segment)
    evaluate = sub.add_parser("evaluate", help="metrics of segmented play against the ground truth")
    evaluate.add_argument("--pred", required=True, help="output of `playseg segment`")
    evaluate.add_argument("--truth", required=True, help="the dataset that was segmented")
    evaluate.add_argument("--json", help="metrics JSON path (default PRED/metrics.json)")
    evaluate.add_argument("--plot", help="timeline PNG path (default PRED/timeline.png)")
    evaluate.add_argument("--plot-episodes", type=int, default=6, help="episodes in the timeline (0: none)")
    evaluate.set_defaults(func=_cmd_evaluate)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="playseg", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    demo = sub.add_parser("demo", help="run the main job on the sample bags in bags/")
    demo.set_defaults(func=_cmd_demo)
    _add_bag_commands(sub)
    _add_generate_command(sub)
    _add_up_command(sub)
    _add_segmentation_commands(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    return int(args.func(args) or 0)


if __name__ == "__main__":
    sys.exit(main())
