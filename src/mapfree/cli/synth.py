"""``mapfree synth``: write a synthetic split in the Map-free layout."""

from __future__ import annotations

import argparse
import time

DESCRIPTION = """\
Render synthetic Map-free scenes: a textured sculpture or mural (real photos from scikit-image) on textured
ground among building facades, seen by phone cameras walking 1-10 m away under changing light.

Writes ROOT/SPLIT/sNNNNN/ with intrinsics.txt, poses.txt, seq0/ and seq1/ JPEGs, metric ground-truth depth
(frame.sensor.png) and a simulated monocular estimate (frame.mono.png). Train scenes hold two scans and
overlaps.npz; val/test scenes a reference (seq0/frame_00000.jpg, identity pose) and queries, some of which
see nothing of the reference. Test poses.txt holds zeros; --private-gt writes the true poses elsewhere.
The same --seed always writes byte-identical files."""

EPILOG = """\
examples:
  mapfree synth data/synth --split val --scenes 10 --queries 40
  mapfree synth data/synth --split train --scenes 20 --train-frames 80
  mapfree synth data/synth --split test --scenes 5 --private-gt data/synth-gt
  mapfree synth data/raw --split scans --scenes 3 --scan-frames 12 --private-gt data/raw-gt
"""


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "synth",
        help="generate synthetic scenes in the Map-free layout",
        description=DESCRIPTION,
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("root", metavar="ROOT", help="dataset root; scenes go to ROOT/SPLIT/sNNNNN")
    p.add_argument(
        "--split",
        choices=("train", "val", "test", "scans"),
        default="val",
        help="split to write (default: val); scans: raw phone scans for `mapfree build`",
    )
    p.add_argument("--scenes", type=int, default=10, help="number of scenes (default: 10)")
    p.add_argument("--queries", type=int, default=40, help="queries per val/test scene (default: 40)")
    p.add_argument(
        "--train-frames", type=int, default=50, help="frames per train scan, two scans a scene (default: 50)"
    )
    p.add_argument("--seed", type=int, default=0, help="random seed; same seed, same files (default: 0)")
    p.add_argument("--first-scene", type=int, default=0, help="number of the first scene id (default: 0 -> s00000)")
    p.add_argument("--size", default="540x720", metavar="WxH", help="image size, width x height (default: 540x720)")
    p.add_argument(
        "--no-overlap",
        type=float,
        default=0.2,
        metavar="FRAC",
        help="fraction of val/test queries that see nothing of the reference (default: 0.2)",
    )
    p.add_argument(
        "--private-gt",
        metavar="DIR",
        help="test/scans split: write true poses (and scans' overlaps) to DIR/SPLIT/sNNNNN/",
    )
    p.add_argument(
        "--scan-frames", type=int, default=12, help="scans split: images per scan, two scans a place (default: 12)"
    )
    p.add_argument("--no-mono", action="store_true", help="skip the simulated monocular depth (frame.mono.png)")
    p.add_argument("--workers", type=int, default=1, help="scenes rendered in parallel processes (default: 1)")
    p.add_argument("--force", action="store_true", help="replace scenes that already exist (default: refuse)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from ..data.synth import SynthOptions, generate
    from . import fail, output_folder_problem

    try:
        w, h = (int(x) for x in args.size.lower().split("x"))
    except ValueError:
        return fail("synth", f"--size must look like 540x720, got {args.size!r}")
    if args.private_gt and args.split not in ("test", "scans"):
        return fail("synth", "--private-gt only applies to --split test or scans")
    checks = [
        (w < 32 or h < 32, f"--size {args.size}: both sides must be >= 32 px"),
        *(
            (getattr(args, k.replace("-", "_")) < 1, f"--{k} must be >= 1, got {getattr(args, k.replace('-', '_'))}")
            for k in ("scenes", "queries", "train-frames", "workers")
        ),
        (args.first_scene < 0, f"--first-scene must be >= 0, got {args.first_scene}"),
        (not 0 <= args.no_overlap < 1, f"--no-overlap must be in [0, 1), got {args.no_overlap}"),
    ]
    problem = next((msg for bad, msg in checks if bad), None) or output_folder_problem("ROOT", args.root)
    if problem:
        return fail("synth", problem)
    from pathlib import Path

    folder = Path(args.root) / args.split
    targets = [folder / f"s{args.first_scene + k:05d}" for k in range(args.scenes)]
    existing = [t.name for t in targets if t.is_dir() and any(t.iterdir())]
    if existing and not args.force:
        listed = ", ".join(existing[:4]) + (" …" if len(existing) > 4 else "")
        return fail(
            "synth",
            f"{folder} already holds {len(existing)} of these scenes ({listed}): --force replaces "
            f"them, --first-scene N writes new ones beside them",
        )
    opts = SynthOptions(
        queries=args.queries,
        train_frames=args.train_frames,
        width=w,
        height=h,
        no_overlap_fraction=args.no_overlap,
        first_scene=args.first_scene,
        write_mono=not args.no_mono,
        workers=args.workers,
    )
    t0 = time.perf_counter()
    if args.split == "scans":
        return _scans(args, opts, t0, existing)
    dirs = generate(
        args.root, args.split, args.scenes, args.queries, args.seed, args.private_gt, opts, progress=not args.quiet
    )
    dt = time.perf_counter() - t0
    replaced = f", replacing {len(existing)} that existed" if existing else ""
    print(
        f"wrote {len(dirs)} {args.split} scene{'s' if len(dirs) != 1 else ''} under {args.root}/{args.split}"
        f"{replaced} in {dt:.1f} s"
    )
    if args.private_gt:
        print(f"private ground truth under {args.private_gt}/test")
    return 0


def _scans(args: argparse.Namespace, opts, t0: float, existing: list[str]) -> int:
    from ..data.synth.scans import ScanOptions, generate_scans
    from . import fail

    if args.scan_frames < 3:
        return fail("synth", "--scan-frames must be >= 3")
    dirs = generate_scans(
        args.root,
        args.scenes,
        args.seed,
        ScanOptions(frames=args.scan_frames, synth=opts),
        args.private_gt,
        args.first_scene,
        progress=not args.quiet,
    )
    replaced = f", replacing {len(existing)} that existed" if existing else ""
    print(
        f"wrote {len(dirs)} place{'s' if len(dirs) != 1 else ''} of raw scans under {args.root}/scans{replaced} in "
        f"{time.perf_counter() - t0:.1f} s"
    )
    if args.private_gt:
        print(f"true poses and overlaps under {args.private_gt}/scans")
    return 0
