"""An independent, straightforward implementation of paper-protocol's SIFT + Ess.Mat + D.Scale baseline.

Written from the paper's protocol text with plain OpenCV calls and nothing of mapfree's matching/depth/solvers, to check
our ``sift_emat_sensor`` preset against: both images' features are extracted for every pair, depth maps
are read for every pair, and the scale vote is the O(n²) max-consensus loop.

    python bench/reference_spec4.py /work/shared/data/realmini-dev --split val [--all-frames]
"""

from __future__ import annotations

import argparse
import json
import sys
import time

import cv2
import numpy as np

from mapfree.data import Dataset
from mapfree.geometry import Pose


def sift_features(gray: np.ndarray, sift: cv2.SIFT) -> tuple[np.ndarray, np.ndarray]:
    kps, desc = sift.detectAndCompute(gray, None)
    if desc is None:
        return np.zeros((0, 2)), np.zeros((0, 128), np.float32)
    kps, desc = kps[:2048], desc[:2048]
    desc = desc / (desc.sum(axis=1, keepdims=True) + 1e-7)  # RootSIFT
    return np.array([k.pt for k in kps], dtype=np.float64), np.sqrt(desc).astype(np.float32)


def ratio_matches(d0: np.ndarray, d1: np.ndarray, ratio: float = 0.8) -> tuple[np.ndarray, np.ndarray]:
    if len(d0) < 2 or len(d1) < 2:
        return np.zeros(0, int), np.zeros(0, int)
    i0, i1 = [], []
    for m in cv2.BFMatcher(cv2.NORM_L2).knnMatch(d0, d1, k=2):
        if len(m) == 2 and m[0].distance < ratio * m[1].distance:
            i0.append(m[0].queryIdx)
            i1.append(m[0].trainIdx)
    return np.array(i0, int), np.array(i1, int)


def scale_vote_loop(s: np.ndarray, thr: float = 0.1) -> tuple[float, int]:
    """O(n²): the hypothesis with the most others within ``thr`` metres (first one wins ties)."""
    best, best_s = 0, 0.0
    for h in s:
        votes = int(np.sum(np.abs(s - h) < thr))
        if votes > best:
            best, best_s = votes, float(h)
    return best_s, best


def lookup(depth: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Depth at the nearest pixel centre (0 outside the map); the public code truncates instead."""
    u, v = np.rint(uv[:, 0]).astype(int), np.rint(uv[:, 1]).astype(int)
    inside = (u >= 0) & (v >= 0) & (u < depth.shape[1]) & (v < depth.shape[0])
    out = np.zeros(len(uv))
    out[inside] = depth[v[inside], u[inside]]
    return out


def relocalize_pair(img0, img1, K0: np.ndarray, K1: np.ndarray, depth0, depth1, thr_px: float = 3.0):
    """(R, t, confidence) of image 1 relative to image 0 (X1 = R X0 + t), or a reason string."""
    sift = cv2.SIFT_create(nfeatures=2048)
    k0, d0 = sift_features(cv2.cvtColor(img0, cv2.COLOR_RGB2GRAY), sift)
    k1, d1 = sift_features(cv2.cvtColor(img1, cv2.COLOR_RGB2GRAY), sift)
    i0, i1 = ratio_matches(d0, d1)
    if len(i0) < 5:
        return "fewer than 5 matches"
    p0, p1 = k0[i0], k1[i1]
    n0 = (p0 - K0[[0, 1], [2, 2]]) / K0[[0, 1], [0, 1]]
    n1 = (p1 - K1[[0, 1], [2, 2]]) / K1[[0, 1], [0, 1]]
    thr = thr_px / np.mean([K0[0, 0], K0[1, 1], K1[0, 0], K1[1, 1]])
    E, mask = cv2.findEssentialMat(n0, n1, np.eye(3), method=cv2.USAC_MAGSAC, prob=0.9999, threshold=thr)
    if E is None or mask is None:
        return "essential matrix failed"
    best = None
    for Ei in np.split(E, len(E) // 3):  # keep the cheirality-best decomposition
        # distanceThresh 50 (OpenCV's default in this overload): far triangulations do not vote, as in the public code.
        n, R, t, m, _ = cv2.recoverPose(Ei, n0, n1, np.eye(3), distanceThresh=50.0, mask=mask.copy())
        if best is None or n > best[0]:
            best = (n, R, t.ravel(), m.ravel() > 0)
    _, R, t_dir, inl = best
    if depth0 is None or depth1 is None:
        return "no depth"
    q0, q1 = p0[inl], p1[inl]
    z0 = lookup(depth0, q0)
    z1 = lookup(depth1, q1)
    ok = (z0 > 0) & (z1 > 0)
    if ok.sum() == 0:
        return "no valid depth at inliers"
    X0 = np.c_[(q0[ok, 0] - K0[0, 2]) / K0[0, 0], (q0[ok, 1] - K0[1, 2]) / K0[1, 1], np.ones(ok.sum())] * z0[ok, None]
    X1 = np.c_[(q1[ok, 0] - K1[0, 2]) / K1[0, 0], (q1[ok, 1] - K1[1, 2]) / K1[1, 1], np.ones(ok.sum())] * z1[ok, None]
    s = (X1 - X0 @ R.T) @ t_dir
    scale, votes = scale_vote_loop(s)
    return R, scale * t_dir, float(votes)


def run(root: str, split: str, all_frames: bool = False, depth_suffix: str = "sensor") -> tuple[dict, dict]:
    """{scene: [(frame, Pose, confidence)]} and {"pairs", "seconds"} for a whole split."""
    out: dict = {}
    pairs, seconds = 0, 0.0
    for scene in Dataset(root).scenes(split):
        ref = scene.reference
        out[scene.name] = []
        queries = scene.queries if all_frames else scene.scored_queries()
        for q in queries:
            t0 = time.perf_counter()
            img0, img1 = ref.image(), q.image()
            d0 = ref.depth(depth_suffix) if ref.has_depth(depth_suffix) else None
            d1 = q.depth(depth_suffix) if q.has_depth(depth_suffix) else None
            res = relocalize_pair(img0, img1, ref.intrinsics.K, q.intrinsics.K, d0, d1)
            seconds += time.perf_counter() - t0
            pairs += 1
            if not isinstance(res, str):
                R, t, conf = res
                out[scene.name].append((q.name, Pose(R, t), conf))
    return out, {"pairs": pairs, "seconds": seconds}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("root")
    ap.add_argument("--split", default="val")
    ap.add_argument("--all-frames", action="store_true")
    ap.add_argument("-o", "--output", default="reference_spec4.zip")
    args = ap.parse_args(argv)
    from mapfree.benchmark import evaluate, write_submission

    cv2.setNumThreads(1)
    sub, stats = run(args.root, args.split, args.all_frames)
    write_submission(args.output, sub)
    report = evaluate(args.output, args.root, args.split)
    print(
        json.dumps(
            {"metrics": report.metrics.to_dict(), **stats, "pairs_per_s": stats["pairs"] / stats["seconds"]}, indent=1
        )
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
