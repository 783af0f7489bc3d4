"""``mapfree scannet PAIRS --method NAME --out DIR``: relative pose on ScanNet-style pair lists (paper suppl.)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

DESCRIPTION = """\
Relative pose of image pairs listed in the SuperGlue/LoFTR text format (ScanNet-1500): per line two image
paths, their EXIF rotations, two 3x3 intrinsics and the 4x4 pose of image 1 relative to image 0.

Each pair is relocalized with --method (depth: ScanNet's own maps with a '*_depth' method, e.g.
sift_emat_depth; or '_none' for up-to-scale poses) and scored: rotation and translation-direction errors,
AUC of the pose error at 5/10/20 degrees, median metric translation error. Writes report.json (per pair),
table.txt and the cumulative pose-error plot under --out.
"""

EPILOG = """\
examples:
  mapfree scannet scannet_test_pairs_with_gt.txt --root scannet_test_1500 --method sift_emat_depth --out sn-out
  mapfree scannet pairs.txt --method xfeat_emat_none --limit 100
"""


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "scannet",
        help="relative pose on a ScanNet pair list (AUC @ 5/10/20°)",
        description=DESCRIPTION,
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("pairs", type=Path, help="pair list (SuperGlue/LoFTR format)")
    p.add_argument("--root", type=Path, help="folder the image paths are relative to (default: the list's folder)")
    p.add_argument("--method", default="sift_emat_depth", help="method name or YAML (default: sift_emat_depth)")
    p.add_argument("--limit", type=int, default=0, help="only the first N pairs (default: all)")
    p.add_argument("--out", type=Path, default=Path("scannet-out"), help="output folder (default: scannet-out)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import numpy as np

    from ..benchmark.relpose import cumulative_error_figure, format_relpose, relpose_report
    from ..data import FormatError
    from ..data.scannet import read_pairs
    from ..relocalize.references import relocalize_pairs

    try:
        pairs = read_pairs(args.pairs, args.root)
        if args.limit > 0:
            pairs = pairs[: args.limit]
        ests = relocalize_pairs(args.method, [(p.frame0, p.frame1) for p in pairs], progress=not args.no_progress)
    except (FileNotFoundError, FormatError, KeyError, ValueError) as e:
        from . import fail

        return fail("scannet", e)
    nan_R, nan_t = np.full((3, 3), np.nan), np.full(3, np.nan)
    report = relpose_report(
        [p.name for p in pairs],
        [p.T_0to1.R for p in pairs],
        [p.T_0to1.t for p in pairs],
        [e.pose.R if e.pose is not None else nan_R for e in ests],
        [e.pose.t if e.pose is not None else nan_t for e in ests],
        [e.ok and not e.extras.get("scale_free") and e.extras.get("metric", True) for e in ests],
    )
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "report.json").write_text(report.to_json(pairs=True))
    table = format_relpose(report, f"Relative pose — {args.pairs.name}, {args.method}")
    (args.out / "table.txt").write_text(table)
    cumulative_error_figure(report).savefig(args.out / "pose_error_cdf.png")
    print(table)
    if not any(e.ok for e in ests):
        from . import EXIT_NOTHING

        reasons = sorted({e.reason for e in ests if e.reason})
        print(
            f"mapfree scannet: no pair got an estimate ({'; '.join(reasons[:3]) or 'no reason given'})", file=sys.stderr
        )
        return EXIT_NOTHING
    return 0
