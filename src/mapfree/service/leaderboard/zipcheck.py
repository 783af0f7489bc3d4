"""The cheap checks a submission ZIP gets before it is stored, in bounded time and memory."""

from __future__ import annotations

import io
import re
import zipfile
import zlib
from dataclasses import dataclass
from typing import BinaryIO

from ..config import Limits
from ..inputs import UploadError

ENTRY_RE = re.compile(r"^pose_(s\d{5})\.txt$")


@dataclass
class ZipInfo:
    scenes: list[str]
    uncompressed_bytes: int  # as the ZIP directory declares them
    zip_bytes: int  # the upload itself


#: How much of each entry the upload check decompresses (the start of the file: encoding, corrupt streams).
SNIFF_BYTES = 4096


def check_submission_zip(data: bytes | BinaryIO, limits: Limits, split: str, known_scenes: set[str] | None) -> ZipInfo:
    """The cheap checks an upload gets before it is stored, in bounded time and memory: a real ZIP (its central
    directory), few entries, flat ``pose_sNNNNN.txt`` names only (no traversal), known scenes, declared sizes
    within the per-entry and total limits and a sane ratio (zip bombs), and the first few kB of each entry
    decompressed (UTF-8 text, a readable stream). Parsing the pose lines is left to the workers."""
    f = io.BytesIO(data) if isinstance(data, (bytes, bytearray)) else data
    f.seek(0, io.SEEK_END)
    size = f.tell()
    f.seek(0)
    if size > limits.max_submission_bytes:
        raise UploadError(413, f"submission is {size} bytes; the limit is {limits.max_submission_bytes}")
    if not size:
        raise UploadError(400, "submission file is empty")
    try:
        zf = zipfile.ZipFile(f)
        infos = zf.infolist()
    except (zipfile.BadZipFile, zipfile.LargeZipFile, ValueError, EOFError) as e:
        raise UploadError(400, f"submission is not a valid ZIP archive ({e})") from None
    if len(infos) > limits.max_zip_entries:
        raise UploadError(413, f"ZIP has {len(infos)} entries; the limit is {limits.max_zip_entries}")
    total, scenes = 0, []
    for info in infos:
        name = info.filename
        if info.is_dir():
            raise UploadError(422, f"ZIP entry {name!r}: folders are not allowed; put pose_sNNNNN.txt at the root")
        if name.startswith(("/", "\\")) or ".." in name or "/" in name or "\\" in name or ":" in name:
            raise UploadError(
                422,
                f"ZIP entry {name!r}: paths are not allowed (path traversal); "
                "entries must be pose_sNNNNN.txt at the root",
            )
        m = ENTRY_RE.match(name)
        if not m:
            raise UploadError(422, f"ZIP entry {name!r}: expected a name like pose_s00460.txt")
        if info.flag_bits & 0x1:
            raise UploadError(422, f"ZIP entry {name!r} is encrypted")
        if info.compress_type not in (zipfile.ZIP_STORED, zipfile.ZIP_DEFLATED):
            raise UploadError(422, f"ZIP entry {name!r}: unsupported compression (use deflate or store)")
        if m.group(1) in scenes:
            raise UploadError(422, f"ZIP entry {name!r} appears twice")
        if known_scenes is not None and m.group(1) not in known_scenes:
            raise UploadError(422, f"ZIP entry {name!r}: scene {m.group(1)} is not in the {split} split")
        ratio = info.file_size / max(info.compress_size, 1)
        if info.file_size > (1 << 20) and ratio > limits.max_zip_ratio:
            raise UploadError(
                413,
                f"ZIP entry {name!r}: compression ratio {ratio:.0f}:1 looks like a zip bomb "
                f"(the limit is {limits.max_zip_ratio:g}:1)",
            )
        if info.file_size > limits.max_zip_entry_bytes:
            raise UploadError(
                413,
                f"ZIP entry {name!r} unpacks to {info.file_size} bytes; the per-file limit is "
                f"{limits.max_zip_entry_bytes} bytes",
            )
        total += info.file_size
        if total > limits.max_zip_uncompressed_bytes:
            raise UploadError(
                413,
                f"ZIP unpacks to more than the total limit of {limits.max_zip_uncompressed_bytes} bytes (zip bomb?)",
            )
        scenes.append(m.group(1))
    if not scenes:
        raise UploadError(422, "ZIP holds no pose_sNNNNN.txt files")
    for info in infos:
        _sniff(zf, info)
    return ZipInfo(sorted(scenes), total, size)


def _sniff(zf: zipfile.ZipFile, info: zipfile.ZipInfo) -> None:
    """Decompress the start of one entry: a corrupt stream or a binary file is refused now. Headers that lie
    about the size are caught too (the stream ends early and its CRC fails); the workers' reader enforces the
    size limits on the whole entry."""
    try:
        with zf.open(info) as f:
            head = f.read(SNIFF_BYTES)
    except (zipfile.BadZipFile, zlib.error, EOFError, OSError, ValueError, NotImplementedError) as e:
        raise UploadError(422, f"ZIP entry {info.filename!r} is corrupt ({e})") from None
    try:
        head.decode("utf-8")
    except UnicodeDecodeError as e:
        if e.start < len(head) - 4 or len(head) < SNIFF_BYTES:  # a multi-byte char cut at the edge is fine
            raise UploadError(422, f"ZIP entry {info.filename!r} is not UTF-8 text") from None
