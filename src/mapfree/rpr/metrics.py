"""Training-time metrics (numpy): pose errors, VCRE and AUC as the benchmark defines them, and the confidence.

A small self-contained copy for validation curves; the benchmark package is the reference scorer.
"""

from __future__ import annotations

import numpy as np

__all__ = ["virtual_points", "vcre_px", "pose_errors", "auc", "confidence_from_log_sigma", "summarize"]

ROT_TAU_RAD = np.deg2rad(5.0)
TRANS_TAU_M = 0.25


def virtual_points() -> np.ndarray:
    """The 196 virtual points of the VCRE (7 x 4 x 7 grid in the ground-truth query camera)."""
    x = np.arange(-0.9, 0.9 + 1e-9, 0.3)
    y = np.array([-0.45, -0.15, 0.15, 0.45])
    z = np.arange(1.8, 3.6 + 1e-9, 0.3)
    X, Y, Z = np.meshgrid(x, y, z, indexing="ij")
    return np.stack([X.ravel(), Y.ravel(), Z.ravel()], -1)


def _project_clipped(X: np.ndarray, K: np.ndarray, W: np.ndarray, H: np.ndarray) -> np.ndarray:
    uvw = np.einsum("bij,bnj->bni", K, X)
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = uvw[..., :2] / uvw[..., 2:3]
    uv = np.nan_to_num(uv, nan=0.0, posinf=1e12, neginf=-1e12)
    return np.stack([np.clip(uv[..., 0], 0, W[:, None]), np.clip(uv[..., 1], 0, H[:, None])], -1)


def vcre_px(R_est, t_est, R_gt, t_gt, K, size) -> np.ndarray:
    """(B,) VCRE in pixels of relative poses (query w.r.t. reference), K (B,3,3) and size (B,2) = (W,H)."""
    R_est, t_est, R_gt, t_gt, K, size = (np.asarray(a, dtype=np.float64) for a in (R_est, t_est, R_gt, t_gt, K, size))
    X = np.broadcast_to(virtual_points(), (len(R_gt), 196, 3))
    W, H = size[:, 0], size[:, 1]
    Xw = np.einsum("bji,bnj->bni", R_gt, X - t_gt[:, None])  # GT query camera -> reference (world) frame
    Xe = np.einsum("bij,bnj->bni", R_est, Xw) + t_est[:, None]  # -> estimated query camera
    return np.linalg.norm(_project_clipped(X, K, W, H) - _project_clipped(Xe, K, W, H), axis=-1).mean(-1)


def pose_errors(R_est, t_est, R_gt, t_gt) -> tuple[np.ndarray, np.ndarray]:
    """(B,) camera-centre distance (m) and rotation angle (deg), as the benchmark measures them."""
    R_est, t_est, R_gt, t_gt = (np.asarray(a, dtype=np.float64) for a in (R_est, t_est, R_gt, t_gt))
    c_est = -np.einsum("bji,bj->bi", R_est, t_est)
    c_gt = -np.einsum("bji,bj->bi", R_gt, t_gt)
    M = np.einsum("bji,bjk->bik", R_est, R_gt)
    cos = np.clip((np.trace(M, axis1=1, axis2=2) - 1) / 2, -1, 1)
    return np.linalg.norm(c_est - c_gt, axis=-1), np.degrees(np.arccos(cos))


def auc(confidence: np.ndarray, accepted: np.ndarray, failures: int = 0) -> float:
    """Area under precision vs ratio of estimates as the confidence threshold sweeps."""
    conf = np.asarray(confidence, dtype=np.float64)
    ok = np.asarray(accepted, dtype=bool)
    if len(conf) == 0:
        return 0.0
    order = np.argsort(conf)[::-1]
    conf, ok = conf[order], ok[order]
    ranks = np.arange(len(conf), dtype=np.float32) + 1
    prec = np.cumsum(ok) / ranks
    rec = ranks / (len(conf) + failures)
    last = np.r_[conf[1:] != conf[:-1], True]  # only the last index of each run of equal confidences
    prec, rec = np.r_[1.0, prec[last]], np.r_[0.0, rec[last]]
    return float(np.sum((rec[1:] - rec[:-1]) * prec[1:]))


def confidence_from_log_sigma(log_sigma: np.ndarray) -> np.ndarray:
    """(B,2) predicted log error scales -> (B,) confidence in (0,1]: 1 / (1 + b_R/5° + b_t/0.25 m).

    Higher when both predicted errors are small relative to the acceptance thresholds; never 0 in print.
    """
    b = np.exp(np.clip(np.asarray(log_sigma, dtype=np.float64), -30, 30))
    return 1.0 / (1.0 + b[:, 0] / ROT_TAU_RAD + b[:, 1] / TRANS_TAU_M)


def summarize(trans_err, rot_err, vcre, confidence, vcre_px_max: float = 90.0) -> dict[str, float]:
    """Medians, precisions and AUCs of a set of estimates (no failures)."""
    trans_err, rot_err, vcre = map(np.asarray, (trans_err, rot_err, vcre))
    pose_ok = (trans_err < 0.25) & (rot_err < 5.0)
    vcre_ok = vcre < vcre_px_max
    return {
        "trans_err_med": float(np.median(trans_err)),
        "rot_err_med": float(np.median(rot_err)),
        "vcre_med": float(np.median(vcre)),
        "pose_prec": float(pose_ok.mean()),
        "vcre_prec": float(vcre_ok.mean()),
        "pose_auc": auc(confidence, pose_ok),
        "vcre_auc": auc(confidence, vcre_ok),
    }
