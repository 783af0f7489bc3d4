"""The solver interface: matches + intrinsics + depth -> a metric relative pose with a confidence."""

from __future__ import annotations

from typing import Protocol, runtime_checkable

import numpy as np

from ..estimate import Estimate
from ..geometry import Intrinsics
from ..matching.base import Matches

__all__ = ["Solver"]


@runtime_checkable
class Solver(Protocol):
    """``solve`` returns the pose of the query camera relative to the reference camera
    (``X_query = R X_ref + t``), or ``Estimate.failure(reason)``. It never returns NaN.
    ``matches.kpts0`` are reference pixels, ``kpts1`` query pixels; depths may be None.
    """

    name: str

    def solve(
        self,
        matches: Matches,
        K_ref: Intrinsics,
        K_query: Intrinsics,
        depth_ref: np.ndarray | None,
        depth_query: np.ndarray | None,
    ) -> Estimate: ...
