"""Judging a confidence that claims to be a probability: expected calibration error, Brier score, reliability
bins and the precision of the frames a threshold accepts."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["ACCEPT_LEVELS", "Reliability", "reliability", "reliability_from_dict", "is_probability"]

#: Thresholds at which the precision of the accepted frames is reported.
ACCEPT_LEVELS = (0.5, 0.8, 0.9)


def is_probability(p: np.ndarray) -> bool:
    """Whether confidences can be read as probabilities: every finite one in [0, 1], at least one.

    Args:
        p: (N,) confidences; NaN for frames without an estimate.

    Returns:
        True when they are probabilities.
    """
    p = np.asarray(p, dtype=np.float64)
    p = p[np.isfinite(p)]
    return bool(len(p) and np.all((p >= 0) & (p <= 1)))


@dataclass
class Reliability:
    """How well probabilities match the outcomes (all on the frames with a probability).

    Attributes:
        frames: Frames judged.
        ece: Expected calibration error over ``bins`` equal-width bins: the frames-weighted mean of
            ``|mean p - fraction right|``.
        brier: Mean squared difference between the probability and the outcome (0 or 1).
        bin_edges: (bins + 1,) edges in [0, 1].
        bin_count: (bins,) frames per bin.
        bin_p: (bins,) mean probability per bin (NaN when empty).
        bin_right: (bins,) fraction right per bin (NaN when empty).
        precision: ``{level: fraction right among the frames with p >= level}`` (None when none is accepted).
        accepted: ``{level: frames with p >= level}``.
    """

    frames: int
    ece: float
    brier: float
    bin_edges: np.ndarray
    bin_count: np.ndarray
    bin_p: np.ndarray
    bin_right: np.ndarray
    precision: dict[float, float | None]
    accepted: dict[float, int]

    def to_dict(self) -> dict:
        """JSON-ready form (NaN becomes None).

        Returns:
            Scalars, per-level precision keyed ``"0.9"`` and the bins as lists.
        """
        clean = lambda a: [None if not np.isfinite(v) else float(v) for v in a]  # noqa: E731
        return {
            "frames": self.frames,
            "ece": self.ece,
            "brier": self.brier,
            "precision": {f"{k:g}": v for k, v in self.precision.items()},
            "accepted": {f"{k:g}": v for k, v in self.accepted.items()},
            "bins": {
                "edges": clean(self.bin_edges),
                "count": [int(c) for c in self.bin_count],
                "p": clean(self.bin_p),
                "right": clean(self.bin_right),
            },
        }


def reliability_from_dict(d: dict) -> Reliability:
    """A ``Reliability`` from its ``to_dict()`` (a calibration file's held-out figures).

    Args:
        d: The dict.

    Returns:
        The figures.
    """
    nan = lambda a: np.array([np.nan if v is None else v for v in a], dtype=np.float64)  # noqa: E731
    b = d["bins"]
    return Reliability(
        int(d["frames"]),
        float(d["ece"]),
        float(d["brier"]),
        nan(b["edges"]),
        np.asarray(b["count"], dtype=np.int64),
        nan(b["p"]),
        nan(b["right"]),
        {float(k): v for k, v in d["precision"].items()},
        {float(k): int(v) for k, v in d["accepted"].items()},
    )


def reliability(p: np.ndarray, right: np.ndarray, bins: int = 10) -> Reliability:
    """ECE, Brier score, reliability bins and precision at ``ACCEPT_LEVELS`` of probabilities against outcomes.

    Args:
        p: (N,) probabilities in [0, 1].
        right: (N,) bool, whether each frame was right.
        bins: Equal-width bins of the ECE and the diagram.

    Returns:
        The figures.

    Raises:
        ValueError: No frame, mismatched lengths or a probability outside [0, 1].
    """
    p = np.asarray(p, dtype=np.float64).reshape(-1)
    y = np.asarray(right, dtype=bool).reshape(-1)
    if len(p) != len(y) or len(p) == 0:
        raise ValueError(f"need as many outcomes as probabilities, at least one (got {len(p)} and {len(y)})")
    if not is_probability(p) or not np.all(np.isfinite(p)):
        raise ValueError("probabilities must be finite and in [0, 1]")
    edges = np.linspace(0.0, 1.0, bins + 1)
    idx = np.clip(np.digitize(p, edges[1:-1], right=False), 0, bins - 1)
    count = np.bincount(idx, minlength=bins)
    with np.errstate(invalid="ignore", divide="ignore"):
        bin_p = np.bincount(idx, weights=p, minlength=bins) / count
        bin_right = np.bincount(idx, weights=y.astype(float), minlength=bins) / count
    filled = count > 0
    ece = float(np.sum(count[filled] * np.abs(bin_p[filled] - bin_right[filled])) / len(p))
    brier = float(np.mean((p - y) ** 2))
    precision: dict[float, float | None] = {}
    accepted: dict[float, int] = {}
    for level in ACCEPT_LEVELS:
        keep = p >= level
        accepted[level] = int(keep.sum())
        precision[level] = float(y[keep].mean()) if keep.any() else None
    return Reliability(len(p), ece, brier, edges, count, bin_p, bin_right, precision, accepted)
