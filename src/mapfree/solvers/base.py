"""The solver interface: matches + intrinsics + depth -> a metric relative pose with a confidence."""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import ClassVar, Literal

import numpy as np

from ..estimate import Estimate
from ..geometry import Intrinsics
from ..matching.base import Matches
from ..options import Options

__all__ = ["Solver", "SolverOptions", "DepthNeed", "BOTH_DEPTHS"]

#: Which image a solver needs a depth map of: the reference (``"ref"``) or the query (``"query"``).
DepthNeed = Literal["ref", "query"]
BOTH_DEPTHS: tuple[DepthNeed, ...] = ("ref", "query")


class SolverOptions(Options):
    """Base of the solvers' options dataclasses: each chooses which confidence its estimates report.

    Attributes:
        confidence: ``"inliers"`` (the paper's inlier count) or ``"score"`` (our ranking confidence); see
            ``mapfree.solvers.confidence``.
    """

    confidence: str


class Solver(ABC):
    """A relative-pose solver.

    ``solve`` returns the pose of the query camera relative to the reference camera (``X_query = R X_ref + t``,
    metres), or ``Estimate.failure(reason)``; it never raises on bad input and never returns NaN.

    Attributes:
        name: The registry name (``essential``, ``pnp``, ``procrustes``, ``mickey``).
        depth_needs: The images it needs a depth map of (``"ref"``, ``"query"``): Ess.Mat and Procrustes both,
            PnP the reference's, MicKey's solver none (its matches carry their keypoints' depths). A metric
            relocalizer refuses a pair up front when a needed map is missing.
    """

    name: ClassVar[str] = ""
    depth_needs: ClassVar[tuple[DepthNeed, ...]] = BOTH_DEPTHS

    @abstractmethod
    def solve(
        self,
        matches: Matches,
        K_ref: Intrinsics,
        K_query: Intrinsics,
        depth_ref: np.ndarray | None,
        depth_query: np.ndarray | None = None,
    ) -> Estimate:
        """The query camera's pose relative to the reference camera.

        Args:
            matches: ``kpts0`` reference pixels, ``kpts1`` query pixels, (N, 2) each.
            K_ref: Intrinsics of the reference image.
            K_query: Intrinsics of the query image.
            depth_ref: (H, W) metres at the reference's size (0 = invalid), or None.
            depth_query: (H, W) metres at the query's size, or None.

        Returns:
            The estimate (``pose`` None with a ``reason`` when there is none), with ``timings`` in seconds.
        """

    @property
    def confidence_mode(self) -> str:
        """Which confidence its estimates report (``"inliers"`` or ``"score"``)."""
        return "inliers"
