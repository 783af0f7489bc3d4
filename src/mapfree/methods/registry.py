"""The registry: a method by the name a user types (``get``), registered methods (``register``), cascades of
methods (``A+B``), method YAML files (``load_yaml``) and the listing of every name (``list_methods``)."""

from __future__ import annotations

import difflib
import os
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

from ..yamlio import read_yaml
from .base import Method, depth_spec
from .names import MATCHERS, parse_name, preset_name
from .rules import check_options
from .yamlconfig import check_yaml_types, config_dirs, yaml_named

__all__ = [
    "get",
    "list_methods",
    "register",
    "load_yaml",
    "CASCADE",
    "CASCADE_SEPARATOR",
    "DEFAULT_ACCEPT",
    "cascade_method",
    "parse_cascade",
    "check_cascade_options",
]

_REGISTRY: dict[str, Method] = {}


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


# --------------------------------------------------------------------------- look-ups


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
        data["depth"] = depth_spec(str(data["depth"]))
    merged.update(data)
    merged["name"] = data.get("name", path.stem)
    method = Method(**merged)
    check_options(method, where=str(path))
    return method


_rpr_registered = False


def _load_plugins() -> None:
    """Register the published RPR models' methods, once, at the first look-up that needs them: ``rpr`` (any
    checkpoint) and ``rpr-<config>`` for each published configuration (``mapfree.rpr.official``: no torch)."""
    global _rpr_registered
    if _rpr_registered:
        return
    _rpr_registered = True
    try:
        from ..rpr.official import OFFICIAL_CONFIGS
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
    p = yaml_named(s)  # a config file wins over a preset of the same name
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
