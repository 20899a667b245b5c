"""The `playseg review` command line (the standard library only: building the parser imports nothing
heavy)."""

from __future__ import annotations

import argparse


def add_review_command(sub: argparse._SubParsersAction) -> None:
    review = sub.add_parser(
        "review", help="annotate play and review a model's proposals in the browser (docs/review.md)"
    )
    review.add_argument(
        "inputs",
        nargs="+",
        metavar="DATASET_OR_BAGS",
        help="a playseg dataset, or bags (directories of bags) converted on the fly with --mapping (cached)",
    )
    review.add_argument(
        "--mapping", help="the `playseg convert` mapping of the bags (not for playseg play bags)"
    )
    review.add_argument("--model", help="a PS checkpoint: propose segments for the episodes not yet reviewed")
    review.add_argument(
        "--labels", metavar="DIR", help="where the labels are kept (default DATASET.review/labels)"
    )
    review.add_argument(
        "--host",
        default="127.0.0.1",
        help="address to bind (default localhost; any other gets a token in the URL)",
    )
    review.add_argument("--port", type=int, default=8765, help="port (default 8765; 0: any free port)")
    review.add_argument(
        "--video-chunk",
        type=int,
        metavar="FRAMES",
        help="observations per video file, each encoded when first shown (default 300)",
    )
    review.set_defaults(func=_cmd_review)


def _cmd_review(args: argparse.Namespace) -> int:
    from playseg_ros.review.app import review

    return review(args.inputs, args.model, args.labels, args.host, args.port, args.mapping, args.video_chunk)
