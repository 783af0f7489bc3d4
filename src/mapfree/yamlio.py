"""YAML files read with errors that name the file and line (method and training configs).

A config may extend another with a top-level ``base: OTHER.yaml`` key (``read_yaml_with_base``): OTHER is read the
same way, recursively, and the file's own keys are deep-merged over it.
"""

from __future__ import annotations

import os
import re
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import yaml

__all__ = ["read_yaml", "read_yaml_with_base", "deep_merge", "key_line", "BASE_KEY"]

#: Top-level key naming the file a config extends.
BASE_KEY = "base"


def read_yaml(path: os.PathLike | str) -> Any:
    """Read a YAML file (safe loader) with errors that name the file and line.

    Args:
        path: The file.

    Returns:
        The parsed document; ``{}`` for an empty file.

    Raises:
        ValueError: Invalid YAML (``path:line: invalid YAML (...)``).
    """
    path = Path(path)
    try:
        return yaml.safe_load(path.read_text()) or {}
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None)
        line = f":{mark.line + 1}" if mark is not None else ""
        raise ValueError(f"{path}{line}: invalid YAML ({getattr(e, 'problem', e)})") from None


def deep_merge(base: Mapping[str, Any], over: Mapping[str, Any]) -> dict[str, Any]:
    """Merge one config over another: mappings merge key by key (recursively); lists and scalars replace.

    Args:
        base: The config extended.
        over: The config whose keys win.

    Returns:
        A new mapping; neither input is modified.
    """
    out = dict(base)
    for k, v in over.items():
        out[k] = deep_merge(out[k], v) if isinstance(v, Mapping) and isinstance(out.get(k), Mapping) else v
    return out


def read_yaml_with_base(path: os.PathLike | str, search: Sequence[os.PathLike | str] = ()) -> dict[str, Any]:
    """Read a YAML config resolved through its ``base:`` chain, each file's keys merged over its base's.

    Args:
        path: The config.
        search: Folders where a ``base`` that is not a path relative to the file is looked up by name
            (``.yaml`` optional).

    Returns:
        The merged mapping, without the ``base`` key.

    Raises:
        FileNotFoundError: ``path`` does not exist.
        ValueError: Invalid YAML, not a mapping, a missing base or a cycle (naming the files and the line of
            the ``base`` key).
    """
    return _resolve(Path(path), tuple(Path(s) for s in search), ())


def _resolve(path: Path, search: tuple[Path, ...], chain: tuple[Path, ...]) -> dict[str, Any]:
    if path.resolve() in {p.resolve() for p in chain}:
        raise ValueError(f"{chain[-1]}: base cycle: {' -> '.join(str(p) for p in (*chain, path))}")
    if not path.is_file():
        raise FileNotFoundError(f"config {path} not found")
    data = read_yaml(path)
    if not isinstance(data, dict):
        raise ValueError(f"{path}: expected a mapping of config keys, got {type(data).__name__}")
    if BASE_KEY not in data:
        return data
    data = dict(data)
    name = data.pop(BASE_KEY)
    where = f"{path}{key_line(path, BASE_KEY)}"
    if not isinstance(name, str) or not name.strip():
        raise ValueError(f"{where}: {BASE_KEY} must name a YAML file (e.g. '{BASE_KEY}: 3d3d.yaml'), got {name!r}")
    candidates = [path.parent / name] + [d / n for d in search for n in (name, f"{name}.yaml")]
    found = next((c for c in candidates if c.is_file()), None)
    if found is None:
        raise ValueError(
            f"{where}: {BASE_KEY} {name!r} not found (looked for "
            f"{', '.join(str(c) for c in dict.fromkeys(candidates))})"
        )
    return deep_merge(_resolve(found, search, (*chain, path)), data)


def key_line(path: os.PathLike | str, key: str) -> str:
    """``:LINE`` of a top-level ``key:`` in the file, for error messages ("" when not found)."""
    path = Path(path)
    pattern = re.compile(rf"^{re.escape(key)}\s*:")
    for i, line in enumerate(path.read_text().splitlines(), 1):
        if pattern.match(line):
            return f":{i}"
    return ""
