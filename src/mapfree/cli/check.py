"""``mapfree check``: verify a Map-free download (or copy, or build) — scenes, text files, images, depth maps."""

from __future__ import annotations

import argparse
from pathlib import Path

from . import EXIT_ERROR, EXIT_OK, HelpFormatter, fail, plural

DESCRIPTION = """\
Verify a Map-free dataset folder: the split folders and their scenes (the release: 460 train s00000-s00459,
65 val s00460-s00524, 130 test s00525-s00654), every scene's intrinsics.txt and poses.txt (a malformed line is
named FILE:LINE), every listed image present with a readable header of the size its intrinsics give (--deep:
decoded), the val/test reference frame, train overlaps.npz, poses_device.txt where present, and the depth maps
beside the images, counted per suffix. Prints a table per split and every problem; exit status 0 when nothing
is wrong, 1 otherwise."""

EPILOG = """\
examples:
  mapfree check data/mapfree                  # the whole release
  mapfree check data/mapfree --split val      # only the val split
  mapfree check data/synth --subset           # a partial copy, synthetic or built scenes: no scene counts
  mapfree check data/mapfree --deep --workers 4
"""


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "check",
        help="verify a Map-free dataset download: scenes, files, images",
        description=DESCRIPTION,
        epilog=EPILOG,
        formatter_class=HelpFormatter,
    )
    p.add_argument("root", type=Path, metavar="ROOT", help="dataset root holding train/, val/, test/")
    p.add_argument(
        "--split",
        action="append",
        choices=["train", "val", "test"],
        help="check only this split (repeatable; default: all three, or those present with --subset)",
    )
    p.add_argument(
        "--subset",
        action="store_true",
        help="any subset of sNNNNN scenes is fine (partial copies, synthetic or built data)",
    )
    p.add_argument("--deep", action="store_true", help="decode every image and depth map (slow)")
    p.add_argument("--workers", type=int, default=1, help="scenes checked in parallel processes (default 1)")
    p.add_argument("--json", action="store_true", help="print the report as JSON instead of tables")
    p.add_argument(
        "--max-problems",
        type=int,
        default=50,
        metavar="N",
        help="problems printed (all of them with --json; default 50)",
    )
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import json

    from rich.console import Console
    from rich.progress import track
    from rich.table import Table

    from ..data.check import check_dataset

    if args.workers < 1:
        return fail("check", "--workers must be >= 1")
    if args.max_problems < 0:
        return fail("check", f"--max-problems must be >= 0, got {args.max_problems}")
    if not args.root.is_dir():
        from ..data.check import not_a_dataset_folder

        return fail("check", f"{args.root}: {not_a_dataset_folder(args.root)}")
    err = Console(stderr=True)
    show = not args.json and err.is_terminal
    report = check_dataset(
        args.root,
        args.split,
        subset=args.subset,
        deep=args.deep,
        workers=args.workers,
        progress=(lambda it, n: track(it, total=n, description="checking scenes", console=err, transient=True))
        if show
        else None,
    )
    if args.json:
        print(json.dumps(report.to_dict(), indent=2))
        return EXIT_OK if report.ok else EXIT_ERROR

    out = Console(soft_wrap=False)
    mode = ("deep: every image decoded" if report.deep else "image headers") + (", subset" if report.subset else "")
    table = Table(title=f"{report.root} ({mode})")
    for col in ("split", "scenes", "frames", "images checked", "unlisted images", "depth maps", "problems"):
        table.add_column(col, justify="left" if col in ("split", "depth maps") else "right")
    for s in report.splits:
        scenes = f"{s.scenes}" if s.expected is None else f"{s.scenes}/{s.expected}"
        depth = ", ".join(f"{k} {n}" for k, n in sorted(s.depth.items())) or "none"
        table.add_row(
            s.split,
            scenes,
            str(s.frames),
            str(s.images_checked),
            str(s.unlisted_images),
            depth,
            f"[red]{len(s.problems)}[/red]" if s.problems else "0",
        )
    if report.splits:
        out.print(table)
    problems = report.all_problems
    for p in problems[: args.max_problems]:
        out.print(str(p), markup=False, highlight=False, soft_wrap=True)
    if len(problems) > args.max_problems:
        out.print(f"… and {len(problems) - args.max_problems} more (--max-problems N, or --json for all)")
    out.print(
        "OK: nothing missing or unreadable" if report.ok else f"{plural(len(problems), 'problem')} found",
        style="green" if report.ok else "red",
    )
    if not report.subset and any(s.expected is not None and s.scenes != s.expected for s in report.splits):
        out.print("(a partial copy, or scenes of your own? --subset checks only the scenes that are there)")
    return EXIT_OK if report.ok else EXIT_ERROR
