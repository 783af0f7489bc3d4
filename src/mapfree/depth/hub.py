"""Short names of the monocular metric depth networks on the Hugging Face hub (no torch import here)."""

from ..weights import HubModel

__all__ = ["HUB_MODELS", "DEPTH_WEIGHTS"]

_DA2 = "depth-anything/Depth-Anything-V2-Metric-{}-{}-hf"
HUB_MODELS: dict[str, str] = {
    "dav2-indoor": _DA2.format("Indoor", "Small"),
    "dav2-indoor-base": _DA2.format("Indoor", "Base"),
    "dav2-indoor-large": _DA2.format("Indoor", "Large"),
    "dav2-outdoor": _DA2.format("Outdoor", "Small"),
    "dav2-outdoor-base": _DA2.format("Outdoor", "Base"),
    "dav2-outdoor-large": _DA2.format("Outdoor", "Large"),
    "zoedepth": "Intel/zoedepth-nyu-kitti",
    "zoedepth-nyu": "Intel/zoedepth-nyu",
    "zoedepth-kitti": "Intel/zoedepth-kitti",
    "dpt-kitti": "facebook/dpt-dinov2-small-kitti",
    "dpt-kitti-base": "facebook/dpt-dinov2-base-kitti",
    "dpt-kitti-large": "facebook/dpt-dinov2-large-kitti",
    "dpt-nyu": "facebook/dpt-dinov2-small-nyu",
    "dpt-nyu-base": "facebook/dpt-dinov2-base-nyu",
    "dpt-nyu-large": "facebook/dpt-dinov2-large-nyu",
    "depth-pro": "apple/DepthPro-hf",
}

#: The networks as ``mapfree.weights`` models: found by the one rule, ``<name>/`` being the last part of the hub id.
DEPTH_WEIGHTS = {short: HubModel(repo, f"depth network {short}") for short, repo in HUB_MODELS.items()}
