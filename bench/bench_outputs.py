"""What a user's outputs cost, each against its baseline in the same run: the size of `run --viz` figures and of the
`evaluate --html` report on a real split (JPEG as written now vs the same figures as full-size PNG, as they were
written before), and the wall time of a SIFT `mapfree relocalize` process against the same process made to import
torch and SciPy's spatial module first (what a SIFT command used to load for nothing).

    python bench/bench_outputs.py REALMINI [--runs 5]

Prints one table; the figures go to docs/reports.md and docs/benchmarks.md.
"""

from __future__ import annotations

import argparse
import base64
import os
import re
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2

REPO = Path(__file__).resolve().parents[1]


def _mapfree(*args: str, env: dict | None = None, prelude: str = "") -> float:
    """Wall time (s) of one ``mapfree`` process; ``prelude``: Python run before the command in the same process."""
    code = f"{prelude}\nimport sys\nfrom mapfree.cli import main\nsys.exit(main(sys.argv[1:]))"
    t0 = time.perf_counter()
    p = subprocess.run(
        [sys.executable, "-c", code, *args],
        capture_output=True,
        text=True,
        env={**os.environ, "PYTHONPATH": str(REPO / "src"), **(env or {})},
    )
    dt = time.perf_counter() - t0
    if p.returncode not in (0, 3):
        raise SystemExit(f"mapfree {' '.join(args)} failed: {p.stderr.strip()}")
    return dt


def sizes(root: Path, work: Path) -> list[tuple[str, str, str]]:
    sub, viz, page = work / "sub.zip", work / "viz", work / "report.html"
    _mapfree("run", str(root), "--method", "sift_pnp_sensor", "-o", str(sub), "--viz", str(viz), "--no-progress")
    _mapfree("evaluate", str(sub), "--dataset", str(root), "--html", str(page), "--viz", str(viz))
    figs = sorted(viz.rglob("*.jpg"))
    jpg = sum(f.stat().st_size for f in figs)
    png = sum(len(cv2.imencode(".png", cv2.imread(str(f)))[1]) for f in figs)  # the same pixels as full-size PNG
    html = page.stat().st_size
    embedded = re.findall(r'src="data:image/jpeg;base64,([^"]+)"', page.read_text())
    as_png = (
        html
        - sum(len(e) for e in embedded)
        + sum(
            len(base64.b64encode(cv2.imencode(".png", cv2.imread(str(f)))[1].tobytes())) for f in figs[: len(embedded)]
        )
    )
    n = len(figs)
    return [
        ("run --viz, per frame", f"{jpg / n / 1e3:.0f} KB (JPEG)", f"{png / n / 1e3:.0f} KB (PNG)"),
        (f"run --viz, {n} frames", f"{jpg / 1e6:.1f} MB", f"{png / 1e6:.1f} MB"),
        ("evaluate --html --viz", f"{html / 1e6:.2f} MB", f"{as_png / 1e6:.2f} MB (≈, frames as PNG)"),
    ]


def start(root: Path, runs: int) -> list[tuple[str, str, str]]:
    scene = root / "val" / "s00000"
    args = (
        "relocalize",
        str(scene / "seq0" / "frame_00000.jpg"),
        str(scene / "seq1" / "frame_00005.jpg"),
        "--method",
        "sift_pnp_sensor",
    )
    now, before = [], []
    for _ in range(runs):  # interleaved, so that load changes hit both alike
        now.append(_mapfree(*args))
        before.append(_mapfree(*args, prelude="import torch, scipy.spatial"))
    a, b = statistics.median(now), statistics.median(before)
    return [
        ("relocalize sift_pnp_sensor, wall (median)", f"{a:.2f} s", f"{b:.2f} s (+torch, scipy.spatial)"),
        ("ratio", f"{b / a:.1f}x faster", ""),
    ]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("root", type=Path, help="a Map-free-layout split with sensor depth (realmini-dev)")
    ap.add_argument("--runs", type=int, default=5)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        rows = sizes(args.root, Path(tmp)) + start(args.root, args.runs)
    load = os.getloadavg()[0]
    print(f"outputs on {args.root.name} (CPU, {os.cpu_count()} cores, load average {load:.1f})")
    w = max(len(r[0]) for r in rows)
    print(f"{'':<{w}}  {'now':<20}  baseline")
    for r in rows:
        print(f"{r[0]:<{w}}  {r[1]:<20}  {r[2]}")


if __name__ == "__main__":
    main()
