"""The method record (``Method``: what to run for a reference-query pair) and the table of method kinds that
build it (``KINDS``, ``register_kind``, ``factory``)."""

from __future__ import annotations

import importlib
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, replace
from typing import Any, cast

from ..depth import HUB_MODELS, PAIR_MODELS

__all__ = ["Method", "KINDS", "DEPTH_ALIASES", "register_kind", "factory", "depth_spec"]

#: Depth tokens that are not a file suffix.
DEPTH_ALIASES = {"none": "none", **{net: net for net in PAIR_MODELS}}


#: Method kind -> ``"module:function"`` building its localizer from a ``Method``, imported at the first build.
KINDS: dict[str, str] = {
    "matching": "mapfree.relocalize.pipeline:build_matching",
    "regression": "mapfree.rpr:build_from_method",
    "cascade": "mapfree.relocalize.cascade:build_cascade",
}
_FACTORIES: dict[str, Callable[[Method], Any]] = {}  # resolved (or ``register_kind``-ed) factories


@dataclass(frozen=True)
class Method:
    """What to run for one reference–query pair: a frozen, picklable record (it travels to worker processes and
    Ray workers as it is). ``kind="matching"`` uses matcher/depth/solver; other kinds are built by their factory
    (``KINDS``) from ``options``.

    Attributes:
        name: What the user typed (a preset, a YAML config's name, ``NAME@DEPTH``).
        kind: ``matching`` or ``regression`` (or a kind added with ``register_kind``).
        matcher: A matcher name (``mapfree.matching.names()``).
        matcher_opts: The matcher's option overrides.
        depth: A depth spec (``files:SUFFIX``, ``none``, a network name, ``hf:ID``).
        solver: A solver name (``essential``, ``pnp``, ``procrustes``, ``mickey``).
        solver_opts: The solver's option overrides.
        options: Options of other kinds (``checkpoint``, ``config``) and of the run (``references``).
        description: One line for listings.
    """

    name: str
    kind: str = "matching"
    matcher: str = "sift"
    matcher_opts: dict[str, Any] = field(default_factory=dict)
    depth: str = "none"
    solver: str = "essential"
    solver_opts: dict[str, Any] = field(default_factory=dict)
    options: dict[str, Any] = field(default_factory=dict)
    description: str = ""

    def to_dict(self) -> dict[str, Any]:
        """The fields as a plain dict (what a run's journal header records).

        Returns:
            ``{"name": …, "kind": …, …}`` in field order, the option dicts copied.
        """
        return asdict(self)

    def with_depth(self, depth: str) -> Method:
        """The same method with another depth.

        Args:
            depth: A depth spec (``files:SUFFIX``, ``none``, ``hf:…``), a network name or a bare file suffix.

        Returns:
            The method named ``NAME@DEPTH``.
        """
        spec = depth_spec(depth)
        return replace(self, depth=spec, name=f"{self.name}@{depth}")

    @property
    def metric(self) -> bool:
        """Whether its poses are metric (anything but a matching method without depth)."""
        return self.kind != "matching" or self.depth != "none"

    @property
    def networks(self) -> bool:
        """Whether running it evaluates neural networks (a learned matcher, a depth network, a regression
        model): such a method asks a cluster for a GPU per worker (``mapfree run --ray``)."""
        classical_depth = self.depth == "none" or self.depth.startswith("files:")
        return self.kind != "matching" or self.matcher.strip().lower() != "sift" or not classical_depth

    def build(self) -> Any:
        """The method's localizer (a ``mapfree.localizer.Localizer``: ``set_reference``, ``localize``,
        ``localize_many``, ``relocalize``), built by its kind's factory.

        Ess.Mat without depth (``*_emat_none``) returns its up-to-scale pose, flagged ``scale_free``, instead of
        failing on the missing depth: the direction is all such a method can give (unless ``solver_opts`` say).

        Returns:
            The localizer.

        Raises:
            KeyError: An unknown kind.
        """
        m = self
        if self.kind == "matching" and self.depth == "none" and self.solver == "essential":
            m = replace(self, solver_opts={"allow_unscaled": True, **self.solver_opts})
        return factory(m.kind)(m)


def register_kind(kind: str, build: Callable[[Method], Any]) -> None:
    """Add a method kind of your own (the built-in ones are the ``KINDS`` table).

    Args:
        kind: The kind's name (``Method.kind``).
        build: Builds a method of that kind's localizer.
    """
    _FACTORIES[kind] = build


def factory(kind: str) -> Callable[[Method], Any]:
    """How methods of ``kind`` are built: its ``KINDS`` entry, imported on first use, or a ``register_kind``-ed one.

    Args:
        kind: ``matching``, ``regression`` or a registered kind.

    Returns:
        The factory (``Method`` -> localizer).

    Raises:
        KeyError: An unknown kind.
    """
    if kind not in _FACTORIES:
        if kind not in KINDS:
            raise KeyError(f"unknown method kind {kind!r} (known: {', '.join(sorted({*KINDS, *_FACTORIES}))})")
        module, function = KINDS[kind].split(":")
        _FACTORIES[kind] = cast(Callable[[Method], Any], getattr(importlib.import_module(module), function))
    return _FACTORIES[kind]


def depth_spec(token: str) -> str:
    """A depth token of a preset name -> a depth spec: a spec as is, a network's short name, else a file suffix."""
    if ":" in token or token == "none":
        return token
    if token in DEPTH_ALIASES:
        return DEPTH_ALIASES[token]
    return token if token in HUB_MODELS else f"files:{token}"
