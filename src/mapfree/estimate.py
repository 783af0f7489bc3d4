"""The record every method returns for one reference–query pair."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .geometry import Pose, rotation_angle_deg

__all__ = ["Estimate"]


@dataclass(repr=False)
class Estimate:
    """A metric relative pose (query camera w.r.t. the reference camera) with a confidence.

    ``pose is None`` means "no estimate" and ``reason`` says why. Confidence is finite and >= 0.
    """

    pose: Pose | None
    confidence: float = 0.0
    inliers: int = 0
    reason: str = ""
    timings: dict[str, float] = field(default_factory=dict)
    extras: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.pose is not None and not self.pose.is_finite():
            self.pose, self.reason = None, self.reason or "non-finite pose"
        c = float(self.confidence)
        self.confidence = c if np.isfinite(c) and c > 0 else 0.0

    def __repr__(self) -> str:
        """One line: the pose as rotation angle and translation, or the reason; never the arrays of ``extras``."""
        if self.pose is None:
            return f"Estimate(no estimate: {self.reason or 'no reason given'})"

        rot = rotation_angle_deg(self.pose.R, np.eye(3))
        t = ", ".join(f"{v:.3f}" for v in self.pose.t)
        return f"Estimate(rotation {rot:.2f} deg, t=({t}) m, confidence {self.confidence:.3g}, inliers {self.inliers})"

    @classmethod
    def failure(cls, reason: str, **timings: float) -> Estimate:
        return cls(None, 0.0, 0, reason, dict(timings))

    @property
    def ok(self) -> bool:
        return self.pose is not None

    def to_dict(self) -> dict:
        d: dict = {
            "ok": self.ok,
            "confidence": self.confidence,
            "inliers": int(self.inliers),
            "reason": self.reason,
            "timings": {k: float(v) for k, v in self.timings.items()},
        }
        if self.pose is not None:
            q, t = self.pose.qt()
            d.update(q_wxyz=q.tolist(), t=t.tolist(), R=self.pose.R.tolist(), center=self.pose.center.tolist())
        return d
