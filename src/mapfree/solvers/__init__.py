"""Pose solvers: matches + intrinsics + depth -> metric relative pose (``Estimate``).

    solver = mapfree.solvers.create("essential", ransac_threshold_px=2.0)   # or "emat", "pnp", "procrustes"
    est = solver.solve(matches, K_ref, K_query, depth_ref, depth_query)

``mickey`` is MicKey's probabilistic Procrustes, which runs on the ``mickey`` matcher's candidates.

Options default to the paper's values (preset ``paper``); preset ``best`` switches to our ranking
confidence (``confidence="score"``). Explicit options override the preset.
"""

from __future__ import annotations

from dataclasses import fields
from typing import Any

from .base import BOTH_DEPTHS, DepthNeed, Solver, SolverOptions
from .common import GuardedSolver
from .confidence import CONFIDENCE_MODES
from .essential import EssentialOptions, EssentialSolver
from .mickey import MickeySolver, MickeySolverOptions
from .pnp import PnPOptions, PnPSolver
from .procrustes import ProcrustesOptions, ProcrustesSolver
from .scale import scale_vote, scale_vote_bruteforce

__all__ = [
    "Solver",
    "SolverOptions",
    "DepthNeed",
    "BOTH_DEPTHS",
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

SOLVERS: dict[str, tuple[type[GuardedSolver[Any]], type[SolverOptions]]] = {
    "essential": (EssentialSolver, EssentialOptions),
    "pnp": (PnPSolver, PnPOptions),
    "procrustes": (ProcrustesSolver, ProcrustesOptions),
    "mickey": (MickeySolver, MickeySolverOptions),  # on the mickey matcher's scored candidates only
}
ALIASES = {"emat": "essential", "ess": "essential", "essential-matrix": "essential", "3d3d": "procrustes"}
PRESETS: dict[str, dict[str, Any]] = {"paper": {}, "best": {"confidence": "score"}}


def _canonical(name: str) -> str:
    key = name.strip().lower().replace("_", "-")
    key = ALIASES.get(key, key)
    if key not in SOLVERS:
        raise KeyError(f"unknown solver {name!r}; available: {', '.join(available())}")
    return key


def available() -> list[str]:
    """Solver names a user can type (aliases included).

    Returns:
        The registry names, then the aliases.
    """
    return sorted(SOLVERS) + sorted(ALIASES)


def option_names(name: str) -> list[str]:
    """The options solver ``name`` accepts.

    Args:
        name: A solver name or alias.

    Returns:
        The fields of its options dataclass.
    """
    return [f.name for f in fields(SOLVERS[_canonical(name)][1])]


def check_options(name: str, values: dict[str, Any], where: str = "", prefix: str = "") -> None:
    """Refuse an option solver ``name`` does not have or a value of the wrong type or range.

    Args:
        name: A solver name or alias.
        values: Option values (``{"ransac_threshold_px": 2.0}``).
        where: The file they came from, for the message.
        prefix: Put before each key in the message (``solver_opts.``).

    Raises:
        OptionError: One line naming the key and what was expected.
        KeyError: An unknown solver.
    """
    key = _canonical(name)
    SOLVERS[key][1].build(values, owner=f"solver {key!r}", where=where, prefix=prefix)


def options_for(name: str, preset: str = "paper", **options: Any) -> SolverOptions:
    """The options of solver ``name`` for a preset, with explicit overrides applied.

    Args:
        name: A solver name or alias.
        preset: ``paper`` (the paper's values) or ``best`` (ranking confidence).
        **options: Overrides of single options.

    Returns:
        The solver's options dataclass.
    """
    if preset not in PRESETS:
        raise KeyError(f"unknown preset {preset!r}; available: {', '.join(PRESETS)}")
    key = _canonical(name)
    return SOLVERS[key][1].build({**PRESETS[preset], **options}, owner=f"solver {key!r}")


def create(name: str, preset: str = "paper", **options: Any) -> Solver:
    """A solver by name, paper defaults unless overridden.

    Args:
        name: ``essential`` (``emat``), ``pnp``, ``procrustes`` or ``mickey``.
        preset: ``paper`` or ``best`` (see ``PRESETS``).
        **options: Overrides of single options (``ransac_threshold_px=2.0``).

    Returns:
        The solver; its ``depth_needs`` say which depth maps it lifts.
    """
    return SOLVERS[_canonical(name)][0](options_for(name, preset, **options))
