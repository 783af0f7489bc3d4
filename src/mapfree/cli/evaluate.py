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
            "Problems in the submission are listed as scene:line: reason. Exit status: 0 scored, 1 the "
            "submission cannot be evaluated at all, 3 not a single scored frame has an estimate (with --strict: "
            "any frame without an estimate or any problem)."
        ),
        epilog="examples:\n"
        "  mapfree evaluate submission.zip --dataset data/mapfree --split val --per-scene --plots plots/\n"
        "  mapfree evaluate submission.zip --dataset data/mapfree --json --frames > report.json\n"
        "  mapfree evaluate test.zip --dataset data/mapfree --split test --gt-root private_gt --compat official\n"
        "  mapfree evaluate multi.zip --dataset data/mapfree --track multi\n"
        "  mapfree evaluate sub.zip --dataset data/mapfree --html report.html --viz figures/\n",
        formatter_class=HelpFormatter,
    )
    p.add_argument("submission", help="submission ZIP file")
    p.add_argument(
        "--dataset",
        required=False,
        default=None,
        help="dataset root holding SPLIT/sNNNNN/ (needed unless --gt-root holds everything)",
    )
    p.add_argument("--split", default="val", choices=("train", "val", "test"), help="split to score (default val)")
    p.add_argument("--gt-root", default=None, help="root with private ground truth SPLIT/sNNNNN/poses.txt")
    p.add_argument(
        "--track",
        default="single",
        choices=("single", "multi"),
        help="leaderboard whose frames are scored: 'single' (every 5th query, default) or 'multi' "
        "(the multi-frame track: queries 9, 19, 29, … of each scene)",
    )
    p.add_argument(
        "--compat",
        default="default",
        choices=("default", "official"),
        help="'official' reproduces the public evaluator's quirks, for leaderboard-comparable numbers "
        "(default: quirks fixed)",
    )
    p.add_argument("--json", action="store_true", help="print the report as JSON")
    p.add_argument("--frames", action="store_true", help="with --json: include per-frame errors")
    p.add_argument("--per-scene", action="store_true", help="also print a per-scene table")
    p.add_argument("--plots", default=None, metavar="DIR", help="write the evaluation figures (PNG, PDF) here")
    p.add_argument(
        "--html",
        default=None,
        metavar="FILE",
        help="write one self-contained HTML report: tables, figures, the worst frames with pictures",
    )
    p.add_argument(
        "--viz",
        default=None,
        metavar="DIR",
        help="with --html: the folder `mapfree run --viz DIR` drew into, for the worst frames' figures "
        "(default: draw the AR check from the dataset's images)",
    )
    p.add_argument("--worst", type=int, default=8, metavar="N", help="with --html: frames shown (default 8)")
    p.add_argument(
        "--strict",
        action="store_true",
        help="exit 3 unless every scored frame has an estimate and the submission has no problem",
    )
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from pathlib import Path

    from . import EXIT_ERROR, EXIT_NOTHING, fail

    if args.dataset is None and args.gt_root is None:
        return fail("evaluate", "give --dataset (and/or --gt-root)")
    for flag, value in (("--plots", args.plots), ("--viz", args.viz)):
        if value is not None and Path(value).exists() and not Path(value).is_dir():
            return fail("evaluate", f"{flag} {value}: not a folder (it names a file)")
    if args.worst < 0:
        return fail("evaluate", f"--worst must be >= 0, got {args.worst}")
    if args.html is not None and Path(args.html).is_dir():
        return fail("evaluate", f"--html {args.html}: a folder; give the report's file name (e.g. report.html)")
    from ..benchmark import EvaluationError, evaluate, format_table
    from ..data import FormatError

    try:
        report = evaluate(
            args.submission, args.dataset, args.split, compat=args.compat, gt_root=args.gt_root, track=args.track
        )
    except (EvaluationError, FormatError, FileNotFoundError, ValueError) as e:
        return fail("evaluate", e)
    if args.json:
        print(report.to_json(frames=args.frames))
    elif report.fatal:
        # Only the causes: the "no estimates" lines of every scene that follow from them add nothing.
        for p in report.problems:
            if p.fatal:
                print(
                    f"mapfree evaluate: error: {args.submission}: {p.reason if p.scene is None else p}", file=sys.stderr
                )
        return EXIT_ERROR
    else:
        print(format_table(report, per_scene=args.per_scene), end="")
    if args.plots:
        from ..benchmark import save_plots

        for path in save_plots(report, args.plots):
            print(f"wrote {path}", file=sys.stderr)
    if args.html:
        from ..benchmark.html import write_html

        figure, note = _figure_source(args)
        path = write_html(
            report,
            args.html,
            title=f"Map-free evaluation of {Path(args.submission).name}",
            figure=figure,
            worst=args.worst,
            source_note=note,
        )
        print(f"wrote {path}", file=sys.stderr)
    if report.fatal:
        return EXIT_ERROR
    n_est, n = int(report.estimated.sum()), len(report.estimated) + report.extra_failures
    if n_est == 0 or (args.strict and (n_est < n or report.problems)):
        mixup = [p.reason for p in report.problems if p.scene is None and "--track" in p.reason]
        why = (
            "; ".join(["no scored frame has an estimate", *mixup])
            if n_est == 0
            else f"{n - n_est} scored frame(s) without an estimate, {len(report.problems)} problem(s)"
        )
        print(f"mapfree evaluate: {why}", file=sys.stderr)
        return EXIT_NOTHING
    return 0


def _figure_source(args: argparse.Namespace):
    """``(figure(scene, frame) -> PNG bytes | None, a note saying where the pictures come from)`` for --html:
    the figure ``mapfree run --viz`` drew (matches + AR check), else the AR check drawn from the dataset's
    images with the submission's pose, else none (no dataset images: only --gt-root)."""
    from pathlib import Path

    from ..benchmark.html import frame_figure_path

    root = Path(args.dataset) / args.split if args.dataset else None
    state: dict = {"submission": args.submission}

    def figure(scene: str, frame: str):
        if args.viz:
            for suffix in (".jpg", ".png"):  # .png: figures of a run before they were JPEG
                p = frame_figure_path(args.viz, scene, frame, suffix)
                if p.is_file():
                    from ..viz import report_picture

                    return report_picture(p.read_bytes())
        if root is None or not (root / scene).is_dir():
            return None
        try:
            return _draw_from_data(root / scene, scene, frame, state)
        except Exception as e:  # a picture is a by-product: the report is written without it
            print(f"mapfree evaluate: no figure for {scene} {frame}: {e}", file=sys.stderr)
            return None

    if args.viz:
        note = (
            f"Figures from {args.viz} (drawn by mapfree run --viz: matches and AR check); frames it has no "
            f"figure for are drawn from the dataset (AR check only)."
        )
    elif root is not None:
        note = (
            "AR check drawn from the dataset's images with the submission's pose (cyan: ground truth, orange: "
            "estimate); run with --viz DIR and pass --viz DIR here to also see the matches."
        )
    else:
        note = "No figures: pass --dataset with the images (or --viz DIR of the run)."
    return figure, note


def _draw_from_data(scene_dir, scene: str, frame: str, state: dict):
    """The AR check of one submitted pose against the scene's reference image (ground truth when the data has it)."""
    from ..benchmark import read_submission
    from ..data import Scene
    from ..geometry import Pose
    from ..viz import ar_panels, jpeg_bytes

    if "estimates" not in state:
        state["estimates"] = read_submission(state["submission"])[0]
    est = state["estimates"].get(scene)
    if est is None or frame not in est.names:
        return None
    i = est.names.index(frame)
    s = Scene(scene_dir)
    ref, query = s.reference, s.frame(frame)
    ref_pose = ref.pose if ref.pose is not None else Pose.identity()
    rel = Pose.from_qt(est.q[i], est.t[i]) @ ref_pose.inverse()
    gt = query.pose @ ref_pose.inverse() if query.pose is not None else None
    return jpeg_bytes(ar_panels(ref.image(), query.image(), ref.intrinsics, query.intrinsics, rel, gt))
