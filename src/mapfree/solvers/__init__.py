"""Pose solvers: matches + intrinsics + depth -> metric relative pose (``Estimate``).

    solver = mapfree.solvers.create("essential", ransac_threshold_px=2.0)   # or "emat", "pnp", "procrustes"
    est = solver.solve(matches, K_ref, K_query, depth_ref, depth_query)

``mickey`` is MicKey's probabilistic Procrustes, which runs on the ``mickey`` matcher's candidates.

Options default to the paper's values (preset ``paper``); preset ``best`` switches to our ranking
confidence (``confidence="score"``). Explicit options override the preset.
"""

from __future__ import annotations

from dataclasses import fields

from .base import Solver
from .confidence import CONFIDENCE_MODES
from .essential import EssentialOptions, EssentialSolver
from .mickey import MickeySolver, MickeySolverOptions
from .pnp import PnPOptions, PnPSolver
from .procrustes import ProcrustesOptions, ProcrustesSolver
from .scale import scale_vote, scale_vote_bruteforce

__all__ = [
    "Solver",
    "create",
    "available",
    "options_for",
    "option_names",
    "check_options",
    "PRESETS",
    "CONFIDENCE_MODES",
    "EssentialOptions",
    "EssentialSolver",
    "MickeySolver",
    "MickeySolverOptions",
    "PnPOptions",
    "PnPSolver",
    "ProcrustesOptions",
    "ProcrustesSolver",
    "scale_vote",
    "scale_vote_bruteforce",
]

SOLVERS: dict[str, tuple[type, type]] = {
    "essential": (EssentialSolver, EssentialOptions),
    "pnp": (PnPSolver, PnPOptions),
    "procrustes": (ProcrustesSolver, ProcrustesOptions),
    "mickey": (MickeySolver, MickeySolverOptions),  # on the mickey matcher's scored candidates only
}
ALIASES = {"emat": "essential", "ess": "essential", "essential-matrix": "essential", "3d3d": "procrustes"}
PRESETS: dict[str, dict] = {"paper": {}, "best": {"confidence": "score"}}


def _canonical(name: str) -> str:
    key = name.strip().lower().replace("_", "-")
    key = ALIASES.get(key, key)
    if key not in SOLVERS:
        raise KeyError(f"unknown solver {name!r}; available: {', '.join(available())}")
    return key


def available() -> list[str]:
    """Solver names a user can type (aliases included)."""
    return sorted(SOLVERS) + sorted(ALIASES)


def option_names(name: str) -> list[str]:
    """The options solver ``name`` accepts (the fields of its options dataclass)."""
    return [f.name for f in fields(SOLVERS[_canonical(name)][1])]


def check_options(name: str, values: dict, where: str = "", prefix: str = "") -> None:
    """Refuse an option solver ``name`` does not have or a value of the wrong type or range (``OptionError``)."""
    key = _canonical(name)
    SOLVERS[key][1].build(values, owner=f"solver {key!r}", where=where, prefix=prefix)


def options_for(name: str, preset: str = "paper", **options):
    """The options dataclass of solver ``name`` for a preset, with explicit overrides applied."""
    if preset not in PRESETS:
        raise KeyError(f"unknown preset {preset!r}; available: {', '.join(PRESETS)}")
    key = _canonical(name)
    return SOLVERS[key][1].build({**PRESETS[preset], **options}, owner=f"solver {key!r}")


def create(name: str, preset: str = "paper", **options) -> Solver:
    """A solver by name (``essential``/``emat``, ``pnp``, ``procrustes``), paper defaults unless overridden."""
    return SOLVERS[_canonical(name)][0](options_for(name, preset, **options))
