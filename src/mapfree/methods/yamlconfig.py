"""Method YAML files: where named ones live (``config_dirs``) and the type of every key, checked before any value
is read (``check_yaml_types``). ``registry.load_yaml`` reads them."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from ..yamlio import key_line

__all__ = ["config_dirs", "yaml_named", "YAML_KEY_TYPES", "check_yaml_types"]


def config_dirs() -> list[Path]:
    """Where named YAML configs live: ``$MAPFREE_METHODS``, the repository's ``configs/methods``, packaged ones."""
    here = Path(__file__).resolve()  # src/mapfree/methods/yamlconfig.py
    dirs = [Path(p) for p in os.environ.get("MAPFREE_METHODS", "").split(os.pathsep) if p]
    dirs += [here.parents[3] / "configs" / "methods", here.parents[1] / "configs" / "methods"]
    return [d for d in dirs if d.is_dir()]


def yaml_named(name: str) -> Path | None:
    for d in config_dirs():
        for ext in (".yaml", ".yml"):
            if (d / f"{name}{ext}").is_file():
                return d / f"{name}{ext}"
    return None


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
