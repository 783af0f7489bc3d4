"""Benchmark the scorer: vectorised ``evaluate`` against the per-frame loop (``benchmark.naive``).

Generates a test-sized split (130 scenes, 15,000 evaluated frames: 75,000 ground-truth query lines per
file type) and a submission with realistic errors, missing frames and tied confidences in a temporary
folder, times the whole evaluation (reading the ground truth and the ZIP included) both ways in the same
run, checks that every number agrees to 1e-6 and prints a table.

    python bench/bench_scoring.py [--scenes 130] [--frames 15000] [--all-queries] [--repeat 3]

Targets: whole evaluation < 1 s on a 2-core machine and >= 20x faster than the loop. Both wall-clock and
this process's CPU time are printed: on a shared machine wall time also counts everyone else's jobs.
``--all-queries`` submits every query (5x the lines) instead of only the scored ones.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from mapfree.benchmark import evaluate, load_truth, write_submission
from mapfree.benchmark.naive import evaluate_naive
from mapfree.geometry import Pose, quat_to_rotmat


def _random_quats(rng: np.random.Generator, n: int, max_deg) -> np.ndarray:
    axis = rng.normal(size=(n, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    half = np.radians(rng.uniform(0, max_deg, n)) / 2
    return np.c_[np.cos(half), axis * np.sin(half)[:, None]]


def _qmul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    w1, x1, y1, z1 = a.T
    w2, x2, y2, z2 = b.T
    return np.stack([
        w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2, w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
        w1 * y2 + y1 * w2 + z1 * x2 - x1 * z2, w1 * z2 + z1 * w2 + x1 * y2 - y1 * x2,
    ], axis=1)


def make_split(root: Path, n_scenes: int, n_evaluated: int, seed: int = 0, all_queries: bool = False) -> dict:
    """Write ``root/val/sNNNNN/{poses,intrinsics}.txt`` and return estimates for a submission."""
    rng = np.random.default_rng(seed)
    per_scene = np.full(n_scenes, n_evaluated // n_scenes)
    per_scene[: n_evaluated - per_scene.sum()] += 1
    estimates = {}
    for s, m in enumerate(per_scene.tolist()):
        scene = f"s{s:05d}"
        d = root / "val" / scene
        d.mkdir(parents=True)
        n = 5 * m - 1  # queries; with the reference's shared key 0 the dict has 5m entries -> m evaluated
        names = ["seq0/frame_00000.jpg"] + [f"seq1/frame_{i:05d}.jpg" for i in range(n)]
        q = np.r_[[[1.0, 0, 0, 0]], _random_quats(rng, n, 40)]
        t = np.r_[[[0.0, 0, 0]], rng.normal(scale=1.5, size=(n, 3))]
        (d / "poses.txt").write_text(
            "".join(f"{nm} {a:.9f} {b:.9f} {c:.9f} {e:.9f} {x:.6f} {y:.6f} {z:.6f}\n" for nm, (a, b, c, e), (x, y, z) in zip(names, q, t))
        )
        fx = 590 + rng.normal(scale=3, size=n + 1)
        (d / "intrinsics.txt").write_text(
            "".join(f"{nm} {f:.6f} {f:.6f} 269.5 359.5 540 720\n" for nm, f in zip(names, fx))
        )
        # Estimates: errors spanning accepted poses to 180-degree flips, 3 % of frames missing.
        idx = np.arange(1, n + 1) if all_queries else 1 + np.arange(0, n, 5)
        k = len(idx)
        scale = rng.choice([0.02, 0.1, 0.5, 3.0], size=k, p=[0.3, 0.3, 0.3, 0.1])
        dq = _random_quats(rng, k, np.minimum(180.0, 40 * scale))
        q_est = _qmul(dq, q[idx])
        t_est = t[idx] + rng.normal(scale=scale[:, None], size=(k, 3))
        conf = rng.integers(0, 300, size=k).astype(float)  # many ties
        keep = rng.random(k) > 0.03
        R = quat_to_rotmat(q_est)
        estimates[scene] = [(names[i], Pose(R[j], t_est[j]), conf[j]) for j, i in enumerate(idx) if keep[j]]
    return estimates


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", type=int, default=130)
    ap.add_argument("--frames", type=int, default=15000, help="evaluated frames in total")
    ap.add_argument("--all-queries", action="store_true", help="submit every query, not only the scored ones")
    ap.add_argument("--repeat", type=int, default=3, help="best of N for the vectorised evaluation")
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        t0 = time.perf_counter()
        estimates = make_split(root, args.scenes, args.frames, all_queries=args.all_queries)
        sub = root / "submission.zip"
        write_submission(sub, estimates)
        gen = time.perf_counter() - t0
        lines = sum(len(v) for v in estimates.values())

        def timed(fn):
            w, c = time.perf_counter(), time.process_time()
            out = fn()
            return out, time.perf_counter() - w, time.process_time() - c

        runs = [timed(lambda: evaluate(sub, root, "val")) for _ in range(args.repeat)]
        report = runs[0][0]
        t_vec, c_vec = min(r[1] for r in runs), min(r[2] for r in runs)
        truth = load_truth(root, "val")
        _, t_warm, c_warm = timed(lambda: evaluate(sub, root, "val", truth=truth))
        (naive_metrics, naive_frames), t_naive, c_naive = timed(lambda: evaluate_naive(sub, root, "val"))

        n_eval = len(report.estimated)
        diffs = [abs(report.metrics[k] - v) for k, v in naive_metrics.items()]
        idx = {(s, f): i for i, (s, f) in enumerate(zip(report.scene, report.frame))}
        frame_diff = 0.0
        for key, errs in naive_frames.items():
            i = idx[key]
            frame_diff = max(frame_diff, *(abs(a - b) for a, b in zip((report.trans_err[i], report.rot_err[i], report.vcre[i]), errs)))
        ok = max(diffs) <= 1e-6 and frame_diff <= 1e-6 and len(naive_frames) == int(report.estimated.sum())

    rows = [
        ("scenes / evaluated frames / submission lines", f"{args.scenes} / {n_eval} / {lines}", ""),
        ("generate data", f"{gen:.2f}", ""),
        ("naive per-frame loop, whole evaluation", f"{t_naive:.3f}", f"{c_naive:.3f}"),
        (f"vectorised, whole evaluation (best of {args.repeat})", f"{t_vec:.3f}", f"{c_vec:.3f}"),
        ("vectorised, ground truth preloaded", f"{t_warm:.3f}", f"{c_warm:.3f}"),
        ("speed-up, whole evaluation", f"{t_naive / t_vec:.1f}x", f"{c_naive / c_vec:.1f}x"),
        ("max |metric difference|", f"{max(diffs):.2e}", ""),
        ("max |per-frame error difference|", f"{frame_diff:.2e}", ""),
        ("identical to 1e-6", "yes" if ok else "NO", ""),
        ("target: < 1 s and >= 20x (CPU time)", "met" if (c_vec < 1 and c_naive / c_vec >= 20) else "not met", ""),
    ]
    width = max(len(r[0]) for r in rows)
    print(f"{'measure':<{width}}  {'wall (s)':>10}  {'CPU (s)':>9}")
    print("-" * (width + 24))
    for k, v, c in rows:
        print(f"{k:<{width}}  {v:>10}  {c:>9}")
    print("(CPU = this process's CPU time: on a shared machine, wall time also counts other people's jobs)")
    print("\nmetrics:", {k: round(v, 4) for k, v in report.metrics.items()})
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
