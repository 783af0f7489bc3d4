"""How close a built scene is to the truth of its place (synthetic scans): poses after the metric scale, overlaps.

The built scene's metric frame is aligned to the true world by a rigid transform only (no scale), so a
wrong metric scale shows up as camera-centre error.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..data.io import read_poses
from ..data.overlaps import read_overlaps
from ..geometry import Pose, rotation_angle_deg
from ..solvers.common import kabsch
from .place import REPORT_FILE

__all__ = ["compare_to_truth"]


def compare_to_truth(scene: Path, truth_place: Path) -> dict:
    """Median rotation error (deg), median centre error relative to the scan's extent, overlap correlation.

    ``truth_place`` holds ``scanK/poses.txt`` (true world-to-camera poses by file name) and ``overlaps.npz``
    (seq = scan index, frame = position in the scan), as ``mapfree synth --split scans --private-gt`` writes.
    """
    scene, truth_place = Path(scene), Path(truth_place)
    report = json.loads((scene / REPORT_FILE).read_text())
    built = read_poses(scene / "poses.txt").as_dict()
    tables: dict[str, dict[str, Pose | None]] = {}  # one read per scan, not per frame
    truth: dict[str, Pose | None] = {}
    for name, src in report["frames"].items():
        src = Path(src)
        scan = src.parent.name
        if scan not in tables:
            tables[scan] = read_poses(truth_place / scan / "poses.txt").as_dict()
        truth[name] = tables[scan][src.name]
    both = [(n, b, t) for n, b in built.items() if b is not None and (t := truth.get(n)) is not None]
    names = [n for n, _, _ in both]
    if len(names) < 3:
        raise ValueError(f"{scene}: fewer than 3 frames with both built and true poses")
    Cb = np.stack([b.center for _, b, _ in both])
    Ct = np.stack([t.center for _, _, t in both])
    A, b = kabsch(Cb, Ct)  # Ct ~ A Cb + b
    centre_err = np.linalg.norm(Cb @ A.T + b - Ct, axis=1)
    rot_err = np.array([rotation_angle_deg(b.R @ A.T, t.R) for _, b, t in both])
    seq = np.array([n.split("/")[0] for n in names])
    extent = {s: float(np.linalg.norm(np.ptp(Ct[seq == s], axis=0))) for s in set(seq)}
    rel = centre_err / np.array([extent[s] for s in seq])
    out = {
        "frames": len(names),
        "rotation_median_deg": float(np.median(rot_err)),
        "centre_median_m": float(np.median(centre_err)),
        "centre_median_rel": float(np.median(rel)),
        "scan_extent_m": extent,
    }
    if (scene / "overlaps.npz").is_file() and (truth_place / "overlaps.npz").is_file():
        ob, ot = read_overlaps(scene / "overlaps.npz"), read_overlaps(truth_place / "overlaps.npz")
        # Built names -> (scan index, position in the scan) of the truth.
        key = {}
        for name, src in report["frames"].items():
            k = int(name[3]), int(name[-9:-4])
            key[k] = (int(Path(src).parent.name.removeprefix("scan") or 0), int(Path(src).stem[-5:]))
        kept = set(key.values())
        vb = {key[(a, b)] + key[(c, d)]: v for (a, b, c, d), v in zip(ob.idxs.tolist(), ob.overlaps) if (a, b) in key}
        vt = {
            tuple(r): v for r, v in zip(ot.idxs.tolist(), ot.overlaps) if tuple(r[:2]) in kept and tuple(r[2:]) in kept
        }
        pairs = sorted(set(vb) | set(vt))
        x = np.array([vb.get(p, 0.0) for p in pairs])
        y = np.array([vt.get(p, 0.0) for p in pairs])
        out["overlap_pairs"] = len(pairs)
        out["overlap_correlation"] = float(np.corrcoef(x, y)[0, 1]) if len(pairs) > 2 else float("nan")
    return out
