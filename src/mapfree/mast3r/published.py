"""The published MASt3R / DUSt3R / DUNE-MASt3R checkpoints, as ``mapfree.weights`` models (no torch here: ``mapfree weights``
lists them without loading any network). ``mapfree.matching.published`` lists them with every matcher's weights."""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

from ..weights import Found, MissingWeightsError, WeightFile, find_in_dirs, missing_message, target_dir

__all__ = ["Mast3rWeights", "MAST3R_WEIGHTS", "DUNE_DECODERS", "DUNE_ENCODERS", "DUNE_KINDS"]


@dataclass(frozen=True)
class Mast3rWeights:
    """A MASt3R/DUSt3R checkpoint as a ``mapfree.weights`` model; never downloaded for the user (CC BY-NC-SA 4.0).

    It is the authors' ``STEM.pth``, or the hub's folder ``STEM/`` (config.json + model.safetensors), in the
    weights folders.

    Attributes:
        stem: The file stem.
        hub_id: Hugging Face hub id.
        url: Direct download of the ``.pth``.
        what: What it is for (``mast3r``, ``dust3r``), the start of every message about it.
        licence: The weights' licence, named in messages.
    """

    stem: str
    hub_id: str
    url: str
    what: str
    licence: str = "CC BY-NC-SA 4.0: mapfree does not ship it"

    @property
    def name(self) -> str:
        """``STEM.pth``."""
        return f"{self.stem}.pth"

    def item(self) -> str:
        """The file or the hub folder, in words."""
        return f"weights file '{self.stem}.pth' (or the hub folder {self.stem}/ with config.json and model.safetensors)"

    def locate(self, explicit: str | os.PathLike | None = None) -> Found | None:
        """Find ``STEM.pth`` or the hub folder in the weights folders (see ``Model.locate``)."""
        if explicit is not None:
            p = Path(explicit).expanduser()
            return Found(p, "the path given") if p.exists() else None
        hit = find_in_dirs(f"{self.stem}.pth", self.stem, self.hub_id.replace("/", "--"))
        return Found(*hit) if hit is not None else None

    def how(self) -> str:
        """Download the ``.pth`` or the hub folder into the weights folder (the licence named)."""
        return (
            f"Download {self.url} (licence {self.licence}) into {target_dir()}, or the hub folder {self.hub_id} "
            f"as {target_dir() / self.stem}/"
        )

    def fetch_command(self) -> str:
        """``curl`` of the ``.pth`` into the weights folder."""
        return f"curl -L --create-dirs -o {target_dir() / self.name} {self.url}"

    def missing(self, why: str = "", explicit: str | os.PathLike | None = None) -> MissingWeightsError:
        """The error for a checkpoint not found (see ``Model.missing``)."""
        if explicit is not None:
            return MissingWeightsError(
                f"{self.what}: checkpoint {explicit} not found (expected a .pth file or a "
                f"folder with config.json and model.safetensors)"
            )
        return MissingWeightsError(missing_message(self.what, self.item(), self.name, self.how(), why))


_NAVER = "https://download.europe.naverlabs.com/ComputerVision"
MAST3R_WEIGHTS = {
    "mast3r": Mast3rWeights(
        "MASt3R_ViTLarge_BaseDecoder_512_catmlpdpt_metric",
        "naver/MASt3R_ViTLarge_BaseDecoder_512_catmlpdpt_metric",
        f"{_NAVER}/MASt3R/MASt3R_ViTLarge_BaseDecoder_512_catmlpdpt_metric.pth",
        "mast3r",
    ),
    "dust3r": Mast3rWeights(
        "DUSt3R_ViTLarge_BaseDecoder_512_dpt",
        "naver/DUSt3R_ViTLarge_BaseDecoder_512_dpt",
        f"{_NAVER}/DUSt3R/DUSt3R_ViTLarge_BaseDecoder_512_dpt.pth",
        "dust3r",
    ),
}

_DUNE = "https://download.europe.naverlabs.com/dune"
_DUNE_LICENCE = "NAVER LABS Europe DUNE licence and CC BY-NC-SA 4.0, non-commercial: mapfree does not ship it"
#: DUNE-MASt3R's decoder files (MASt3R's ViT-B decoders and heads fine-tuned on a DUNE encoder), by matcher name.
DUNE_DECODERS = {
    "dune-mast3r": WeightFile(
        "dunemast3r_cvpr25_vitbase.pth",
        "dune-mast3r (decoder for the DUNE ViT-B/14 paper encoder)",
        (f"{_DUNE}/dunemast3r_cvpr25_vitbase.pth",),
        licence=_DUNE_LICENCE,
        torch_hub=False,
    ),
    "dune-mast3r-small": WeightFile(
        "dunemast3r_cvpr25_vitsmall.pth",
        "dune-mast3r-small (decoder for the DUNE ViT-S/14 encoder)",
        (f"{_DUNE}/dunemast3r_cvpr25_vitsmall.pth",),
        licence=_DUNE_LICENCE,
        torch_hub=False,
    ),
}
#: The DUNE encoder files, by the ``dune_backbone_name`` a decoder file names (the public ``torch.hub`` entry).
DUNE_ENCODERS = {
    "dune_vitbase_14_448_paper_encoder": WeightFile(
        "dune_vitbase14_448_paper.pth",
        "DUNE ViT-B/14 paper encoder (for dune-mast3r)",
        (f"{_DUNE}/dune_vitbase14_448_paper.pth",),
        licence=_DUNE_LICENCE,
        torch_hub=False,
    ),
    "dune_vitsmall_14_448_encoder": WeightFile(
        "dune_vitsmall14_448.pth",
        "DUNE ViT-S/14 encoder (for dune-mast3r-small)",
        (f"{_DUNE}/dune_vitsmall14_448.pth",),
        licence=_DUNE_LICENCE,
        torch_hub=False,
    ),
}
#: Matcher names of DUNE-MASt3R -> the encoder their published decoder file names.
DUNE_KINDS = {
    "dune-mast3r": "dune_vitbase_14_448_paper_encoder",
    "dune-mast3r-small": "dune_vitsmall_14_448_encoder",
}
