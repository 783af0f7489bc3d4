"""``mapfree build``: Map-free scenes from your own scans (SfM, metric scale, overlaps, correspondences)."""

from __future__ import annotations

import argparse
import time
from dataclasses import replace

DESCRIPTION = """\
Turn raw scans of places into Map-free scenes. SCANS holds one folder per place, each with two or more scan
folders (images or a video, optional intrinsics.txt, rgb.txt timestamps and device_poses.txt in TUM format).
All scans of a place are reconstructed together with pycolmap, scaled to metres from the device track (or
depth maps), and written as ROOT/SPLIT/sNNNNN with intrinsics.txt, poses.txt, poses_device.txt, overlaps.npz,
build_report.json and build_report.png. Train scenes keep both scans in one metric frame (origin: the first
registered frame of scan 0); val/test scenes keep that frame as the reference (identity) and scan 1 as
queries (test poses.txt holds zeros; --private-gt writes the true ones). Finished places are skipped."""

EPILOG = """\
examples:
  mapfree synth data/raw --split scans --scenes 3 --private-gt data/raw-gt
  mapfree build data/raw/scans --out data/built --split train --workers 2 --correspondences
  mapfree build data/raw/scans --out data/built --split val --ray local
  mapfree build /shared/scans --out /shared/built --split train --ray ray://head:10001
"""


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "build",
        help="build Map-free scenes from your own scans (pycolmap SfM)",
        description=DESCRIPTION,
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("scans", metavar="SCANS", help="folder of places, each a folder of two or more scans")
    p.add_argument("--out", required=True, metavar="ROOT", help="dataset root; scenes go to ROOT/SPLIT/sNNNNN")
    p.add_argument(
        "--split", choices=("train", "val", "test"), default="train", help="layout to write (default: train)"
    )
    p.add_argument("--workers", type=int, default=1, help="places built in parallel (default: 1)")
    p.add_argument(
        "--ray",
        metavar="ADDRESS",
        help="run places as Ray tasks: 'local' or a cluster address "
        "(every node must see SCANS and ROOT at the same paths)",
    )
    p.add_argument("--fps", type=float, default=2.0, help="video scans: frames sampled per second (default: 2)")
    p.add_argument(
        "--device-axes",
        choices=("opencv", "opengl"),
        default="opencv",
        help="camera axes of device_poses.txt (ARKit/ARCore: opengl; default: opencv)",
    )
    p.add_argument("--allow-unscaled", action="store_true", help="no device poses or depth: keep SfM units")
    p.add_argument("--sfm-depth", action="store_true", help="write sparse SfM depth frame_NNNNN.sfm.png")
    p.add_argument(
        "--correspondences",
        action="store_true",
        help="write correspondences.npz: ground-truth matches of training pairs from depth",
    )
    p.add_argument(
        "--overlap-points",
        choices=("auto", "depth", "sfm"),
        default="auto",
        help="points behind overlaps.npz: surface points from the frames' metric depth, or SfM tracks "
        "(default auto: depth when every frame has a depth map)",
    )
    p.add_argument(
        "--min-registered",
        type=float,
        default=0.5,
        metavar="FRAC",
        help="fraction of each scan's images SfM must register (default: 0.5)",
    )
    p.add_argument(
        "--matcher",
        default="colmap",
        metavar="NAME",
        help="features and matches: colmap (pycolmap SIFT, default) or a mapfree.matching name "
        "(sift, xfeat, aliked-lightglue, ...) written into COLMAP's database",
    )
    p.add_argument("--max-features", type=int, default=4096, help="SIFT features per image (default: 4096)")
    p.add_argument("--private-gt", metavar="DIR", help="test split: write true poses to DIR/test/sNNNNN/")
    p.add_argument(
        "--first-scene", type=int, default=0, help="number of the first scene when places are not named sNNNNN"
    )
    p.add_argument("--force", action="store_true", help="rebuild places that are already built")
    p.add_argument(
        "--keep-work", action="store_true", help="keep the COLMAP database and model under ROOT/SPLIT/.build"
    )
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from ..matching import names as matcher_names
    from ..scenebuild import BuildOptions, SfmOptions
    from ..scenebuild.run import build_all
    from . import fail, output_folder_problem

    if args.matcher != "colmap" and args.matcher.strip().lower().replace("_", "-") not in matcher_names():
        return fail("build", f"unknown --matcher {args.matcher!r}; colmap or one of {', '.join(matcher_names())}")
    checks = [
        (args.workers < 1, f"--workers must be >= 1, got {args.workers}"),
        (args.fps <= 0, f"--fps must be > 0, got {args.fps}"),
        (not 0 < args.min_registered <= 1, f"--min-registered must be in (0, 1], got {args.min_registered}"),
        (args.max_features < 64, f"--max-features must be >= 64, got {args.max_features}"),
    ]
    problem = next((msg for bad, msg in checks if bad), None) or output_folder_problem("--out", args.out)
    if problem:
        return fail("build", problem)
    if args.private_gt and args.split != "test":
        return fail("build", "--private-gt only applies to --split test")
    opts = BuildOptions(
        split=args.split,
        fps=args.fps,
        device_axes=args.device_axes,
        min_registered=args.min_registered,
        allow_unscaled=args.allow_unscaled,
        sfm_depth=args.sfm_depth,
        correspondences=args.correspondences,
        keep_work=args.keep_work,
        overlap_points=args.overlap_points,
        sfm=replace(SfmOptions(), max_features=args.max_features, matcher=args.matcher),
    )
    t0 = time.perf_counter()
    try:
        results = build_all(
            args.scans,
            args.out,
            opts,
            args.workers,
            args.ray,
            args.private_gt,
            args.force,
            args.first_scene,
            progress=not args.quiet,
        )
    except FileNotFoundError as e:
        return fail("build", e)
    for r in results:
        line = f"{r.place} -> {args.split}/{r.scene}: {r.status}"
        if r.status == "ok":
            rep = r.report
            line += (
                f" ({rep['registered']}/{rep['images']} images, {rep['reprojection_error_px']:.2f} px, "
                f"scale from {rep['scale']['source']}, residual {100 * (rep['scale']['residual'] or 0):.1f} %, "
                f"{r.seconds:.1f} s)"
            )
        elif r.reason:
            line += f": {r.reason}"
        print(line)
    failed = sum(r.status == "failed" for r in results)
    print(
        f"{len(results) - failed}/{len(results)} place(s) built under {args.out}/{args.split} "
        f"in {time.perf_counter() - t0:.1f} s"
    )
    return 1 if failed else 0
