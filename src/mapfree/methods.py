"""The method registry: a method is a string a user can type.

A method is either a *matching* pipeline (matcher + options, depth spec, solver + options) or another kind
(``regression``). ``KINDS`` names each kind's factory as ``"module:function"``, imported only when a method of that
kind is first built. Names of the form ``{matcher}_{solver}_{depth}`` (``sift_emat_dptkitti``,
``aliked-lightglue_pnp_sensor``) are parsed on the fly; anything else is a registered method (the best offline
presets, the two-view and MicKey presets, the published RPR models), a YAML file under ``configs/methods/`` or a
path to one.
"""

from __future__ import annotations

import difflib
import importlib
import os
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any, cast

from .depth import HUB_MODELS, PAIR_MODELS
from .mast3r.published import DUNE_KINDS
from .matching import needs as matcher_needs
from .method_names import BEST_OFFLINE, BEST_OFFLINE_REFERENCE_DEPTH
from .yamlio import key_line, read_yaml

if TYPE_CHECKING:
    from .weights import Model

__all__ = [
    "Method",
    "MATCHERS",
    "OFFLINE_MATCHERS",
    "SOLVERS",
    "DEPTH_ALIASES",
    "BEST_OFFLINE",
    "BEST_OFFLINE_REFERENCE_DEPTH",
    "PAPER_THRESHOLD_PX",
    "get",
    "list_methods",
    "requirements",
    "register",
    "register_kind",
    "factory",
    "KINDS",
    "parse_name",
    "preset_name",
    "load_yaml",
    "config_dirs",
    "check_options",
    "query_depth_fallback",
    "depth_free_problem",
    "QUERY_DEPTH_SOLVERS",
    "LIFTING_SOLVERS",
    "weight_models",
    "all_weight_models",
    "CASCADE",
    "CASCADE_SEPARATOR",
    "cascade_method",
    "parse_cascade",
    "check_cascade_options",
]

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
#: Depth tokens that are not a file suffix.
DEPTH_ALIASES = {"none": "none", **{net: net for net in PAIR_MODELS}}
#: Ess.Mat RANSAC threshold (pixels) of the paper's rows: 3 px for SIFT, 2 px for learned matchers.
PAPER_THRESHOLD_PX = {"sift": 3.0}
_LEARNED_THRESHOLD_PX = 2.0


#: Method kind -> ``"module:function"`` building its localizer from a ``Method``, imported at the first build.
KINDS: dict[str, str] = {
    "matching": "mapfree.relocalize.pipeline:build_matching",
    "regression": "mapfree.rpr:build_from_method",
    "cascade": "mapfree.relocalize.cascade:build_cascade",
}
_FACTORIES: dict[str, Callable[[Method], Any]] = {}  # resolved (or ``register_kind``-ed) factories
_REGISTRY: dict[str, Method] = {}


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
        spec = _depth_spec(depth)
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


# --------------------------------------------------------------------------- cascades


#: The kind of a cascade of methods (``mapfree.relocalize.cascade``).
CASCADE = "cascade"
#: The string form joins the stages with it: ``A+B+C`` (unquoted in a shell; the characters of a plain name).
CASCADE_SEPARATOR = "+"
DEFAULT_ACCEPT = 0.8


def check_cascade_options(options: dict[str, Any], where: str) -> None:
    """Refuse a cascade's options that cannot run: ``stages`` not a list of >= 1 method names, ``accept`` not a
    number in (0, 1], a stage that is no method.

    Args:
        options: ``{"stages": [...], "accept": 0.8}``.
        where: The file or name they came from, for the message.

    Raises:
        ValueError: One line naming the problem.
    """
    stages = options.get("stages")
    if not isinstance(stages, list) or not stages or not all(isinstance(s, str) and s.strip() for s in stages):
        raise ValueError(f"{where}: a cascade needs stages: a list of method names (got {stages!r})")
    accept = options.get("accept", DEFAULT_ACCEPT)
    if isinstance(accept, bool) or not isinstance(accept, (int, float)) or not 0 < accept <= 1:
        raise ValueError(f"{where}: a cascade's accept must be a probability in (0, 1], got {accept!r}")
    for s in stages:
        try:
            stage = get(s)
        except (KeyError, FileNotFoundError) as e:
            raise ValueError(f"{where}: stage {s!r}: {e.args[0] if e.args else e}") from None
        if stage.kind == CASCADE:
            raise ValueError(f"{where}: stage {s!r} is itself a cascade (list its stages instead)")


def cascade_method(
    stages: Sequence[str], accept: float = DEFAULT_ACCEPT, name: str | None = None, where: str = ""
) -> Method:
    """A cascade as a ``Method`` (what ``get("A+B")`` and a ``kind: cascade`` YAML give).

    Args:
        stages: The stages' method names, in the order they are tried.
        accept: Stop at the first stage whose ``p_correct`` is at least this.
        name: The method's name (default ``A+B``).
        where: Where the cascade was written, for error messages.

    Returns:
        The method.

    Raises:
        ValueError: Stages or accept that cannot run (``check_cascade_options``).
    """
    check_cascade_options(
        {"stages": list(stages), "accept": accept}, where or name or CASCADE_SEPARATOR.join(map(str, stages))
    )
    names = [s.strip() for s in stages]
    return Method(
        name=name or CASCADE_SEPARATOR.join(names),
        kind=CASCADE,
        matcher="",
        solver="",
        depth="none",
        options={"stages": names, "accept": float(accept)},
        description=f"cascade of {', '.join(names)}: the next stage only where p_correct < {accept:g}",
    )


def parse_cascade(name: str) -> Method | None:
    """``A+B+C`` -> the cascade of those methods (accept 0.8), or None for a name of another form (a path, a YAML
    file, a name without ``+``).

    Args:
        name: What the user typed.

    Returns:
        The method, or None.

    Raises:
        ValueError: A stage that is no method, or an empty one (``A++B``).
    """
    if CASCADE_SEPARATOR not in name or name.endswith((".yaml", ".yml")) or os.sep in name:
        return None
    return cascade_method(name.split(CASCADE_SEPARATOR), where=f"cascade {name!r}")


# --------------------------------------------------------------------------- kinds


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


def register(method: Method, overwrite: bool = False) -> Method:
    """Register a named method (e.g. a trained regression model) so ``get(name)`` finds it.

    Args:
        method: The method, under its ``name``.
        overwrite: Replace a method of that name.

    Returns:
        The method.

    Raises:
        ValueError: The name is taken (without ``overwrite``).
    """
    if method.name in _REGISTRY and not overwrite:
        raise ValueError(f"method {method.name!r} is already registered")
    _REGISTRY[method.name] = method
    return method


# --------------------------------------------------------------------------- names


def _depth_spec(token: str) -> str:
    """A depth token of a preset name -> a depth spec: a spec as is, a network's short name, else a file suffix."""
    if ":" in token or token == "none":
        return token
    if token in DEPTH_ALIASES:
        return DEPTH_ALIASES[token]
    return token if token in HUB_MODELS else f"files:{token}"


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
        depth=_depth_spec(depth_tok),
        solver=solver,
        solver_opts=solver_opts,
        description=f"{matcher} matches, {solver} solver, depth {depth_tok} (paper settings"
        + (f", {threshold:g} px)" if solver == "essential" else ")")
        + (f"; needs {matcher_needs(matcher)}" if matcher in _NEEDS_IN_DESCRIPTION else ""),
    )


def config_dirs() -> list[Path]:
    """Where named YAML configs live: ``$MAPFREE_METHODS``, the repository's ``configs/methods``, packaged ones."""
    here = Path(__file__).resolve()
    dirs = [Path(p) for p in os.environ.get("MAPFREE_METHODS", "").split(os.pathsep) if p]
    dirs += [here.parents[2] / "configs" / "methods", here.parent / "configs" / "methods"]
    return [d for d in dirs if d.is_dir()]


def load_yaml(path: os.PathLike | str) -> Method:
    """A method from a YAML file. Keys: those of ``Method``; ``extends: NAME`` starts from another method."""
    path = Path(path)
    data = read_yaml(path)
    if not isinstance(data, dict):
        raise ValueError(f"{path}: a method config must be a mapping")
    if data.get("kind") == CASCADE:
        extra = sorted(set(data) - {"kind", "name", "stages", "accept", "description"})
        if extra:
            raise ValueError(f"{path}: unknown key(s) {', '.join(extra)} of a cascade (allowed: stages, accept, name)")
        stages = data.get("stages")
        if not isinstance(stages, list):
            raise ValueError(f"{path}: a cascade needs stages: a list of method names (got {stages!r})")
        return cascade_method(stages, data.get("accept", DEFAULT_ACCEPT), str(data.get("name", path.stem)), str(path))
    known = set(Method.__dataclass_fields__) | {"extends"}
    unknown = sorted(set(data) - known)
    if unknown:
        raise ValueError(f"{path}: unknown key(s) {', '.join(unknown)} (allowed: {', '.join(sorted(known))})")
    check_yaml_types(path, data)
    base = get(data.pop("extends")) if "extends" in data else Method(name=path.stem)
    merged = base.to_dict()
    for key in ("matcher_opts", "solver_opts", "options"):
        merged[key] = {**merged[key], **(data.pop(key, None) or {})}
    if "depth" in data:
        data["depth"] = _depth_spec(str(data["depth"]))
    merged.update(data)
    merged["name"] = data.get("name", path.stem)
    method = Method(**merged)
    check_options(method, where=str(path))
    return method


#: What each key of a method YAML holds: ``(type, what a value looks like)``; every key is checked here, in one
#: place, before anything else reads the file's values.
YAML_KEY_TYPES: dict[str, tuple[type, str]] = {
    "extends": (str, "a method name or YAML file (e.g. sift_pnp_sensor)"),
    "name": (str, "text"),
    "description": (str, "text"),
    "kind": (str, "a method kind (matching, regression)"),
    "matcher": (str, "a matcher name (e.g. sift)"),
    "solver": (str, "a solver name (essential, pnp, procrustes, mickey)"),
    "depth": (str, "a depth spec (a file suffix such as sensor, none, or a network such as dav2-indoor)"),
    "matcher_opts": (dict, "a mapping of option: value (e.g. {max_features: 2000})"),
    "solver_opts": (dict, "a mapping of option: value (e.g. {confidence: score})"),
    "options": (dict, "a mapping of option: value"),
}
#: Keys of which a method YAML must give one: without any, it would silently run the defaults (SIFT, Ess.Mat, no
#: depth, poses up to scale).
_NAMING_KEYS = ("extends", "kind", "matcher", "solver")


def check_yaml_types(path: os.PathLike | str, data: dict[str, Any]) -> None:
    """Refuse a method YAML that names no method, or whose values have the wrong type, naming file, line and key.

    Args:
        path: The YAML file (for the message, and to find the key's line).
        data: Its parsed top-level mapping (keys already known to be ``Method`` fields or ``extends``).

    Raises:
        ValueError: ``FILE: empty method config …`` or ``FILE:LINE: KEY: expected …, got VALUE``.
    """
    if not any(k in data for k in _NAMING_KEYS):
        what = "an empty method config" if not data else f"it names no method (only {', '.join(sorted(data))})"
        raise ValueError(
            f"{path}: {what}: give 'extends: NAME' (a preset such as sift_pnp_sensor, or another YAML) or "
            f"'matcher:' and 'solver:'"
        )
    for key, value in data.items():
        want, looks = YAML_KEY_TYPES[key]
        empty_opts = want is dict and value is None  # `solver_opts:` with nothing under it
        if not (isinstance(value, want) or empty_opts) or (want is str and not value.strip()):
            raise ValueError(f"{path}{key_line(path, key)}: {key}: expected {looks}, got {value!r}")


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
    from . import matching, solvers

    matching.check_options(method.matcher, method.matcher_opts, where=where or method.name, prefix="matcher_opts.")
    solvers.check_options(method.solver, method.solver_opts, where=where or method.name, prefix="solver_opts.")


def _yaml_named(name: str) -> Path | None:
    for d in config_dirs():
        for ext in (".yaml", ".yml"):
            if (d / f"{name}{ext}").is_file():
                return d / f"{name}{ext}"
    return None


_rpr_registered = False


def _load_plugins() -> None:
    """Register the published RPR models' methods, once, at the first look-up that needs them: ``rpr`` (any
    checkpoint) and ``rpr-<config>`` for each published configuration (``mapfree.rpr.official``: no torch)."""
    global _rpr_registered
    if _rpr_registered:
        return
    _rpr_registered = True
    try:
        from .rpr.official import OFFICIAL_CONFIGS
    except ImportError:  # pragma: no cover - an install without the regression package's dependencies
        return
    regression = Method(name="rpr", kind="regression", matcher="", solver="", depth="none")
    presets = [
        replace(regression, description="relative pose regression network (mapfree train); needs --checkpoint CKPT"),
        *(
            replace(
                regression,
                name=f"rpr-{config}",
                options={"config": config},
                description=f"published Map-free RPR model {config} (configs/rpr/{config}.yaml); "
                f"--checkpoint CKPT or {config}.ckpt in a weights folder (`mapfree weights`)",
            )
            for config in OFFICIAL_CONFIGS
        ),
    ]
    for method in presets:
        if method.name not in _REGISTRY:
            register(method)


def get(name_or_path: str | os.PathLike) -> Method:
    """A method by preset name, YAML config name, registered name, or path to a YAML file.

    ``NAME@DEPTH`` swaps the depth of any method (``best-offline@mono``); ``A+B+C`` is a cascade of
    methods (``mapfree.relocalize.cascade``).
    """
    s = str(name_or_path)
    cascade = parse_cascade(s)  # before NAME@DEPTH and paths: its stages may hold either
    if cascade is not None:
        return cascade
    if s.endswith((".yaml", ".yml")) or os.sep in s:
        if not Path(s).is_file():
            raise FileNotFoundError(f"method config {s} not found")
        return load_yaml(s)
    if "@" in s:
        base, depth = s.rsplit("@", 1)
        return get(base).with_depth(depth)
    if s in _REGISTRY:
        return _REGISTRY[s]
    p = _yaml_named(s)  # a config file wins over a preset of the same name
    if p is not None:
        return load_yaml(p)
    parsed = parse_name(s)
    if parsed is not None:
        return parsed
    _load_plugins()
    if s in _REGISTRY:
        return _REGISTRY[s]
    close = difflib.get_close_matches(s, list_methods(), n=3, cutoff=0.75)
    hint = f"did you mean {' or '.join(map(repr, close))}? " if close else ""
    raise KeyError(
        f"unknown method {s!r}: {hint}use {{matcher}}_{{solver}}_{{depth}} with matcher in {', '.join(MATCHERS)}, "
        f"solver in emat/pnp/procrustes, depth a file suffix or 'none'; or a YAML config "
        f"(see `mapfree run --list-methods`)"
    )


def list_methods(depths: tuple[str, ...] = ("dptkitti", "dptnyu", "sensor", "mono", "none")) -> list[str]:
    """Every preset name for the given depth tokens, the YAML configs, and registered methods."""
    # Without depth only Ess.Mat estimates anything (PnP/Procrustes need maps: ``depth_free_problem``).
    names = [
        preset_name(m, s, d)
        for d in depths
        for m in MATCHERS
        for s in (("emat",) if d == "none" else ("emat", "pnp", "procrustes"))
    ]
    for d in config_dirs():
        names += sorted(p.stem for p in d.glob("*.y*ml"))
    _load_plugins()
    names += sorted(_REGISTRY)
    return list(dict.fromkeys(names))


def requirements(name: str) -> str:
    """What running method ``name`` needs: the matcher's weights or packages and where depth comes from."""
    m = get(name)
    if m.kind != "matching":
        return m.description or f"a {m.kind} method"
    if m.depth == "none":
        depth = "no depth (direction only)"
    elif m.depth == "mickey":
        depth = "depth of the mickey network's own keypoints (no depth files)"
    elif m.depth in PAIR_MODELS:
        depth = f"depth from the {m.depth} network's own pointmaps (no depth files)"
    elif m.depth.startswith("files:"):
        depth = f"depth maps FRAME.{m.depth[len('files:') :]}.png"
    else:
        depth = f"depth network {HUB_MODELS.get(m.depth, m.depth.removeprefix('hf:'))}"
    return f"{matcher_needs(m.matcher)}; {depth}"


def weight_models(name: str) -> list[Model]:
    """The weights (``mapfree.weights`` models) that ``name`` needs: a method (its matcher's and depth network's,
    a published RPR network's), a matcher or a depth network name. ``KeyError`` for a name that is none of these."""
    from .depth.hub import DEPTH_WEIGHTS
    from .matching import registry_key
    from .matching.published import MATCHER_WEIGHTS, matcher_weights

    if registry_key(name) in MATCHER_WEIGHTS:
        return list(MATCHER_WEIGHTS[registry_key(name)])
    if name in DEPTH_WEIGHTS:
        return [DEPTH_WEIGHTS[name]]
    try:
        m = get(name)
    except KeyError:
        known = [*list_methods(), *MATCHER_WEIGHTS, *DEPTH_WEIGHTS]
        close = difflib.get_close_matches(name, known, n=3, cutoff=0.75)
        hint = f"did you mean {' or '.join(map(repr, close))}? " if close else ""
        raise KeyError(
            f"{name!r} is no method, matcher or depth network: {hint}see `mapfree run --list-methods`, "
            f"or `mapfree weights` without a name for every model"
        ) from None
    if m.kind == "regression":
        from .rpr.official import RPR_WEIGHTS

        config = m.options.get("config")
        return [RPR_WEIGHTS[config]] if config in RPR_WEIGHTS and not m.options.get("checkpoint") else []
    if m.kind != "matching":
        return []
    out = list(matcher_weights(registry_key(m.matcher), m.matcher_opts))
    if m.depth in DEPTH_WEIGHTS:
        out.append(DEPTH_WEIGHTS[m.depth])
    elif m.depth.startswith("hf:") and not Path(m.depth[3:]).expanduser().is_dir():
        from .weights import HubModel

        out.append(HubModel(m.depth[3:], f"depth network {m.depth}"))
    return out


def all_weight_models() -> list[tuple[Model, list[str]]]:
    """Every published model a built-in matcher, depth network or RPR method can use, each with the names that
    use it (``mapfree weights`` lists them)."""
    from .depth.hub import DEPTH_WEIGHTS
    from .matching.published import MATCHER_WEIGHTS, OPTION_WEIGHTS

    users: dict[str, tuple[Any, list[str]]] = {}
    by_option = [(f"{matcher} ({option}: {value})", (v,)) for (matcher, option, value), v in OPTION_WEIGHTS.items()]
    sources: list[tuple[str, tuple]] = [
        *MATCHER_WEIGHTS.items(),
        *by_option,
        *((k, (v,)) for k, v in DEPTH_WEIGHTS.items()),
    ]
    try:
        from .rpr.official import RPR_WEIGHTS

        sources += [(f"rpr-{k}", (v,)) for k, v in RPR_WEIGHTS.items()]
    except ImportError:  # pragma: no cover - a training-free install without the regression package's deps
        pass
    for user, models in sources:
        for model in models:
            users.setdefault(model.name, (model, []))[1].append(user)
    return list(users.values())


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


_register_builtins()
_register_two_view_presets()
_register_mickey_presets()
