"""Per-frame errors and aggregate scores of the Map-free benchmark, vectorised over frames.

Every function takes stacked arrays for N frames: world-to-camera quaternions ``q`` (N,4, wxyz, any
non-zero norm) and translations ``t`` (N,3), as written in ``poses.txt`` and submissions.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = [
    "Thresholds",
    "virtual_points",
    "camera_centers",
    "translation_error",
    "rotation_error_deg",
    "vcre",
    "precision_ratio_curve",
    "auc",
    "segment_auc",
]


@dataclass(frozen=True)
class Thresholds:
    """Acceptance thresholds of the precision and AUC metrics; the first of each tuple is the headline.

    Attributes:
        pose: ``(metres, degrees)`` pairs: a frame is accepted when both errors are below them.
        vcre: Pixel thresholds of the VCRE (90 and 45: 10 % and 5 % of a 540x720 image's diagonal).
    """

    pose: tuple[tuple[float, float], ...] = ((0.25, 5), (0.5, 10))  # (metres, degrees)
    vcre: tuple[float, ...] = (90, 45)  # pixels: 10 % and 5 % of a 540x720 image's diagonal

    @staticmethod
    def pose_name(t_m: float, r_deg: float) -> str:
        """Metric-name suffix of a pose threshold, as the public evaluator spells it.

        Args:
            t_m: Translation threshold, metres.
            r_deg: Rotation threshold, degrees.

        Returns:
            E.g. ``Pose Error < (25.0cm, 5deg)``.
        """
        return f"Pose Error < ({t_m * 100}cm, {r_deg:g}deg)"

    @staticmethod
    def vcre_name(px: float) -> str:
        """Metric-name suffix of a VCRE threshold, as the public evaluator spells it.

        Args:
            px: Threshold, pixels.

        Returns:
            E.g. ``VCRE < 90px``.
        """
        return f"VCRE < {px:g}px"


def virtual_points() -> np.ndarray:
    """The virtual points the VCRE moves: a 7 x 4 x 7 grid in front of the true query camera.

    Returns:
        (196, 3) points in the query camera frame, metres (0.3 m apart, 1.8 m to 3.6 m deep).
    """
    x = (np.arange(7) - 3) * 0.3
    y = (np.arange(4) - 1.5) * 0.3
    z = np.arange(7) * 0.3 + 1.8
    yy, xx, zz = np.meshgrid(y, x, z, indexing="ij")  # same order as the public evaluator's meshgrid
    return np.stack([xx.ravel(), yy.ravel(), zz.ravel()], axis=1)


_POINTS = virtual_points()


def _unit(q: np.ndarray) -> np.ndarray:
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def _rotmat(q: np.ndarray) -> np.ndarray:
    """(N,4) unit wxyz -> (N,3,3)."""
    w, x, y, z = q.T
    return np.stack(
        [
            1 - 2 * (y * y + z * z),
            2 * (x * y - w * z),
            2 * (x * z + w * y),
            2 * (x * y + w * z),
            1 - 2 * (x * x + z * z),
            2 * (y * z - w * x),
            2 * (x * z - w * y),
            2 * (y * z + w * x),
            1 - 2 * (x * x + y * y),
        ],
        axis=-1,
    ).reshape(-1, 3, 3)


def camera_centers(q: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Camera centres ``-R^T t`` of world-to-camera poses.

    Args:
        q: (N, 4) quaternions ``w x y z``, any non-zero norm.
        t: (N, 3) translations, metres.

    Returns:
        (N, 3) centres in world coordinates, metres.
    """
    return -np.einsum("nji,nj->ni", _rotmat(_unit(q)), t)


def translation_error(q_gt: np.ndarray, t_gt: np.ndarray, q_est: np.ndarray, t_est: np.ndarray) -> np.ndarray:
    """Translation error of the benchmark: distance between estimated and true camera centres.

    Args:
        q_gt: (N, 4) true world-to-camera quaternions ``w x y z``.
        t_gt: (N, 3) true translations, metres.
        q_est: (N, 4) estimated quaternions.
        t_est: (N, 3) estimated translations, metres.

    Returns:
        (N,) errors in metres.
    """
    return np.linalg.norm(camera_centers(q_est, t_est) - camera_centers(q_gt, t_gt), axis=1)


def rotation_error_deg(q_gt: np.ndarray, q_est: np.ndarray) -> np.ndarray:
    """Geodesic angle between the rotations (degrees), (N,).

    Computed as ``2 asin |vec(conj(q_gt) q_est)|`` like the public evaluator: accurate near 0°, where
    the trace formula loses about 1e-6 degree.

    Args:
        q_gt: (N, 4) true quaternions ``w x y z``, any non-zero norm.
        q_est: (N, 4) estimated quaternions.

    Returns:
        (N,) errors in degrees.
    """
    a, b = _unit(q_gt), _unit(q_est)
    aw, av = a[:, :1], -a[:, 1:]  # conjugate of q_gt
    bw, bv = b[:, :1], b[:, 1:]
    vec = aw * bv + bw * av + np.cross(av, bv)
    s = np.clip(np.linalg.norm(vec, axis=1), 0.0, 1.0)
    return 2.0 * np.degrees(np.arcsin(s))


def vcre(
    q_gt: np.ndarray,
    t_gt: np.ndarray,
    q_est: np.ndarray,
    t_est: np.ndarray,
    K: np.ndarray,
    W: np.ndarray,
    H: np.ndarray,
    chunk: int = 256,
) -> np.ndarray:
    """Virtual correspondence reprojection error (pixels), (N,).

    The 196 virtual points live in the true query camera; they are projected with K, and again after
    moving them by ``inv(T_est_cam2world) T_gt_cam2world``; both projections are clipped to
    ``[0, W] x [0, H]``; the error is the mean pixel distance. A point landing exactly on the estimated
    camera centre (0/0) counts as projecting to the image corner (0, 0).

    Args:
        q_gt: (N, 4) true world-to-camera quaternions ``w x y z``.
        t_gt: (N, 3) true translations, metres.
        q_est: (N, 4) estimated quaternions.
        t_est: (N, 3) estimated translations, metres.
        K: (N, 4) ``fx fy cx cy`` of each query, pixels (float32 in the public evaluator).
        W: (N,) image widths, pixels.
        H: (N,) image heights, pixels.
        chunk: Frames per vectorised pass (memory, not results).

    Returns:
        (N,) errors in pixels.
    """
    n = len(q_gt)
    out = np.empty(n)
    if n == 0:
        return out
    fx, fy, cx, cy = K.astype(np.float64).T
    Rg, Re = _rotmat(_unit(q_gt)), _rotmat(_unit(q_est))
    cg = -np.einsum("nji,nj->ni", Rg, t_gt)
    ce = -np.einsum("nji,nj->ni", Re, t_est)
    # Homogeneous pixels of the moved points: K [R_e R_g^T | R_e (c_g - c_e)] X, one 3x4 matrix per frame.
    A = np.empty((n, 3, 4))
    A[:, :, :3] = Re @ np.swapaxes(Rg, 1, 2)
    A[:, :, 3] = np.einsum("nij,nj->ni", Re, cg - ce)
    A[:, 0] = fx[:, None] * A[:, 0] + cx[:, None] * A[:, 2]
    A[:, 1] = fy[:, None] * A[:, 1] + cy[:, None] * A[:, 2]
    P = _POINTS
    Ph = np.vstack([P.T, np.ones(len(P))])
    a, b = P[:, 0] / P[:, 2], P[:, 1] / P[:, 2]
    one_size = bool(np.all(W[0] == W) and np.all(H[0] == H))  # scalar bounds clip much faster
    # Buffers reused chunk after chunk: every pass stays in cache and nothing is allocated per chunk. A stacked
    # matmul, not one big GEMM: BLAS threads spinning on a busy machine cost more than they save.
    m = min(chunk, n)
    uvw, u, v, g = np.empty((m, 3, len(P))), np.empty((m, len(P))), np.empty((m, len(P))), np.empty((m, len(P)))
    for s in range(0, n, chunk):
        e = min(s + chunk, n)
        k = e - s
        X, U, V, G = uvw[:k], u[:k], v[:k], g[:k]
        np.matmul(A[s:e], Ph, out=X)
        with np.errstate(divide="ignore", invalid="ignore"):
            np.divide(X[:, 0], X[:, 2], out=U)
            np.divide(X[:, 1], X[:, 2], out=V)
        w_, h_ = (float(W[s]), float(H[s])) if one_size else (W[s:e, None], H[s:e, None])
        np.clip(U, 0.0, w_, out=U)  # NaN (0/0) propagates; handled below
        np.clip(V, 0.0, h_, out=V)
        U -= np.clip(np.add(np.multiply(fx[s:e, None], a, out=G), cx[s:e, None], out=G), 0.0, w_, out=G)
        V -= np.clip(np.add(np.multiply(fy[s:e, None], b, out=G), cy[s:e, None], out=G), 0.0, h_, out=G)
        U *= U
        V *= V
        U += V
        out[s:e] = np.sqrt(U, out=U).mean(axis=1)
    bad = np.flatnonzero(np.isnan(out))
    if len(bad):  # rare: a 0/0 projection counts as the corner (0, 0), so its offset is -uv_gt
        X = A[bad] @ Ph
        wb, hb = W[bad, None], H[bad, None]
        with np.errstate(divide="ignore", invalid="ignore"):
            du, dv = X[:, 0] / X[:, 2], X[:, 1] / X[:, 2]
        du = np.where(np.isnan(du), 0.0, np.clip(du, 0.0, wb)) - np.clip(fx[bad, None] * a + cx[bad, None], 0.0, wb)
        dv = np.where(np.isnan(dv), 0.0, np.clip(dv, 0.0, hb)) - np.clip(fy[bad, None] * b + cy[bad, None], 0.0, hb)
        out[bad] = np.hypot(du, dv).mean(axis=1)
    return out


def precision_ratio_curve(confidence: np.ndarray, accepted: np.ndarray, failures: int) -> tuple[np.ndarray, np.ndarray]:
    """Precision against the ratio of frames kept, as the confidence threshold is lowered.

    Only the last of tied confidences is a threshold. Ranks are float32 as in the public evaluator, so the
    ratios round the same way.

    Args:
        confidence: (N,) confidences of the estimated frames.
        accepted: (N,) whether each frame meets the criterion, or (k, N) for k criteria at once.
        failures: Frames without an estimate (they count in the ratio's denominator).

    Returns:
        (T,) float32 ratios of frames kept, increasing and truncated at full ratio, and the precision at
            each: (T,), or (k, T) for (k, N) ``accepted``.
    """
    conf = np.asarray(confidence, dtype=np.float64)
    acc = np.asarray(accepted, dtype=bool)
    n = len(conf)
    if n == 0:
        return np.zeros(0, np.float32), np.zeros(acc.shape[:-1] + (0,))
    order = np.argsort(conf)[::-1]
    conf = conf[order]
    tp = acc[..., order]
    last = np.append(np.flatnonzero(np.diff(conf)), n - 1)
    ranks = np.arange(n, dtype=np.float32) + 1
    precision = np.cumsum(tp, axis=-1)[..., last] / ranks[last]
    ratio = ranks[last] / np.float32(float(n) + float(failures))
    keep = np.searchsorted(ratio, ratio[-1]) + 1  # truncate at the first point of full ratio
    return ratio[:keep], precision[..., :keep]


def auc(confidence: np.ndarray, accepted: np.ndarray, failures: int) -> float | np.ndarray:
    """Area under the precision-ratio curve, ``sum (r_k - r_{k-1}) p_k`` with ``r_0 = 0`` (the AUC metrics).

    Args:
        confidence: (N,) confidences of the estimated frames.
        accepted: (N,) whether each frame meets the criterion, or (k, N) for k criteria at once.
        failures: Frames without an estimate.

    Returns:
        The area, a float for (N,) ``accepted``; (k,) areas for (k, N).
    """
    ratio, precision = precision_ratio_curve(confidence, accepted, failures)
    step = np.diff(np.concatenate([np.zeros(1, np.float32), ratio]))  # float32 steps, like the public evaluator
    area = np.abs(np.sum(step * precision, axis=-1))
    return float(area) if np.ndim(area) == 0 else area


def segment_auc(segment: np.ndarray, confidence: np.ndarray, accepted: np.ndarray, failures: np.ndarray) -> np.ndarray:
    """``auc`` of every segment (scene) at once: (k, S) areas for (k, N) ``accepted``.

    ``segment`` (N,) holds each estimate's segment in ``0..S-1``; ``failures`` (S,) the failures of each.
    Same definition and float32 ratios as ``auc`` (the truncation at full ratio only matters when two
    float32 ratios collide, i.e. beyond 2**24 frames in a segment).
    """
    acc = np.atleast_2d(np.asarray(accepted, dtype=bool))
    S = len(failures)
    out = np.zeros((len(acc), S))
    n = len(confidence)
    if n == 0:
        return out
    order = np.lexsort((-np.asarray(confidence, dtype=np.float64), segment))
    seg, conf, tp = segment[order], np.asarray(confidence)[order], acc[:, order]
    counts = np.bincount(seg, minlength=S)
    first = np.cumsum(counts) - counts
    rank = (np.arange(n) - first[seg] + 1).astype(np.float32)
    cum = np.cumsum(tp, axis=1)
    base = cum[:, first[seg]] - tp[:, first[seg]]  # accepted count before each frame's segment
    last = np.ones(n, dtype=bool)
    last[:-1] = (seg[1:] != seg[:-1]) | (conf[1:] != conf[:-1])
    thr = np.flatnonzero(last)
    precision = (cum - base)[:, thr] / rank[thr]
    total = (counts + np.asarray(failures)).astype(np.float32)
    ratio = rank[thr] / total[seg[thr]]
    prev = np.zeros_like(ratio)
    prev[1:] = ratio[:-1]
    prev[np.r_[True, seg[thr][1:] != seg[thr][:-1]]] = 0
    step = ratio - prev  # float32, like auc()
    for i in range(len(acc)):
        out[i] = np.abs(np.bincount(seg[thr], weights=step * precision[i], minlength=S))
    return out
