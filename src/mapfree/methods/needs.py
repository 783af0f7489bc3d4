"""What running a method needs: its matcher's weights or packages and where its depth comes from
(``requirements``), the published weights it loads (``weight_models``, ``all_weight_models``)."""

from __future__ import annotations

import difflib
from pathlib import Path
from typing import TYPE_CHECKING, Any

from ..depth import HUB_MODELS, PAIR_MODELS
from ..matching import needs as matcher_needs
from .registry import get, list_methods

if TYPE_CHECKING:
    from ..weights import Model

__all__ = ["requirements", "weight_models", "all_weight_models"]


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
    from ..depth.hub import DEPTH_WEIGHTS
    from ..matching import registry_key
    from ..matching.published import MATCHER_WEIGHTS, matcher_weights

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
        from ..rpr.official import RPR_WEIGHTS

        config = m.options.get("config")
        return [RPR_WEIGHTS[config]] if config in RPR_WEIGHTS and not m.options.get("checkpoint") else []
    if m.kind != "matching":
        return []
    out = list(matcher_weights(registry_key(m.matcher), m.matcher_opts))
    if m.depth in DEPTH_WEIGHTS:
        out.append(DEPTH_WEIGHTS[m.depth])
    elif m.depth.startswith("hf:") and not Path(m.depth[3:]).expanduser().is_dir():
        from ..weights import HubModel

        out.append(HubModel(m.depth[3:], f"depth network {m.depth}"))
    return out


def all_weight_models() -> list[tuple[Model, list[str]]]:
    """Every published model a built-in matcher, depth network or RPR method can use, each with the names that
    use it (``mapfree weights`` lists them)."""
    from ..depth.hub import DEPTH_WEIGHTS
    from ..matching.published import MATCHER_WEIGHTS, OPTION_WEIGHTS

    users: dict[str, tuple[Any, list[str]]] = {}
    by_option = [(f"{matcher} ({option}: {value})", (v,)) for (matcher, option, value), v in OPTION_WEIGHTS.items()]
    sources: list[tuple[str, tuple]] = [
        *MATCHER_WEIGHTS.items(),
        *by_option,
        *((k, (v,)) for k, v in DEPTH_WEIGHTS.items()),
    ]
    try:
        from ..rpr.official import RPR_WEIGHTS

        sources += [(f"rpr-{k}", (v,)) for k, v in RPR_WEIGHTS.items()]
    except ImportError:  # pragma: no cover - a training-free install without the regression package's deps
        pass
    for user, models in sources:
        for model in models:
            users.setdefault(model.name, (model, []))[1].append(user)
    return list(users.values())
