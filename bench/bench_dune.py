"""DUNE-MASt3R against MASt3R on the CPU: per-pair time and peak memory, files in to matches out.

    python bench/bench_dune.py [ROOT] [--models dune-mast3r-small,dune-mast3r,mast3r] [--pairs 2] [--threads 2]
                               [--weights DIR]

Each network is the published architecture with fill-rule weights in the published file layout (written once
into ``--weights``, default a temporary folder; accuracy needs the real files): DUNE-MASt3R with the ViT-S/14
and the ViT-B/14 paper encoder at 518 (patch 14), MASt3R ViT-L at 512 (patch 16), all with the same ViT-B
decoders. Each runs in a fresh process (its peak resident memory is the process's, loading included) through the
``mapfree`` matcher on the CPU: a warm-up pair of ``val/s00000``, then ``--pairs`` never-seen pairs (the reference
``seq0/frame_00000.jpg`` and a query of ``seq1`` of the next scenes), each timed from reading both files to the
reciprocal matches (both images encoded: nothing cached), in wall time and in the process's CPU time (the
steadier of the two on a shared machine). Prints one table and the speed ratios to MASt3R measured in this run.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from benchpaths import DEFAULT_ROOT  # noqa: E402  (also puts src/ on the path)

LABELS = {
    "dune-mast3r-small": "DUNE-S (ViT-S/14 + ViT-B dec., 518)",
    "dune-mast3r": "DUNE-B (ViT-B/14 + ViT-B dec., 518)",
    "mast3r": "MASt3R (ViT-L/16 + ViT-B dec., 512)",
}


def write_weights(folder: Path, kind: str) -> None:
    """The fill-rule stand-in of ``kind`` under its published name(s), unless already there (float16 files:
    half the disk; the loader computes in float32)."""
    import torch

    if kind == "mast3r":
        from mapfree.mast3r.checkpoint import PUBLISHED
        from mapfree_dev.standins.mast3r import write_published_standin

        if not (folder / f"{PUBLISHED['mast3r'].stem}.pth").is_file():
            write_published_standin(folder, "mast3r", torch.float16)
        return
    from mapfree.mast3r.published import DUNE_DECODERS
    from mapfree_dev.standins.dune import write_published_standin as write_dune

    if not (folder / DUNE_DECODERS[kind].filename).is_file():
        write_dune(folder, kind, torch.float16)


def pairs(root: Path, n: int) -> tuple[tuple[Path, Path], list[tuple[Path, Path]]]:
    """The warm-up pair (val/s00000) and ``n`` pairs of the next scenes, each its scene's reference and a query."""
    scenes = sorted((root / "val").glob("s*"))

    def pair(scene: Path, i: int) -> tuple[Path, Path]:
        queries = sorted((scene / "seq1").glob("frame_*.jpg"))
        return scene / "seq0" / "frame_00000.jpg", queries[(5 * i) % len(queries)]

    timed = [pair(scenes[1 + i % (len(scenes) - 1)], i) for i in range(n)]
    return pair(scenes[0], 0), timed


def child(kind: str, root: Path, n: int) -> dict:
    """In a fresh process: load, warm up, time ``n`` never-seen pairs; peak memory of the whole process."""
    import numpy as np
    import PIL.Image
    import torch
    from PIL.ImageOps import exif_transpose

    from mapfree.matching.mast3r import Mast3rMatcher

    def read(p: Path) -> np.ndarray:
        with PIL.Image.open(p) as im:
            return np.asarray(exif_transpose(im).convert("RGB"))

    t = time.perf_counter()
    matcher = Mast3rMatcher(kind=kind, device="cpu")
    load_s = time.perf_counter() - t
    warm, timed = pairs(root, n)

    def run(a: Path, b: Path) -> int:
        f0, f1 = matcher.extract(read(a)), matcher.extract(read(b))
        return len(matcher.match(f0, f1))

    run(*warm)
    times, cpu, counts = [], [], []
    for a, b in timed:
        t, c = time.perf_counter(), time.process_time()
        counts.append(run(a, b))
        times.append(time.perf_counter() - t)
        cpu.append(time.process_time() - c)
    return {
        "kind": kind,
        "long_side": matcher.engine.long_side,
        "load_s": load_s,
        "pair_s": times,
        "cpu_s": cpu,
        "matches": counts,
        "peak_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
        "threads": torch.get_num_threads(),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("root", nargs="?", type=Path, default=DEFAULT_ROOT, help="realmini-dev (val/s0000N)")
    ap.add_argument("--models", default="dune-mast3r-small,dune-mast3r,mast3r")
    ap.add_argument("--pairs", type=int, default=2, help="timed pairs per model (after one warm-up pair)")
    ap.add_argument("--threads", type=int, default=2, help="torch intra-op threads")
    ap.add_argument("--weights", type=Path, help="folder for the stand-in files (kept); default: a temporary one")
    ap.add_argument("--child", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.root is None:
        ap.error("give the realmini-dev folder")
    if args.child:
        import torch

        torch.set_num_threads(args.threads)
        print(json.dumps(child(args.child, args.root, args.pairs)))
        return
    kinds = args.models.split(",")
    with tempfile.TemporaryDirectory() as tmp:
        folder = args.weights or Path(tmp)
        folder.mkdir(parents=True, exist_ok=True)
        for kind in kinds:
            write_weights(folder, kind)
        env = {
            **os.environ,
            "MAPFREE_WEIGHTS_DIR": str(folder),
            "MAPFREE_OFFLINE": "1",
            **{v: str(args.threads) for v in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS")},
        }
        rows = []
        for kind in kinds:
            cmd = [sys.executable, __file__, str(args.root), "--child", kind, "--pairs", str(args.pairs)]
            r = subprocess.run([*cmd, "--threads", str(args.threads)], capture_output=True, text=True, env=env)
            if r.returncode:
                sys.exit(f"{kind}: {r.stderr.strip().splitlines()[-1] if r.stderr.strip() else r.returncode}")
            rows.append(json.loads(r.stdout.strip().splitlines()[-1]))
    base = next((row for row in rows if row["kind"] == "mast3r"), None)
    print(f"{args.pairs} never-seen pairs per model after 1 warm-up pair, CPU, {args.threads} torch threads")
    print(
        "| model | input | wall s/pair (median; each) | CPU s/pair (median) | matches | peak MiB | load s | "
        "vs MASt3R: wall | vs MASt3R: CPU |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    for row in rows:
        med, cpu = statistics.median(row["pair_s"]), statistics.median(row["cpu_s"])
        wall_x = f"{statistics.median(base['pair_s']) / med:.2f}×" if base else "-"
        cpu_x = f"{statistics.median(base['cpu_s']) / cpu:.2f}×" if base else "-"
        print(
            f"| {LABELS[row['kind']]} | {row['long_side']} | {med:.1f}; {', '.join(f'{t:.1f}' for t in row['pair_s'])} | "
            f"{cpu:.1f} | {', '.join(map(str, row['matches']))} | {row['peak_mib']:.0f} | {row['load_s']:.1f} | "
            f"{wall_x} | {cpu_x} |"
        )


if __name__ == "__main__":
    main()
