"""The `playseg` command line: one entry point, one subcommand per job."""

from __future__ import annotations

import argparse
import sys


def _cmd_demo(args: argparse.Namespace) -> int:
    from playseg_ros.demo import run_demo

    return run_demo()


def _cmd_bag_info(args: argparse.Namespace) -> int:
    from playseg_ros.bag_io import BagError, bag_info_text

    try:
        print(bag_info_text(args.path))
    except BagError as error:
        print(f"playseg bag info: {error}", file=sys.stderr)
        return 1
    return 0


def _cmd_bag_recover(args: argparse.Namespace) -> int:
    from playseg_ros.bag_io import BagError, recover_bag

    try:
        report = recover_bag(args.path)
    except BagError as error:
        print(f"playseg bag recover: {error}", file=sys.stderr)
        return 1
    for item in report:
        action = f"rebuilt, {item.dropped_bytes} trailing bytes dropped" if item.rebuilt else "finished, kept"
        print(f"{item.path}: {item.messages} messages ({action})")
    return 0


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


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="playseg", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    demo = sub.add_parser("demo", help="run the main job on the sample bags in bags/")
    demo.set_defaults(func=_cmd_demo)
    _add_bag_commands(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    return int(args.func(args) or 0)


if __name__ == "__main__":
    sys.exit(main())
