"""Pipeline speed: per preset, pairs per second and the time split (match / depth / solve).

Also runs the straightforward SPEC §4 implementation (``reference_spec4.py``: both images' features per pair,
depth read per pair, O(n²) scale vote) on the same pairs in the same process and compares it with our
``sift_emat_sensor`` preset: speed ratio (target >= 2x) and pose agreement.

    python bench/bench_pipeline.py [ROOT] [--presets sift_emat_sensor,xfeat_emat_sensor] [--all-frames]

Timings are wall-clock on this machine with ``--threads`` threads (default 1) for OpenCV and torch.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

DEFAULT_ROOT = next((p for p in (Path(__file__).resolve().parents[2] / "shared/data/realmini-dev",
                                 Path("/work/shared/data/realmini-dev")) if p.is_dir()), None)
DEFAULT_PRESETS = ["sift_emat_sensor", "sift_pnp_sensor", "sift_procrustes_sensor", "xfeat_emat_sensor",
                   "xfeat-star_emat_sensor", "xfeat-lighterglue_emat_sensor", "aliked-lightglue_emat_sensor",
                   "disk-lightglue_emat_sensor"]


def scene_pairs(root, split: str, all_frames: bool, depth_suffix: str = "sensor") -> list:
    """[(scene, [query frames])] for the scenes whose reference has depth (metric methods need it)."""
    from mapfree.data import Dataset

    out = []
    for s in Dataset(root).scenes(split):
        if not s.reference.has_depth(depth_suffix):
            continue
        out.append((s, s.queries if all_frames else s.scored_queries()))
    return out


def bench_preset(name: str, pairs: list, repeat_warmup: bool = True, prefetch: int = 0) -> dict:
    """Run a preset over all pairs; reference preparation counted once per scene, as a real run does.
    ``prefetch`` > 0: the next query is read and extracted in a background thread (``localize_many``)."""
    from mapfree.relocalize import Relocalizer

    loc = Relocalizer.from_method(name)
    if repeat_warmup:  # first call loads weights / allocates; not part of the steady state
        s, qs = pairs[0]
        loc.set_reference(s.reference)
        loc.localize(qs[0])
    stages = {"match": 0.0, "depth": 0.0, "solve": 0.0}
    prep, poses, n = 0.0, [], 0
    t0 = time.perf_counter()
    for s, qs in pairs:
        anchor = loc.set_reference(s.reference)
        prep += sum(anchor.timings.values())
        for est in loc.localize_many(qs, prefetch=prefetch):
            for k in stages:
                stages[k] += est.timings.get(k, 0.0)
            poses.append(est.pose)
            n += 1
    wall = time.perf_counter() - t0
    return {"preset": name + (" (prefetch)" if prefetch else ""), "pairs": n, "seconds": wall, "pairs_per_s": n / wall, "poses": poses,
            "ms": {k: 1000 * v / n for k, v in stages.items()}, "ref_prep_ms_per_scene": 1000 * prep / len(pairs)}


def bench_reference(pairs: list, depth_suffix: str = "sensor") -> dict:
    import reference_spec4 as ref

    poses, n = [], 0
    t0 = time.perf_counter()
    for s, qs in pairs:
        r = s.reference
        for q in qs:
            img0, img1 = r.image(), q.image()
            d0 = r.depth(depth_suffix) if r.has_depth(depth_suffix) else None
            d1 = q.depth(depth_suffix) if q.has_depth(depth_suffix) else None
            res = ref.relocalize_pair(img0, img1, r.intrinsics.K, q.intrinsics.K, d0, d1)
            from mapfree.geometry import Pose

            poses.append(None if isinstance(res, str) else Pose(res[0], res[1]))
            n += 1
    wall = time.perf_counter() - t0
    return {"preset": "straightforward SPEC §4", "pairs": n, "seconds": wall, "pairs_per_s": n / wall, "poses": poses}


def pose_agreement(a: list, b: list) -> dict:
    from mapfree.geometry import rotation_angle_deg

    both = [(p, q) for p, q in zip(a, b) if p is not None and q is not None]
    dr = [float(rotation_angle_deg(p.R, q.R)) for p, q in both]
    dt = [float(np.linalg.norm(p.t - q.t)) for p, q in both]
    return {"both_estimated": len(both), "only_one": sum((p is None) != (q is None) for p, q in zip(a, b)),
            "identical": sum(r < 1e-6 and t < 1e-6 for r, t in zip(dr, dt)),
            "max_rot_diff_deg": max(dr, default=0.0), "max_trans_diff_m": max(dt, default=0.0),
            "median_trans_diff_m": float(np.median(dt)) if dt else 0.0}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("root", nargs="?", default=DEFAULT_ROOT)
    ap.add_argument("--split", default="val")
    ap.add_argument("--presets", default=",".join(DEFAULT_PRESETS))
    ap.add_argument("--all-frames", action="store_true", help="every query (default: the scored ones)")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--max-pairs", type=int, help="at most this many query pairs per scene (slow CPUs)")
    ap.add_argument("--json", type=Path, help="also write the results here")
    ap.add_argument("--no-prefetch", dest="prefetch", action="store_false",
                    help="skip the pipelined run (next query extracted in a background thread)")
    args = ap.parse_args(argv)
    for var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
        os.environ[var] = str(args.threads)
    import cv2
    import torch

    cv2.setNumThreads(args.threads)
    torch.set_num_threads(args.threads)
    device = "cuda" if torch.cuda.is_available() else "cpu"
    pairs = scene_pairs(args.root, args.split, args.all_frames)
    if args.max_pairs:
        pairs = [(s, qs[: args.max_pairs]) for s, qs in pairs]
    print(f"{sum(len(q) for _, q in pairs)} pairs in {len(pairs)} scenes, device {device}, {args.threads} thread(s)\n")

    straight = bench_reference(pairs)
    rows = []
    for name in args.presets.split(","):
        try:
            rows.append(bench_preset(name, pairs))
        except Exception as e:  # a preset whose weights are missing is reported, not fatal
            print(f"{name}: skipped ({type(e).__name__}: {e})")
    ours = next((r for r in rows if r["preset"] == "sift_emat_sensor"), None)
    if ours is not None and args.prefetch:
        rows.insert(rows.index(ours) + 1, bench_preset("sift_emat_sensor", pairs, prefetch=1))

    print("| preset | device | pairs/s | match ms | depth ms | solve ms | ref prep ms/scene |")
    print("|---|---|---|---|---|---|---|")
    print(f"| {straight['preset']} | cpu | {straight['pairs_per_s']:.2f} | – | – | – | – |")
    for r in rows:
        m = r["ms"]
        print(f"| {r['preset']} | {device} | {r['pairs_per_s']:.2f} | {m['match']:.0f} | {m['depth']:.1f} | "
              f"{m['solve']:.1f} | {r['ref_prep_ms_per_scene']:.0f} |")
    result = {"device": device, "threads": args.threads, "rows": [
        {k: v for k, v in r.items() if k != "poses"} for r in [straight, *rows]]}
    print()
    for r in [r for r in rows if r["preset"].startswith("sift_emat_sensor")]:
        speedup = r["pairs_per_s"] / straight["pairs_per_s"]
        agree = pose_agreement(r["poses"], straight["poses"])
        ok = speedup >= 2.0
        print(f"{r['preset']} vs straightforward SPEC §4: {speedup:.2f}x faster "
              f"({'PASS' if ok else 'FAIL'}: target >= 2x); poses: {json.dumps(agree)}")
        result.setdefault("speedup", {})[r["preset"]] = speedup
        result.setdefault("agreement", {})[r["preset"]] = agree
    if args.json:
        args.json.write_text(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
