"""The record every method returns for one reference–query pair."""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field, fields
from typing import Protocol

import numpy as np

from .geometry import Pose, rotation_angle_deg

__all__ = ["Estimate", "Signals", "PixelMatches"]


class PixelMatches(Protocol):
    """Corresponding pixels of the reference and the query, as a matcher found them (``mapfree.matching.Matches``).

    Attributes:
        kpts0: (N, 2) pixels in the reference.
        kpts1: (N, 2) pixels in the query.
    """

    kpts0: np.ndarray
    kpts1: np.ndarray

    def __len__(self) -> int: ...


@dataclass
class Signals:
    """Per-frame evidence of how trustworthy an estimate is, as its method measured it (None: not measured).

    A calibration (``mapfree calibrate``) turns these into the probability that the pose is right.

    Attributes:
        n_matches: Correspondences handed to the solver.
        n_inliers: Correspondences the final pose agrees with.
        inlier_ratio: ``n_inliers`` over the matches the solver could use, in [0, 1].
        score: The solver's ranking score (``mapfree.solvers.confidence``), >= 0.
        residual: Mean or median residual of the inliers under the final pose: pixels (PnP reprojection) or
            metres (3-D alignment RMSE, Ess.Mat scale spread).
        depth_valid_fraction: Fraction of the matches with valid depth where the solver needs it, in [0, 1].
        scale_ratio: Ratio of two independent metric scale estimates of the same points (the query's depth
            against the reference's depth moved by the pose), 1 when they agree; > 0.
        learned_confidence: A network's own confidence in its matches or pose (MASt3R/MicKey mean match
            confidence, a regression network's certainty), >= 0.
    """

    n_matches: int | None = None
    n_inliers: int | None = None
    inlier_ratio: float | None = None
    score: float | None = None
    residual: float | None = None
    depth_valid_fraction: float | None = None
    scale_ratio: float | None = None
    learned_confidence: float | None = None

    def __post_init__(self) -> None:
        for f in fields(self):  # a non-finite measurement is no measurement
            v = getattr(self, f.name)
            if v is not None and not math.isfinite(float(v)):
                setattr(self, f.name, None)

    def to_dict(self) -> dict[str, float]:
        """The measured signals (None left out), as floats.

        Returns:
            ``{name: value}``, JSON-ready.
        """
        return {k: float(v) for k, v in asdict(self).items() if v is not None}

    @classmethod
    def from_dict(cls, d: dict) -> Signals:
        """The signals of ``to_dict`` (unknown keys ignored).

        Args:
            d: ``{name: value}``.

        Returns:
            The signals.
        """
        names = {f.name for f in fields(cls)}
        return cls(**{k: v for k, v in d.items() if k in names and v is not None})


@dataclass(repr=False)
class Estimate:
    """A metric relative pose (query camera w.r.t. the reference camera) with a confidence.

    ``pose is None`` means "no estimate" and ``reason`` says why; a non-finite pose becomes "no estimate"
    and a non-finite or negative confidence becomes 0.

    Attributes:
        pose: Transform from the reference camera frame to the query camera frame (metres), or None.
        confidence: Finite, >= 0; higher means more trusted (the benchmark's AUC ranks by it).
        inliers: Correspondences the solver kept (0 for methods without any).
        reason: Why there is no estimate; empty when there is one.
        timings: Seconds per stage, by stage name.
        extras: Method-specific details (for example ``method``, alternative confidences, ``num_matches``); its
            finite numbers are journaled.
        signals: The per-frame evidence a calibration reads (``Signals``).
        p_correct: Calibrated probability that the pose is within 90 px of reprojection error (VCRE), in [0, 1],
            or None without a calibration (``mapfree.calibration``).
        stage: Which stage of a cascade answered (its method name); empty otherwise.
        matches: The correspondences the pose was solved from (drawn by ``--viz``), in the pixels of the views
            the method was given; None for methods without any (regression) or a failure before matching.
        photo: Which of an anchor's photos answered (its position among them), or None for a one-reference
            localizer.
    """

    pose: Pose | None
    confidence: float = 0.0
    inliers: int = 0
    reason: str = ""
    timings: dict[str, float] = field(default_factory=dict)
    extras: dict = field(default_factory=dict)
    signals: Signals = field(default_factory=Signals)
    p_correct: float | None = None
    stage: str = ""
    matches: PixelMatches | None = None
    photo: int | None = None

    def __post_init__(self) -> None:
        if self.pose is not None and not self.pose.is_finite():
            self.pose, self.reason = None, self.reason or "non-finite pose"
        c = float(self.confidence)
        self.confidence = c if np.isfinite(c) and c > 0 else 0.0
        if self.p_correct is not None:
            p = float(self.p_correct)
            self.p_correct = min(max(p, 0.0), 1.0) if math.isfinite(p) else None

    def __repr__(self) -> str:
        """One line: the pose as rotation angle and translation, or the reason; never the arrays of ``extras``."""
        if self.pose is None:
            return f"Estimate(no estimate: {self.reason or 'no reason given'})"

        rot = rotation_angle_deg(self.pose.R, np.eye(3))
        t = ", ".join(f"{v:.3f}" for v in self.pose.t)
        return f"Estimate(rotation {rot:.2f} deg, t=({t}) m, confidence {self.confidence:.3g}, inliers {self.inliers})"

    @classmethod
    def failure(cls, reason: str, **timings: float) -> Estimate:
        """A "no estimate" record.

        Args:
            reason: Why there is no pose, in one line.
            **timings: Seconds spent per stage before giving up.

        Returns:
            An estimate with ``pose`` None and confidence 0.
        """
        return cls(None, 0.0, 0, reason, dict(timings))

    @property
    def ok(self) -> bool:
        return self.pose is not None

    def to_dict(self) -> dict:
        """JSON-ready form of the record, ``extras``, ``matches`` and ``photo`` left out.

        Returns:
            ``ok``, ``confidence``, ``inliers``, ``reason``, ``timings``, ``signals``, ``p_correct`` and ``stage``
                where set, and with a pose ``q_wxyz``, ``t``,
                ``R`` and ``center`` as lists.
        """
        d: dict = {
            "ok": self.ok,
            "confidence": self.confidence,
            "inliers": int(self.inliers),
            "reason": self.reason,
            "timings": {k: float(v) for k, v in self.timings.items()},
            "signals": self.signals.to_dict(),
        }
        if self.p_correct is not None:
            d["p_correct"] = self.p_correct
        if self.stage:
            d["stage"] = self.stage
        if self.pose is not None:
            q, t = self.pose.qt()
            d.update(q_wxyz=q.tolist(), t=t.tolist(), R=self.pose.R.tolist(), center=self.pose.center.tolist())
        return d
