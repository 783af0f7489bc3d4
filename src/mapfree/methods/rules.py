"""What a method can run on: the depth its solver needs (``depth_free_problem``, ``query_depth_fallback``) and
options its matcher and solver have (``check_options``)."""

from __future__ import annotations

from dataclasses import replace

from ..depth import PAIR_MODELS
from .base import Method

__all__ = ["QUERY_DEPTH_SOLVERS", "LIFTING_SOLVERS", "query_depth_fallback", "depth_free_problem", "check_options"]

#: Solvers that need a depth map of the query too; without one a method falls back to PnP (``query_depth_fallback``).
QUERY_DEPTH_SOLVERS = ("essential", "procrustes")
#: Solvers that lift the reference's pixels to 3D with its depth: without any depth map they give no pose.
LIFTING_SOLVERS = ("pnp", "procrustes")


def query_depth_fallback(method: Method) -> Method:
    """The method to run for a query without a depth map: ``method`` itself, or its PnP twin (reference depth
    only, at the reference's metric scale) when its solver would need the query's depth. The service and
    ``mapfree relocalize`` both answer a plain photo this way (the default ``best-offline`` is Procrustes)."""
    # a pair network's query depth comes from the network, with the pair: no fallback
    if (
        method.kind == "matching"
        and method.depth not in ("none", *PAIR_MODELS)
        and method.solver in QUERY_DEPTH_SOLVERS
    ):
        return replace(method, solver="pnp", solver_opts={}, name=f"{method.name}+pnp")
    return method


def depth_free_problem(method: Method) -> str | None:
    """Why ``method`` cannot estimate anything from images alone (PnP or Procrustes with depth ``none``: they run
    only on depth maps handed to them with the images, as the service's anchors do), else None."""
    if method.kind == "matching" and method.matcher != "mickey" and "mickey" in (method.depth, method.solver):
        return (
            f"method {method.name!r}: the mickey depth and solver read the keypoints of the mickey matcher, "
            f"not {method.matcher}'s: use the mickey matcher (e.g. mickey or mickey_pnp_mickey)"
        )
    if method.kind != "matching" or method.depth != "none" or method.solver not in LIFTING_SOLVERS:
        return None
    where = "the reference" if method.solver == "pnp" else "both images"
    return (
        f"method {method.name!r} has no depth source, and its {method.solver} solver needs a depth map of "
        f"{where}: choose a depth suffix or network (e.g. {method.matcher}_{method.solver}_sensor) or Ess.Mat "
        f"without depth ({method.matcher}_emat_none, up to scale)"
    )


def check_options(method: Method, where: str = "") -> None:
    """Refuse a matcher or solver option the component does not have (suggesting the nearest known one) or a value
    of the wrong type or range, before anything is built: the component's own options dataclass checks them, as
    it does for the command line and for Python (``mapfree.options``). ``where``: the file they came from."""
    if method.kind != "matching":
        return
    from .. import matching, solvers

    matching.check_options(method.matcher, method.matcher_opts, where=where or method.name, prefix="matcher_opts.")
    solvers.check_options(method.solver, method.solver_opts, where=where or method.name, prefix="solver_opts.")
