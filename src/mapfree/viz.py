"""Pictures of one relocalization: the matches (inliers coloured) and the paper's AR check.

The AR check places a grid of virtual 3D points in front of the reference camera and renders it into the
query with the estimated pose (and with the ground truth when known): where the two renderings disagree,
a virtual object would visibly jump. With a ground truth the grid is the benchmark's VCRE grid, so the
drawn displacement is exactly what the VCRE metric averages. Drawing is OpenCV; images are RGB uint8.
"""

from __future__ import annotations

import os
from pathlib import Path

import cv2
import numpy as np

from .data.io import naming, write_image
from .estimate import Estimate
from .geometry import Intrinsics, Pose, project

__all__ = [
    "vcre_grid",
    "epipolar_inliers",
    "draw_matches",
    "draw_grid",
    "ar_panels",
    "relocalization_figure",
    "save_png",
    "vcre_px",
    "estimate_figure",
    "png_bytes",
    "jpeg_bytes",
    "report_picture",
    "save_figure",
    "fit",
]

GREEN, RED, ORANGE, CYAN, WHITE = (40, 200, 60), (230, 40, 40), (255, 150, 0), (0, 200, 255), (255, 255, 255)


def vcre_grid() -> np.ndarray:
    """The virtual points of the VCRE metric, drawn by the AR check.

    Returns:
        (196, 3) points on a 7 x 4 x 7 grid in front of a camera, camera frame, metres.
    """
    x = np.linspace(-0.9, 0.9, 7)
    y = np.array([-0.45, -0.15, 0.15, 0.45])
    z = np.linspace(1.8, 3.6, 7)
    X, Y, Z = np.meshgrid(x, y, z, indexing="ij")
    return np.stack([X.ravel(), Y.ravel(), Z.ravel()], axis=1)


def vcre_px(pose_est: Pose, pose_gt: Pose, K: Intrinsics) -> float:
    """Virtual correspondence reprojection error of one relative pose, clipped to the image.

    Args:
        pose_est: Estimated pose of the query relative to the reference.
        pose_gt: True pose of the query relative to the reference.
        K: Intrinsics of the query.

    Returns:
        Mean displacement of the virtual points, pixels.
    """
    X_q = vcre_grid()  # in the ground-truth query camera
    X_ref = pose_gt.inverse().transform(X_q)
    size = np.array([K.width, K.height], dtype=np.float64)
    uv_gt = np.clip(project(X_q, K.K), 0, size)
    uv_est = project(pose_est.transform(X_ref), K.K)
    uv_est = np.clip(np.nan_to_num(uv_est, nan=0.0, posinf=1e9, neginf=-1e9), 0, size)
    return float(np.mean(np.linalg.norm(uv_gt - uv_est, axis=1)))


def epipolar_inliers(
    kpts0: np.ndarray, kpts1: np.ndarray, K0: Intrinsics, K1: Intrinsics, pose: Pose, threshold_px: float = 3.0
) -> np.ndarray:
    """Matches consistent with a relative pose, whichever solver gave it (the green lines of a figure).

    Args:
        kpts0: (N, 2) pixels in the reference image.
        kpts1: (N, 2) pixels in the query image.
        K0: Intrinsics of the reference.
        K1: Intrinsics of the query.
        pose: Pose of the query relative to the reference.
        threshold_px: Largest Sampson distance of a consistent match, pixels.

    Returns:
        (N,) bool.
    """
    if len(kpts0) == 0:
        return np.zeros(0, dtype=bool)
    t = pose.t / max(np.linalg.norm(pose.t), 1e-12)
    tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    F = np.linalg.inv(K1.K).T @ tx @ pose.R @ np.linalg.inv(K0.K)
    x0 = np.c_[kpts0, np.ones(len(kpts0))]
    x1 = np.c_[kpts1, np.ones(len(kpts1))]
    Fx0, Ftx1 = x0 @ F.T, x1 @ F
    num = np.sum(x1 * Fx0, axis=1) ** 2
    den = Fx0[:, 0] ** 2 + Fx0[:, 1] ** 2 + Ftx1[:, 0] ** 2 + Ftx1[:, 1] ** 2
    with np.errstate(divide="ignore", invalid="ignore"):
        d = np.sqrt(num / den)
    return np.nan_to_num(d, nan=np.inf) < threshold_px


def _side_by_side(img0: np.ndarray, img1: np.ndarray) -> tuple[np.ndarray, int]:
    h = max(img0.shape[0], img1.shape[0])
    canvas = np.zeros((h, img0.shape[1] + img1.shape[1], 3), np.uint8)
    canvas[: img0.shape[0], : img0.shape[1]] = img0
    canvas[: img1.shape[0], img0.shape[1] :] = img1
    return canvas, img0.shape[1]


def _label(img: np.ndarray, text: str, row: int = 0) -> None:
    """White text on a dark box, top-left, one row per call (OpenCV's fonts are ASCII only: ° becomes "deg")."""
    text = text.replace("°", " deg").replace("…", "...").replace("×", "x").replace("≥", ">=").replace("≤", "<=")
    text = text.encode("ascii", "replace").decode()
    (w, h), base = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, 0.5, 1)
    y = 6 + (h + base + 6) * row
    cv2.rectangle(img, (4, y), (12 + w, y + h + base + 4), (20, 20, 20), -1)
    cv2.putText(img, text, (8, y + h + 2), cv2.FONT_HERSHEY_SIMPLEX, 0.5, WHITE, 1, cv2.LINE_AA)


def draw_matches(
    img0: np.ndarray,
    img1: np.ndarray,
    kpts0: np.ndarray,
    kpts1: np.ndarray,
    inliers: np.ndarray | None = None,
    max_lines: int = 400,
    seed: int = 0,
    label: str | None = None,
) -> np.ndarray:
    """Reference and query side by side with their matches: inliers green, the others red.

    Args:
        img0: (H0, W0, 3) uint8 RGB reference.
        img1: (H1, W1, 3) uint8 RGB query.
        kpts0: (N, 2) pixels in ``img0``.
        kpts1: (N, 2) pixels in ``img1``.
        inliers: (N,) bool; every match green when None.
        max_lines: Matches drawn at most (a random subset beyond).
        seed: Seed of the subset.
        label: The headline; default the number of matches and of green ones.

    Returns:
        (max(H0, H1), W0 + W1, 3) uint8 RGB.
    """
    canvas, off = _side_by_side(img0, img1)
    n = len(kpts0)
    inl = np.ones(n, bool) if inliers is None else np.asarray(inliers, bool)
    idx = np.arange(n)
    if n > max_lines:
        idx = np.sort(np.random.default_rng(seed).choice(n, max_lines, replace=False))
    for i in sorted(idx, key=lambda i: inl[i]):  # inliers drawn last, on top
        a = tuple(int(round(v)) for v in kpts0[i])
        b = (int(round(kpts1[i][0])) + off, int(round(kpts1[i][1])))
        colour = GREEN if inl[i] else RED
        cv2.line(canvas, a, b, colour, 1, cv2.LINE_AA)
        cv2.circle(canvas, a, 2, colour, -1, cv2.LINE_AA)
        cv2.circle(canvas, b, 2, colour, -1, cv2.LINE_AA)
    _label(
        canvas,
        label
        if label is not None
        else f"{n} matches, {int(inl.sum())} consistent with the pose"
        if inliers is not None
        else f"{n} matches",
    )
    return canvas


def draw_grid(img: np.ndarray, X_cam: np.ndarray, K: Intrinsics, colour: tuple, radius: int = 3) -> np.ndarray:
    """Draw camera-frame points as filled dots (those in front of the camera, near or inside the image).

    Args:
        img: (H, W, 3) uint8 RGB, not modified.
        X_cam: (N, 3) points in the camera frame, metres.
        K: Intrinsics of the image.
        colour: RGB colour of the dots.
        radius: Dot radius, pixels.

    Returns:
        A copy of ``img`` with the dots.
    """
    out = img.copy()
    uv = project(X_cam, K.K)
    ok = (X_cam[:, 2] > 1e-6) & np.all(np.isfinite(uv), axis=1)
    ok &= (uv[:, 0] >= -50) & (uv[:, 0] <= K.width + 50) & (uv[:, 1] >= -50) & (uv[:, 1] <= K.height + 50)
    for u, v in uv[ok]:
        cv2.circle(out, (int(round(u)), int(round(v))), radius, colour, -1, cv2.LINE_AA)
    return out


def ar_panels(
    ref_img: np.ndarray,
    query_img: np.ndarray,
    K_ref: Intrinsics,
    K_query: Intrinsics,
    pose: Pose | None,
    gt_pose: Pose | None = None,
    reason: str = "",
) -> np.ndarray:
    """The AR check: a virtual grid seen from the reference, and rendered into the query by the estimate.

    The query shows the grid placed by the estimate (orange) and by the ground truth (cyan, with each
    point's displacement: what VCRE averages).

    Args:
        ref_img: (H, W, 3) uint8 RGB reference.
        query_img: (H', W', 3) uint8 RGB query.
        K_ref: Intrinsics of the reference.
        K_query: Intrinsics of the query.
        pose: Estimated pose of the query relative to the reference, or None.
        gt_pose: True pose, when known.
        reason: Why there is no estimate (shown when ``pose`` is None).

    Returns:
        The two panels side by side, uint8 RGB.
    """
    # The grid lives in the reference camera frame; with a ground truth it is the VCRE grid of the query.
    X_ref = gt_pose.inverse().transform(vcre_grid()) if gt_pose is not None else vcre_grid()
    left = draw_grid(ref_img, X_ref, K_ref, CYAN if gt_pose is not None else ORANGE)
    right = query_img.copy()
    if gt_pose is not None:
        right = draw_grid(right, gt_pose.transform(X_ref), K_query, CYAN, radius=4)
        if pose is not None:  # each virtual point's displacement: what VCRE averages
            a, b = project(gt_pose.transform(X_ref), K_query.K), project(pose.transform(X_ref), K_query.K)
            ok = np.all(np.isfinite(a) & np.isfinite(b) & (np.abs(a) < 1e5) & (np.abs(b) < 1e5), axis=1)
            for p, q in zip(a[ok], b[ok]):
                cv2.line(right, tuple(int(round(v)) for v in p), tuple(int(round(v)) for v in q), WHITE, 1, cv2.LINE_AA)
    if pose is not None:
        right = draw_grid(right, pose.transform(X_ref), K_query, ORANGE, radius=2)
    canvas, _ = _side_by_side(left, right)
    _label(canvas, "AR check: virtual grid, estimate = orange" + (", ground truth = cyan" if gt_pose else ""))
    if pose is None:
        text = f"no estimate: {reason}" if reason else "no estimate"
        _label(canvas, text if len(text) <= 90 else text[:87] + "...", row=1)
    elif gt_pose is not None:
        terr = float(np.linalg.norm(pose.center - gt_pose.center))
        rerr = float(np.degrees(np.arccos(np.clip((np.trace(pose.R.T @ gt_pose.R) - 1) / 2, -1, 1))))
        _label(canvas, f"error {terr:.2f} m, {rerr:.1f} deg, VCRE {vcre_px(pose, gt_pose, K_query):.0f} px", row=1)
    return canvas


def relocalization_figure(
    ref_img: np.ndarray,
    query_img: np.ndarray,
    K_ref: Intrinsics,
    K_query: Intrinsics,
    kpts0: np.ndarray | None,
    kpts1: np.ndarray | None,
    pose: Pose | None,
    gt_pose: Pose | None = None,
    threshold_px: float = 3.0,
    title: str = "",
    reason: str = "",
    solver_inliers: int | None = None,
) -> np.ndarray:
    """The figure of one relocalization: matches on top, the AR check below, one RGB image.

    Args:
        ref_img: (H, W, 3) uint8 RGB reference.
        query_img: (H', W', 3) uint8 RGB query.
        K_ref: Intrinsics of the reference.
        K_query: Intrinsics of the query.
        kpts0: (N, 2) matched pixels in the reference; None for a method without correspondences (pose
            regression): the AR check alone.
        kpts1: (N, 2) matched pixels in the query, or None.
        pose: Estimated pose of the query relative to the reference, or None.
        gt_pose: True pose, when known.
        threshold_px: Green matches are within this distance of the pose's epipolar lines, pixels.
        title: A line drawn on the figure.
        reason: Why there is no pose, when there is none.
        solver_inliers: The solver's own inlier count (the estimate's ``inliers``), shown in the headline.

    Returns:
        uint8 RGB image.
    """
    bottom = ar_panels(ref_img, query_img, K_ref, K_query, pose, gt_pose, reason)
    if kpts0 is None or kpts1 is None:
        if title:
            _label(bottom, title, row=2)
        return bottom
    inl = epipolar_inliers(kpts0, kpts1, K_ref, K_query, pose, threshold_px) if pose is not None else None
    label = None
    if inl is not None and solver_inliers is not None:
        label = (
            f"{len(kpts0)} matches, {solver_inliers} solver inliers; green: {int(inl.sum())} within "
            f"{threshold_px:g} px of the pose"
        )
    top = draw_matches(ref_img, query_img, kpts0, kpts1, inl, label=label)
    if title:
        _label(top, title, row=1)
    w = max(top.shape[1], bottom.shape[1])
    pad = lambda im: np.pad(im, ((0, 0), (0, w - im.shape[1]), (0, 0)))  # noqa: E731
    return np.concatenate([pad(top), np.full((6, w, 3), 255, np.uint8), pad(bottom)], axis=0)


#: ``run --viz`` figures: JPEG at this quality, the long side at most this many pixels (about 150-300 KB a frame of
#: the dataset's 540x720 images, against 1.2 MB as full-size PNG).
FIGURE_QUALITY, FIGURE_MAX_SIDE = 85, 1280
#: Pictures embedded in an HTML report: smaller still, so eight worst frames and the plots stay well under 2 MB.
REPORT_QUALITY, REPORT_MAX_SIDE = 80, 960


def fit(rgb: np.ndarray, max_side: int | None) -> np.ndarray:
    """Scale an image down (area interpolation) to a longest side.

    Args:
        rgb: (H, W, 3) image.
        max_side: Longest side, pixels; None or 0 keeps the size.

    Returns:
        The image, unchanged when it is small enough.
    """
    h, w = rgb.shape[:2]
    if not max_side or max(h, w) <= max_side:
        return rgb
    s = max_side / max(h, w)
    return cv2.resize(rgb, (max(1, round(w * s)), max(1, round(h * s))), interpolation=cv2.INTER_AREA)


def png_bytes(rgb: np.ndarray) -> bytes:
    """Encode an image as PNG (to embed in a page).

    Args:
        rgb: (H, W, 3) uint8 RGB.

    Returns:
        The PNG bytes.

    Raises:
        ValueError: OpenCV could not encode it.
    """
    ok, buf = cv2.imencode(".png", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    if not ok:
        raise ValueError("could not encode the image as PNG")
    return buf.tobytes()


def jpeg_bytes(rgb: np.ndarray, max_side: int | None = REPORT_MAX_SIDE, quality: int = REPORT_QUALITY) -> bytes:
    """Encode an image as JPEG, scaled down to a longest side (to embed in a page).

    Args:
        rgb: (H, W, 3) uint8 RGB.
        max_side: Longest side, pixels; None keeps the size.
        quality: JPEG quality, 0-100.

    Returns:
        The JPEG bytes.

    Raises:
        ValueError: OpenCV could not encode it.
    """
    ok, buf = cv2.imencode(
        ".jpg", cv2.cvtColor(fit(rgb, max_side), cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, int(quality)]
    )
    if not ok:
        raise ValueError("could not encode the image as JPEG")
    return buf.tobytes()


def report_picture(data: bytes, max_side: int = REPORT_MAX_SIDE, quality: int = REPORT_QUALITY) -> bytes:
    """Make an encoded figure (PNG or JPEG, e.g. from ``run --viz``) fit for an HTML report.

    Args:
        data: The encoded image.
        max_side: Longest side, pixels.
        quality: JPEG quality, 0-100, when it is re-encoded.

    Returns:
        ``data`` itself when it is already a JPEG no larger than ``max_side``, else such a JPEG.

    Raises:
        ValueError: OpenCV cannot decode ``data``.
    """
    if data[:3] == b"\xff\xd8\xff":
        h, w = _jpeg_size(data)
        if max(h, w) <= max_side:
            return data
    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
    if img is None:
        raise ValueError("not an image OpenCV can decode")
    return jpeg_bytes(cv2.cvtColor(img, cv2.COLOR_BGR2RGB), max_side, quality)


def _jpeg_size(data: bytes) -> tuple[int, int]:
    """(height, width) from a JPEG's start-of-frame marker, without decoding it ((inf, inf) if not found)."""
    i = 2
    while i + 9 < len(data):
        if data[i] != 0xFF:
            break
        marker, length = data[i + 1], int.from_bytes(data[i + 2 : i + 4], "big")
        if 0xC0 <= marker <= 0xCF and marker not in (0xC4, 0xC8, 0xCC):
            return int.from_bytes(data[i + 5 : i + 7], "big"), int.from_bytes(data[i + 7 : i + 9], "big")
        i += 2 + length
    return (1 << 30, 1 << 30)


def save_png(path: os.PathLike | str, rgb: np.ndarray) -> Path:
    """Write an image, PNG or, for a ``.jpg`` name, JPEG; parent folders are created.

    Args:
        path: The file.
        rgb: (H, W, 3) uint8 RGB.

    Returns:
        ``path``.

    Raises:
        OSError: It could not be written (naming the file).
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    write_image(path, cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    return path


def save_figure(
    path: os.PathLike | str, rgb: np.ndarray, max_side: int = FIGURE_MAX_SIDE, quality: int = FIGURE_QUALITY
) -> Path:
    """Write a figure as JPEG scaled down to a longest side (``run --viz``: one a frame); folders are created.

    Args:
        path: The file.
        rgb: (H, W, 3) uint8 RGB.
        max_side: Longest side, pixels.
        quality: JPEG quality, 0-100.

    Returns:
        ``path``.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with naming(path):
        path.write_bytes(jpeg_bytes(rgb, max_side, quality))
    return path


def estimate_figure(
    ref_img: np.ndarray,
    query_img: np.ndarray,
    K_ref: Intrinsics,
    K_query: Intrinsics,
    estimate: Estimate,
    gt_pose: Pose | None = None,
    threshold_px: float = 3.0,
    title: str = "",
) -> np.ndarray:
    """``relocalization_figure`` of an ``Estimate``: its matches when the method has any, its pose or reason.

    Args:
        ref_img: (H, W, 3) uint8 RGB reference.
        query_img: (H', W', 3) uint8 RGB query.
        K_ref: Intrinsics of the reference.
        K_query: Intrinsics of the query.
        estimate: The method's estimate; its ``matches`` are drawn when present (a regression
            method's estimate has none: no empty matches panel).
        gt_pose: True pose, when known.
        threshold_px: Green matches are within this distance of the pose's epipolar lines, pixels.
        title: A line drawn on the figure.

    Returns:
        uint8 RGB image.
    """
    m = estimate.matches
    k0, k1 = (m.kpts0, m.kpts1) if m is not None else (None, None)
    return relocalization_figure(
        ref_img,
        query_img,
        K_ref,
        K_query,
        k0,
        k1,
        estimate.pose,
        gt_pose,
        threshold_px=threshold_px,
        title=title,
        reason=estimate.reason,
        solver_inliers=int(estimate.inliers) if estimate.pose is not None else None,
    )
