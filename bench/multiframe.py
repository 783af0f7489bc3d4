"""Multi-frame vs single-frame on the multi-frame track's scored queries, for several methods.

For each method this runs ``mapfree run --track multi`` (resumable: a second call only re-fuses) and scores,
on exactly the queries the multi-frame leaderboard scores, (a) each query's own single-frame estimate and
(b) the fused burst. Prints a markdown table.

    python bench/multiframe.py /work/shared/data/realmini-dev out/ sift_pnp_sensor xfeat_pnp_sensor
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

KEYS = [
    "Precision @ VCRE < 90px",
    "AUC @ VCRE < 90px",
    "Precision @ Pose Error < (25.0cm, 5deg)",
    "AUC @ Pose Error < (25.0cm, 5deg)",
    "Average Median Translation Error",
    "Average Median Rotation Error",
    "Average Median Reprojection Error",
    "Estimates for % of frames",
]
SHORT = ["VCRE prec", "VCRE AUC", "pose prec", "pose AUC", "med t (m)", "med R (°)", "med VCRE (px)", "estimated"]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("root", type=Path)
    ap.add_argument("out", type=Path)
    ap.add_argument("methods", nargs="+")
    ap.add_argument("--split", default="val")
    ap.add_argument("--workers", type=int, default=1)
    args = ap.parse_args()

    from mapfree.benchmark import evaluate, load_truth
    from mapfree.relocalize.multiframe import frames_path, run_multi

    truth = load_truth(args.root, args.split, track="multi")
    n = sum(len(t.names) for t in truth.values())
    print(f"| method ({n} scored queries) | track | " + " | ".join(SHORT) + " |")
    print("|---|---|" + "---|" * len(SHORT))
    for method in args.methods:
        out = args.out / f"{method.replace('/', '_')}.zip"
        t0 = time.perf_counter()
        res = run_multi(args.root, args.split, method, out, workers=args.workers, resume=True, progress=False)
        seconds = time.perf_counter() - t0
        for label, sub in (("single", frames_path(out)), ("**multi**", res.submission)):
            m = evaluate(sub, truth=truth, split=args.split).metrics
            cells = [f"{m[k]:.3f}" if k != "Average Median Reprojection Error" else f"{m[k]:.1f}" for k in KEYS]
            print(f"| {method} | {label} | " + " | ".join(cells) + " |")
        print(f"<!-- {method}: {res.frames.computed} frames computed, {res.frames.skipped} reused, {seconds:.1f} s -->")


if __name__ == "__main__":
    main()
