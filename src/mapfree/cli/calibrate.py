"""``mapfree calibrate``: fit a method's calibrated probability that its pose is right."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from . import HelpFormatter


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "calibrate",
        help="fit the probability that a method's pose is right (p_correct) on a split with ground truth",
        description=(
            "Run a method on every query of a split with ground-truth poses (or read the journal of such a run) and "
            "fit p_correct = P(VCRE < 90 px) and p_pose = P(error < 25 cm and 5°) from each estimate's signals "
            "(inliers, ratios, residuals, scale agreement): a logistic model followed by an isotonic map "
            "(scikit-learn), written as JSON with its cross-validated ECE, Brier score and precision. Use the file "
            "with `mapfree run --calibration FILE` (and --confidence calibrated)."
        ),
        epilog="examples:\n"
        "  mapfree calibrate data/mapfree --split val --method best-offline -o best-offline.calib.json\n"
        "  mapfree calibrate data/mapfree --method best-offline --journal runs/val.journal.jsonl -o bo.calib.json\n"
        "  mapfree calibrate data/mapfree data/synthetic --method best-offline -o best-offline.calib.json\n",
        formatter_class=HelpFormatter,
    )
    p.add_argument("roots", type=Path, nargs="+", metavar="ROOT", help="dataset root(s) holding SPLIT/sNNNNN/")
    p.add_argument("--split", default="val", help="a split with ground-truth poses (default val)")
    p.add_argument("--method", required=True, help="method name, A+B (a cascade) or YAML file")
    p.add_argument("-o", "--output", type=Path, required=True, help="the calibration file to write (.json)")
    p.add_argument(
        "--journal",
        type=Path,
        action="append",
        default=None,
        help="read this run journal (OUTPUT.journal.jsonl of `mapfree run --all-frames`) instead of running; "
        "once per ROOT, in order",
    )
    p.add_argument("--workers", type=int, default=1, help="parallel processes of the run (default 1)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from . import fail, output_file_problem

    problem = output_file_problem("-o", args.output, (".json",))
    if problem:
        return fail("calibrate", problem)
    if args.journal is not None:
        if len(args.journal) != len(args.roots):
            return fail("calibrate", f"--journal given {len(args.journal)} times for {len(args.roots)} ROOT(s)")
        missing = [j for j in args.journal if not j.is_file()]
        if missing:
            return fail("calibrate", f"--journal {missing[0]}: no such file")
    if args.workers < 1:
        return fail("calibrate", "--workers must be >= 1")
    from ..calibration import CalibrationError
    from ..data import FormatError
    from ..relocalize.calibrate import calibrate

    stem = args.output.name.removesuffix(".json")
    runs = [args.output.with_name(f"{stem}.run{i if i else ''}.zip") for i in range(len(args.roots))]
    try:
        cal = calibrate(
            args.roots,
            args.split,
            args.method,
            journals=args.journal,
            run_outputs=runs,
            workers=args.workers,
            progress=not args.no_progress,
        )
        cal.save(args.output)
    except (CalibrationError, FormatError, FileNotFoundError, KeyError, ValueError, OSError) as e:
        return fail("calibrate", e)
    for target, fig in cal.figures.items():
        prec = fig["precision"].get("0.9")
        print(
            f"{target}: {fig['frames']} frames, held-out ECE {fig['ece']:.3f}, Brier {fig['brier']:.3f}, "
            f"precision at p>=0.9 {'-' if prec is None else f'{prec:.2f}'} ({fig['accepted']['0.9']} frames)"
        )
    print(f"wrote {args.output} (signals: {', '.join(cal.signals)})", file=sys.stderr)
    return 0
