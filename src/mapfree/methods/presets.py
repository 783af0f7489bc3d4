"""The registered presets: the best offline methods, the two-view networks' (MASt3R, DUSt3R, DUNE-MASt3R) and
MicKey's (``register_presets``, run once when ``mapfree.methods`` is imported)."""

from __future__ import annotations

from dataclasses import replace

from ..mast3r.published import DUNE_KINDS
from ..matching import needs as matcher_needs
from ..method_names import BEST_OFFLINE, BEST_OFFLINE_REFERENCE_DEPTH
from .base import Method
from .names import parse_name, preset_name
from .registry import register

__all__ = ["register_presets"]


def register_presets() -> None:
    """Register the built-in presets (``get`` finds them by name)."""
    _register_builtins()
    _register_two_view_presets()
    _register_mickey_presets()


def _register_builtins() -> None:
    # Chosen by measurement on realmini-dev val (docs/benchmarks.md): the highest AUC @ VCRE < 90px among
    # the offline presets, on the scored frames and on all frames, with the ranking confidence.
    best = parse_name("xfeat_procrustes_sensor")
    pnp = parse_name("xfeat_pnp_sensor")
    assert best is not None and pnp is not None
    register(
        replace(
            best,
            name=BEST_OFFLINE,
            solver_opts={**best.solver_opts, "confidence": "score"},
            description="best offline preset: XFeat, Procrustes (3D-3D RANSAC), ranking confidence; "
            "needs depth for both images (files:sensor; swap with best-offline@SUFFIX)",
        )
    )
    register(
        replace(
            pnp,
            name=BEST_OFFLINE_REFERENCE_DEPTH,
            solver_opts={**pnp.solver_opts, "confidence": "score"},
            description="best offline preset when only the reference has depth: XFeat, PnP, "
            "ranking confidence (files:sensor at the reference)",
        )
    )


def _register_two_view_presets() -> None:
    # MASt3R / DUSt3R with their own pointmaps as depth: no depth files, one forward pass per pair (PnP).
    how = {
        "pnp": "PnP on the reference's depth (one forward pass per pair)",
        "emat": "Ess.Mat scaled by both images' depth (a second, symmetric decoder pass for the query's depth)",
        "procrustes": "3D-3D Procrustes on both images' depth (a second, symmetric decoder pass)",
    }
    for net in ("mast3r", "dust3r", *DUNE_KINDS):
        doc = "docs/dune-mast3r.md" if net in DUNE_KINDS else "docs/mast3r.md"
        for solver in how:
            m = parse_name(preset_name(net, solver, net))
            assert m is not None
            register(
                replace(
                    m,
                    description=f"{net} matches and {net} metric depth, {how[solver]}; needs "
                    f"{matcher_needs(net)} ({doc})",
                )
            )


def _register_mickey_presets() -> None:
    # MicKey: its own solver on its scored candidates (the public pipeline), and our solvers on its mutual
    # matches with each keypoint's metric depth. Procrustes takes MicKey's inlier threshold (0.15 m; not tuned).
    needs = f"needs {matcher_needs('mickey')} (docs/mickey.md)"
    register(
        Method(
            name="mickey",
            matcher="mickey",
            depth="mickey",
            solver="mickey",
            description=f"MicKey end to end: metric keypoints, dual-softmax matching, its probabilistic "
            f"Procrustes RANSAC and confidence (soft inlier count); {needs}",
        )
    )
    how = {
        "pnp": ("PnP on the reference keypoints' depth", {}),
        "emat": ("Ess.Mat scaled by the keypoints' depth", {}),
        "procrustes": ("3D-3D Procrustes on both images' keypoint depths, 0.15 m", {"inlier_threshold": 0.15}),
    }
    for solver, (what, opts) in how.items():
        m = parse_name(preset_name("mickey", solver, "mickey"))
        assert m is not None
        register(
            replace(m, solver_opts={**m.solver_opts, **opts}, description=f"mickey mutual matches, {what}; {needs}")
        )
