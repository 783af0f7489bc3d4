"""mapfree build on synthetic raw scans: accuracy against the truth and seconds per place vs images per scan.

For each scan length, writes PLACES synthetic places (two scans each, `mapfree synth --split scans`), builds
them (pycolmap SfM, metric scale from the drifting device track, layout, overlaps) one place at a time on one
thread, and compares with the true poses and overlaps: median rotation error, median camera-centre error
relative to the scan's extent (after a rigid alignment: the scale is the build's own), overlap correlation
with synth's own (surface points spread evenly over the frames, exact visibility).

    .venv/bin/python bench/bench_build.py [--places 4] [--frames 8,12,16] [--size 270x360] [--overlap-points sfm]
                                          [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
from rich.console import Console
from rich.table import Table

from mapfree.data.synth import SynthOptions
from mapfree.data.synth.scans import ScanOptions, generate_scans
from mapfree.scenebuild import BuildOptions
from mapfree.scenebuild.accuracy import compare_to_truth
from mapfree.scenebuild.place import build_place


def _cpu() -> float:
    t = os.times()
    return t.user + t.system + t.children_user + t.children_system


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--places", type=int, default=4)
    ap.add_argument("--frames", default="8,12,16", help="images per scan, comma-separated")
    ap.add_argument("--size", default="270x360", help="image size WxH")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument(
        "--overlap-points",
        choices=("auto", "depth", "sfm"),
        default="auto",
        help="points behind the built overlaps (sfm: the SfM tracks, as without depth maps)",
    )
    ap.add_argument("--json", type=Path, help="write the rows here")
    args = ap.parse_args()
    w, h = (int(v) for v in args.size.split("x"))
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for n in (int(v) for v in args.frames.split(",")):
            root = Path(tmp) / f"f{n}"
            opts = ScanOptions(frames=n, synth=replace(SynthOptions(width=w, height=h), write_mono=False))
            generate_scans(root, args.places, args.seed, opts, private_gt_dir=root / "gt", progress=False)
            for place in sorted((root / "scans").iterdir()):
                t0, c0 = time.perf_counter(), _cpu()
                build = BuildOptions(report_plot=False, overlap_points=args.overlap_points)
                r = build_place(place, root / "out/train" / place.name, build)
                row = {
                    "frames_per_scan": n,
                    "place": place.name,
                    "status": r.status,
                    "reason": r.reason,
                    "seconds": time.perf_counter() - t0,
                    "cpu_seconds": _cpu() - c0,
                    "sfm_seconds": r.report.get("sfm_seconds"),
                }
                if r.status == "ok":
                    row.update(compare_to_truth(root / "out/train" / place.name, root / "gt/scans" / place.name))
                    row["registered"] = f"{r.report['registered']}/{r.report['images']}"
                    row["scale_residual"] = r.report["scale"]["residual"]
                rows.append(row)
                print(json.dumps({k: v for k, v in row.items() if k != "scan_extent_m"}, default=float), flush=True)
    table = Table(
        title=f"mapfree build, {args.places} synthetic places per row, {w}x{h}, 1 thread per place, "
        f"overlaps from {args.overlap_points} points"
    )
    for c in (
        "images/scan",
        "built",
        "s/place (median)",
        "rot. err. median (deg)",
        "centre err. (% extent)",
        "overlap corr.",
        "scale residual (%)",
    ):
        table.add_column(c, justify="right")
    for n in sorted({r["frames_per_scan"] for r in rows}):
        sel = [r for r in rows if r["frames_per_scan"] == n]
        ok = [r for r in sel if r["status"] == "ok"]

        def med(k, s=1.0, ok=ok):
            return f"{s * np.median([r[k] for r in ok]):.2f}" if ok else "-"

        table.add_row(
            str(n),
            f"{len(ok)}/{len(sel)}",
            f"{np.median([r['seconds'] for r in sel]):.1f}",
            med("rotation_median_deg"),
            med("centre_median_rel", 100),
            med("overlap_correlation"),
            med("scale_residual", 100),
        )
    Console().print(table)
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1, default=float))


if __name__ == "__main__":
    main()
