"""Synthetic split generation speed: a 10-scene val split, 40 queries each, 540x720 (target < 60 s on 2 cores).

Baseline in the same run: the bare cost of writing the same files (JPEG + two 16-bit PNG depth maps per frame)
from constant arrays, i.e. the floor any generator pays for the Map-free layout.

    .venv/bin/python bench/bench_synth.py [--scenes 10] [--queries 40] [--workers 2]
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

import numpy as np
from rich.console import Console
from rich.table import Table

from mapfree.data import write_depth
from mapfree.data.synth import SynthOptions, generate
from mapfree.data.synth.textures import load_atlas


def _cpu() -> float:
    """CPU seconds of this process and its finished children (worker processes)."""
    t = os.times()
    return t.user + t.system + t.children_user + t.children_system


def io_floor(root: Path, frames: int, width: int, height: int) -> tuple[float, float]:
    """(wall, CPU) seconds to write ``frames`` JPEG + 2 depth PNGs of the same size (realistic-looking content)."""
    import cv2

    rng = np.random.default_rng(0)
    img = cv2.GaussianBlur(rng.integers(0, 255, (height, width, 3), dtype=np.uint8), (0, 0), 2)
    yy = np.linspace(2, 12, height, dtype=np.float32)[:, None]
    depth = np.repeat(yy, width, axis=1) + rng.normal(0, 0.01, (height, width)).astype(np.float32)
    t0, c0 = time.perf_counter(), _cpu()
    for i in range(frames):
        cv2.imwrite(str(root / f"f{i}.jpg"), img, [cv2.IMWRITE_JPEG_QUALITY, 92])
        write_depth(root / f"f{i}.sensor.png", depth)
        write_depth(root / f"f{i}.mono.png", depth * 1.1)
    return time.perf_counter() - t0, _cpu() - c0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", type=int, default=10)
    ap.add_argument("--queries", type=int, default=40)
    ap.add_argument("--workers", type=int, default=2, help="scene processes (default 2: the machine's cores)")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()

    t0 = time.perf_counter()
    load_atlas()
    t_atlas = time.perf_counter() - t0
    frames = args.scenes * (args.queries + 1)
    with tempfile.TemporaryDirectory() as tmp:
        t0, c0 = time.perf_counter(), _cpu()
        generate(
            Path(tmp) / "synth",
            "val",
            args.scenes,
            args.queries,
            args.seed,
            options=SynthOptions(workers=args.workers),
            progress=False,
        )
        t_gen, c_gen = time.perf_counter() - t0, _cpu() - c0
        io_dir = Path(tmp) / "io"
        io_dir.mkdir()
        t_io, c_io = io_floor(io_dir, frames, 540, 720)

    table = Table(
        title=f"synthetic val split: {args.scenes} scenes x {args.queries} queries, 540x720, {args.workers} worker(s)"
    )
    for col in ("what", "wall s", "wall ms / frame", "CPU s", "CPU ms / frame", "CPU ratio"):
        table.add_column(col, justify="right" if col != "what" else "left")
    table.add_row("texture atlas (once per process)", f"{t_atlas:.2f}", "", "", "", "")
    table.add_row(
        "generate (render + write)",
        f"{t_gen:.1f}",
        f"{1e3 * t_gen / frames:.0f}",
        f"{c_gen:.1f}",
        f"{1e3 * c_gen / frames:.0f}",
        f"{c_gen / c_io:.1f}x",
    )
    table.add_row(
        "baseline: only writing the files",
        f"{t_io:.1f}",
        f"{1e3 * t_io / frames:.0f}",
        f"{c_io:.1f}",
        f"{1e3 * c_io / frames:.0f}",
        "1.0x",
    )
    Console().print(table)
    verdict = "OK" if t_gen < 60 else "SLOWER THAN TARGET"
    print(
        f"target: < 60 s wall for the split -> {t_gen:.1f} s ({verdict}); {frames} frames; "
        f"load average now {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores (CPU time is the load-free figure)"
    )


if __name__ == "__main__":
    main()
