"""A plain per-frame loop implementation of the benchmark, written the straightforward way.

It reads files line by line, keys frames by number in dicts, and scores one frame at a time with 4x4
matrices, like the public evaluator. It exists to cross-check the vectorised scorer (tests, bench) and
as the speed baseline; use ``mapfree.benchmark.evaluate`` for real work. It assumes a valid submission
(bad lines are skipped without a report).
"""

from __future__ import annotations

import io
import os
import zipfile
from pathlib import Path

import numpy as np

__all__ = ["evaluate_naive"]


def _qmult(a, b):
    w1, x1, y1, z1 = a
    w2, x2, y2, z2 = b
    return np.array(
        [
            w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
            w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
            w1 * y2 + y1 * w2 + z1 * x2 - x1 * z2,
            w1 * z2 + z1 * w2 + x1 * y2 - y1 * x2,
        ]
    )


def _qinv(q):
    """Conjugate over the norm (a unit quaternion for any non-zero q)."""
    return np.array([q[0], -q[1], -q[2], -q[3]]) / np.sqrt(np.dot(q, q))


def _qmat(q):
    w, x, y, z = q / np.sqrt(np.dot(q, q))
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def _to_cam2world(q, t):
    qi = _qinv(q)
    centre = -_qmult(qi, _qmult(np.r_[0.0, t], _qinv(qi)))[1:]
    return qi, centre


def _load_poses(lines, with_confidence, skip_negative):
    out = {}
    for line in lines:
        parts = line.split()
        if len(parts) != (9 if with_confidence else 8) or "#" in parts[0]:
            continue
        try:
            key = int(parts[0][-9:-4])
            vals = [float(v) for v in parts[1:]]
        except ValueError:
            continue
        if not all(np.isfinite(vals)):
            continue
        q, t = np.array(vals[:4]), np.array(vals[4:7])
        if np.isclose(np.linalg.norm(q), 0):
            continue
        conf = vals[7] if with_confidence else None
        if skip_negative and conf is not None and conf < 0:
            continue
        out[key] = (*_to_cam2world(q, t), conf, parts[0])
    return out


def _load_K(path):
    K = {}
    for line in Path(path).read_text().splitlines():
        parts = line.split()
        if not parts or "#" in parts[0]:
            continue
        fx, fy, cx, cy, W, H = map(float, parts[1:])
        K[int(parts[0][-9:-4])] = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]], dtype=np.float32)
    return K, W, H


def _grid():
    pts = []
    for y in (np.arange(4) - 1.5) * 0.3:
        for x in (np.arange(7) - 3) * 0.3:
            for z in np.arange(7) * 0.3 + 1.8:
                pts.append([x, y, z, 1.0])
    return np.array(pts)


_GRID = _grid()


def _project(pts, K, W, H):
    uvw = (K @ pts[:, :3].T).T
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = np.nan_to_num(uvw[:, :2] / uvw[:, 2:], nan=0.0, posinf=np.inf, neginf=-np.inf)
    uv[:, 0] = np.clip(uv[:, 0], 0, W)
    uv[:, 1] = np.clip(uv[:, 1], 0, H)
    return uv


def _vcre(q_est, c_est, q_gt, c_gt, K, W, H):
    T_est, T_gt = np.eye(4), np.eye(4)
    T_est[:3, :3], T_est[:3, 3] = _qmat(q_est), c_est
    T_gt[:3, :3], T_gt[:3, 3] = _qmat(q_gt), c_gt
    moved = (np.linalg.inv(T_est) @ T_gt @ _GRID.T).T
    return float(np.linalg.norm(_project(_GRID, K, W, H) - _project(moved, K, W, H), axis=1).mean())


def _rot_err(q_est, q_gt):
    a, b = q_gt / np.linalg.norm(q_gt), q_est / np.linalg.norm(q_est)
    s = np.linalg.norm(_qmult(a, _qinv(b))[1:])
    return float(np.arcsin(min(float(s), 1.0)) * 360.0 / np.pi)


def _auc(confidences, accepted, failures):
    items = sorted(zip(confidences, accepted), key=lambda x: -x[0])
    n = len(items)
    area, tp, prev_ratio = 0.0, 0, np.float32(0)
    for k, (c, ok) in enumerate(items, 1):
        tp += int(ok)
        if k < n and items[k][0] == c:
            continue  # only the last of tied confidences is a threshold
        ratio = np.float32(k) / np.float32(n + failures)
        area += float(ratio - prev_ratio) * (tp / k)
        prev_ratio = ratio
    return area


def evaluate_naive(
    submission_zip: os.PathLike | str,
    dataset_root: os.PathLike | str | None,
    split: str = "val",
    compat: str = "default",
    gt_root: os.PathLike | str | None = None,
    thresholds=((0.25, 5), (0.5, 10)),
    vcre_thresholds=(90, 45),
) -> tuple[dict[str, float | None], dict[tuple[str, str], tuple[float, float, float]]]:
    """(metrics, {(scene, frame): (trans_err, rot_err, vcre)}) computed one frame at a time."""
    base = gt_root if gt_root is not None else dataset_root
    if base is None:
        raise ValueError("need a dataset root or a ground-truth root")
    root = Path(base) / split
    results: dict[str, list[tuple[float, float, float, float]]] = {}
    failures = 0
    per_frame: dict[tuple[str, str], tuple[float, float, float]] = {}
    with zipfile.ZipFile(submission_zip) as zf:
        members = set(zf.namelist())
        for scene in sorted(p.name for p in root.iterdir() if p.is_dir()):
            intr = root / scene / "intrinsics.txt"
            if not intr.is_file() and dataset_root is not None:
                intr = Path(dataset_root) / split / scene / "intrinsics.txt"
            K, W, H = _load_K(intr)
            gt = _load_poses((root / scene / "poses.txt").read_text().splitlines(), False, False)
            if f"pose_{scene}.txt" not in members:
                scored = [v[3] for i, v in enumerate(gt.values()) if i % 5 == 0 and v[3].startswith("seq1/")]
                failures += len(gt) if compat == "official" else len(scored)
                continue
            text = io.TextIOWrapper(zf.open(f"pose_{scene}.txt"), encoding="utf-8").read()
            est = _load_poses(text.splitlines(), True, compat != "official")
            rows = []
            for i, (key, (q_gt, c_gt, _, name)) in enumerate(gt.items()):
                if i % 5 or (compat != "official" and not name.startswith("seq1/")):
                    continue
                if key not in est:
                    failures += 1
                    continue
                q_est, c_est, conf, _ = est[key]
                te = float(np.linalg.norm(c_est - c_gt))
                re = _rot_err(q_est, q_gt)
                ve = _vcre(q_est, c_est, q_gt, c_gt, K[key], W, H)
                rows.append((te, re, ve, conf))
                per_frame[(scene, name)] = (te, re, ve)
            if rows:
                results[scene] = rows
    all_rows = [r for rows in results.values() for r in rows]
    total = len(all_rows) + failures
    metrics: dict[str, float | None] = {}
    for j, key in enumerate(("Translation", "Rotation", "Reprojection")):
        medians = [float(np.median([r[j] for r in rows])) for rows in results.values()]
        metrics[f"Average Median {key} Error"] = float(np.mean(medians)) if medians else None
    conf = [r[3] for r in all_rows]
    for tm, rd in thresholds:
        ok = [r[0] < tm and r[1] < rd for r in all_rows]
        metrics[f"Precision @ Pose Error < ({tm * 100}cm, {rd:g}deg)"] = sum(ok) / total
        metrics[f"AUC @ Pose Error < ({tm * 100}cm, {rd:g}deg)"] = _auc(conf, ok, failures)
    for px in vcre_thresholds:
        ok = [r[2] < px for r in all_rows]
        metrics[f"Precision @ VCRE < {px:g}px"] = sum(ok) / total
        metrics[f"AUC @ VCRE < {px:g}px"] = _auc(conf, ok, failures)
    metrics["Estimates for % of frames"] = len(all_rows) / total
    return metrics, per_frame
