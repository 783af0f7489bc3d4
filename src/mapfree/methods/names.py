"""Preset names, ``{matcher}_{solver}_{depth}``: the matchers and solvers they may name and the paper's settings
of each row."""

from __future__ import annotations

from typing import Any

from ..depth import PAIR_MODELS
from ..matching import needs as matcher_needs
from .base import Method, depth_spec

__all__ = ["MATCHERS", "OFFLINE_MATCHERS", "SOLVERS", "PAPER_THRESHOLD_PX", "preset_name", "parse_name"]

#: Matchers whose presets exist; ``OFFLINE_MATCHERS`` run without downloading weights.
MATCHERS: tuple[str, ...] = (
    "sift",
    "xfeat",
    "xfeat-star",
    "xfeat-lighterglue",
    "aliked-lightglue",
    "disk-lightglue",
    "loftr",
    "superpoint-lightglue",
    "superglue",
    "superglue-indoor",
    "efficientloftr",
)
OFFLINE_MATCHERS = MATCHERS[:6]
MATCHERS += PAIR_MODELS  # networks with their own depth; weights are the user's download (docs/mast3r.md, mickey.md)
#: Matchers whose presets' descriptions say what they need (``matching.needs``): weights the user places.
_NEEDS_IN_DESCRIPTION = PAIR_MODELS
#: Solver token in a preset name -> solver registry name.
SOLVERS = {"emat": "essential", "essential": "essential", "pnp": "pnp", "procrustes": "procrustes"}
#: Ess.Mat RANSAC threshold (pixels) of the paper's rows: 3 px for SIFT, 2 px for learned matchers.
PAPER_THRESHOLD_PX = {"sift": 3.0}
_LEARNED_THRESHOLD_PX = 2.0


def preset_name(matcher: str, solver: str, depth: str) -> str:
    return f"{matcher}_{solver}_{depth}"


def parse_name(name: str) -> Method | None:
    """``{matcher}_{solver}_{depth}`` -> the paper's configuration of that row, or None if not of that form."""
    parts = name.split("_")
    if len(parts) < 3:
        return None
    matcher, solver_tok, depth_tok = parts[0], parts[1], "_".join(parts[2:])
    if matcher not in MATCHERS or solver_tok not in SOLVERS or not depth_tok:
        return None
    threshold = PAPER_THRESHOLD_PX.get(matcher, _LEARNED_THRESHOLD_PX)
    solver = SOLVERS[solver_tok]
    # Only Ess.Mat's threshold depends on the matcher in the paper; PnP uses 3 px throughout.
    solver_opts: dict[str, Any] = {"ransac_threshold_px": threshold} if solver == "essential" else {}
    return Method(
        name=name,
        matcher=matcher,
        depth=depth_spec(depth_tok),
        solver=solver,
        solver_opts=solver_opts,
        description=f"{matcher} matches, {solver} solver, depth {depth_tok} (paper settings"
        + (f", {threshold:g} px)" if solver == "essential" else ")")
        + (f"; needs {matcher_needs(matcher)}" if matcher in _NEEDS_IN_DESCRIPTION else ""),
    )
