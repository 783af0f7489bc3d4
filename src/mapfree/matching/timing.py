"""Per-matcher timings (extract one image, match one pair) on a real pair: ``python -m mapfree.matching.timing``."""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import cv2
import numpy as np
import torch

from . import available, create

__all__ = ["time_matcher", "main"]


def time_matcher(name: str, im0: np.ndarray, im1: np.ndarray, repeats: int = 3, **options: object) -> dict:
    """Median extract (per image) and match (per pair) milliseconds after one warm-up.

    Args:
        name: A matcher name.
        im0: (H, W, 3) uint8 RGB.
        im1: (H, W, 3) uint8 RGB.
        repeats: Timed runs.
        **options: The matcher's options.

    Returns:
        ``extract_ms``, ``match_ms`` (wall clock), ``extract_cpu_ms``, ``match_cpu_ms`` (process CPU time, which a
        busy shared machine cannot inflate), mean keypoints and the number of matches.
    """
    m = create(name, **options)
    m.match(m.extract(im0), m.extract(im1))  # warm-up: lazy init, allocator
    ext, mat, ext_cpu, mat_cpu = [], [], [], []
    for _ in range(repeats):
        t0, c0 = time.perf_counter(), time.process_time()
        f0 = m.extract(im0)
        f1 = m.extract(im1)
        t1, c1 = time.perf_counter(), time.process_time()
        res = m.match(f0, f1)
        t2, c2 = time.perf_counter(), time.process_time()
        ext.append((t1 - t0) / 2 * 1e3)
        mat.append((t2 - t1) * 1e3)
        ext_cpu.append((c1 - c0) / 2 * 1e3)
        mat_cpu.append((c2 - c1) * 1e3)
    return {
        "name": name,
        "extract_ms": statistics.median(ext),
        "match_ms": statistics.median(mat),
        "extract_cpu_ms": statistics.median(ext_cpu),
        "match_cpu_ms": statistics.median(mat_cpu),
        "kpts": (len(f0) + len(f1)) / 2,
        "matches": len(res),
    }


def main(argv: list[str] | None = None) -> int:
    """``python -m mapfree.matching.timing``: time every offline matcher on one pair of a Map-free scene.

    Args:
        argv: Command-line arguments (default: ``sys.argv``).

    Returns:
        The exit status.
    """
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--data", default="/work/shared/data/realmini-dev", help="a Map-free root with val/s00000")
    ap.add_argument("--size", default="", help="resize both images to WxH first, e.g. 540x720 (the Map-free size)")
    ap.add_argument("--names", nargs="*", default=None, help="matchers (default: every offline one)")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--device", default=None)
    a = ap.parse_args(argv)
    torch.set_num_threads(a.threads)
    from ..data import Dataset

    scene = Dataset(Path(a.data)).scene("val", "s00000")
    im0, im1 = scene.reference.image(), scene.queries[10].image()
    if a.size:
        w, h = (int(v) for v in a.size.lower().split("x"))
        im0, im1 = (cv2.resize(im, (w, h), interpolation=cv2.INTER_LINEAR) for im in (im0, im1))
    dev = a.device or ("cuda" if torch.cuda.is_available() else "cpu")
    print(f"{im0.shape[1]}x{im0.shape[0]} images, device {dev}, {a.threads} thread(s)")
    print(
        f"{'matcher':20s} {'extract':>8s} {'match':>8s} {'pair':>8s} {'pair cpu':>8s} {'kpts':>6s} {'matches':>7s}  (ms)"
    )
    for name in a.names or available():
        r = time_matcher(name, im0, im1, a.repeats, device=dev)
        pair = 2 * r["extract_ms"] + r["match_ms"]
        cpu = 2 * r["extract_cpu_ms"] + r["match_cpu_ms"]
        print(
            f"{name:20s} {r['extract_ms']:8.0f} {r['match_ms']:8.0f} {pair:8.0f} {cpu:8.0f} "
            f"{r['kpts']:6.0f} {r['matches']:7d}"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
