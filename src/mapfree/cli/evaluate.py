"""``mapfree evaluate``: score a submission ZIP against a split's ground truth."""

from __future__ import annotations

import argparse
import sys

from . import HelpFormatter


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "evaluate",
        help="score a submission ZIP (Map-free benchmark metrics)",
        description=(
            "Score a submission ZIP (pose_sNNNNN.txt files) against the ground truth of a split, exactly as the "
            "Map-free benchmark does: median errors, precision and AUC for pose (25 cm, 5°) and VCRE (90 px). "
            "Problems in the submission are listed as scene:line: reason. Exit code 1 only when the "
            "submission cannot be evaluated at all."
        ),
        epilog="examples:\n"
               "  mapfree evaluate submission.zip --dataset data/mapfree --split val --per-scene --plots plots/\n"
               "  mapfree evaluate submission.zip --dataset data/mapfree --json --frames > report.json\n"
               "  mapfree evaluate test.zip --dataset data/mapfree --split test --gt-root private_gt --compat official\n"
               "  mapfree evaluate multi.zip --dataset data/mapfree --track multi\n",
        formatter_class=HelpFormatter,
    )
    p.add_argument("submission", help="submission ZIP file")
    p.add_argument("--dataset", required=False, default=None,
                   help="dataset root holding SPLIT/sNNNNN/ (needed unless --gt-root holds everything)")
    p.add_argument("--split", default="val", choices=("train", "val", "test"), help="split to score (default val)")
    p.add_argument("--gt-root", default=None, help="root with private ground truth SPLIT/sNNNNN/poses.txt")
    p.add_argument("--track", default="single", choices=("single", "multi"),
                   help="leaderboard whose frames are scored: 'single' (every 5th query, default) or 'multi' "
                        "(the multi-frame track: queries 9, 19, 29, … of each scene)")
    p.add_argument("--compat", default="default", choices=("default", "official"),
                   help="'official' reproduces the public evaluator's quirks, for leaderboard-comparable numbers "
                        "(default: quirks fixed)")
    p.add_argument("--json", action="store_true", help="print the report as JSON")
    p.add_argument("--frames", action="store_true", help="with --json: include per-frame errors")
    p.add_argument("--per-scene", action="store_true", help="also print a per-scene table")
    p.add_argument("--plots", default=None, metavar="DIR", help="write the evaluation figures (PNG, PDF) here")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from ..benchmark import EvaluationError, evaluate, format_table
    from ..data import FormatError

    if args.dataset is None and args.gt_root is None:
        print("error: give --dataset (and/or --gt-root)", file=sys.stderr)
        return 1
    try:
        report = evaluate(args.submission, args.dataset, args.split, compat=args.compat, gt_root=args.gt_root,
                          track=args.track)
    except (EvaluationError, FormatError, FileNotFoundError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    if args.json:
        print(report.to_json(frames=args.frames))
    elif report.fatal:
        # Only the causes: the "no estimates" lines of every scene that follow from them add nothing.
        for p in report.problems:
            if p.fatal:
                print(f"error: {args.submission}: {p.reason if p.scene is None else p}", file=sys.stderr)
        return 1
    else:
        print(format_table(report, per_scene=args.per_scene), end="")
    if args.plots:
        from ..benchmark import save_plots

        for path in save_plots(report, args.plots):
            print(f"wrote {path}", file=sys.stderr)
    return 1 if report.fatal else 0
