"""MicKey's published files (the authors' checkpoints and Meta's DINOv2 backbone), as ``mapfree.weights``
models (no torch here: ``mapfree weights`` lists them without loading any network). ``mapfree.matching.published``
lists them with every matcher's weights."""

from __future__ import annotations

from ..weights import WeightFile

__all__ = ["MICKEY_ZIP_URL", "MICKEY_CHECKPOINTS", "MICKEY_DINOV2"]

MICKEY_ZIP_URL = "https://storage.googleapis.com/niantic-lon-static/research/mickey/assets/mickey_weights.zip"
_MICKEY_LICENCE = "Niantic non-commercial licence: mapfree does not ship it"
#: MicKey's files live together in ``mickey/`` of a weights folder (the authors' zip unzipped there may keep its
#: ``mickey_weights/`` folder): the checkpoints (with the ``config.yaml`` beside them) and the DINOv2 backbone,
#: which is also found in the weights folder itself and in torch's hub cache (where the public code downloads it).
MICKEY_CHECKPOINTS = {
    name: WeightFile(
        f"{name}.ckpt",
        "MicKey",
        (MICKEY_ZIP_URL,),
        aliases=(f"mickey/mickey_weights/{name}.ckpt",),
        licence=_MICKEY_LICENCE,
        archive=True,
        folder="mickey",
        torch_hub=False,
    )
    for name in ("mickey", "mickey_sc")
}
MICKEY_DINOV2 = WeightFile(
    "dinov2_vitl14_pretrain.pth",
    "MicKey's DINOv2 ViT-L/14 backbone",
    ("https://dl.fbaipublicfiles.com/dinov2/dinov2_vitl14/dinov2_vitl14_pretrain.pth",),
    aliases=("mickey/mickey_weights/dinov2_vitl14_pretrain.pth", "dinov2_vitl14_pretrain.pth"),
    licence="Meta's DINOv2, Apache 2.0",
    folder="mickey",
)
