"""The record every method returns for one reference–query pair."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .geometry import Pose, rotation_angle_deg

__all__ = ["Estimate"]


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
        extras: Method-specific details (for example ``method``, the matches drawn by ``--viz``).
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
        """JSON-ready form of the record, ``extras`` left out.

        Returns:
            ``ok``, ``confidence``, ``inliers``, ``reason``, ``timings``, and with a pose ``q_wxyz``, ``t``,
                ``R`` and ``center`` as lists.
        """
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
