"""What every request's inputs share: ``UploadError`` (a 4xx naming the problem), display names, and reading an
uploaded file within a limit."""

from __future__ import annotations

import unicodedata
from typing import BinaryIO

from fastapi import HTTPException, UploadFile


def read_upload(f: UploadFile | None, limit: int, what: str) -> bytes | None:
    """An uploaded file's bytes, refusing more than ``limit`` without reading it all. Endpoints that touch the
    database are plain ``def`` (run in the thread pool): a blocking database wait never stalls the event loop."""
    if f is None or (not f.filename and not f.size):
        return None
    data = f.file.read(limit + 1)
    if len(data) > limit:
        raise UploadError(413, f"{what}: larger than the limit of {limit} bytes")
    return data


def spooled_upload(f: UploadFile | None, what: str) -> BinaryIO:
    """The spooled file of an upload (on disk past 1 MB), never read whole: the body limit bounds its size."""
    if f is None or (not f.filename and not f.size):
        raise UploadError(400, f"{what}: no file uploaded")
    return f.file


class UploadError(Exception):
    def __init__(self, status: int, message: str):
        super().__init__(message)
        self.status, self.message = status, message


def problem(exc: UploadError | HTTPException) -> tuple[int, str]:
    """A refused form's status and message, to show above the form when it comes back."""
    if isinstance(exc, UploadError):
        return exc.status, exc.message
    return exc.status_code, str(exc.detail)


def check_name(name: str | None, max_chars: int, what: str = "name") -> str:
    """A display name: trimmed, bounded, without control or invisible formatting characters (U+202E and other
    bidirectional overrides would let a name display as something it is not)."""
    name = (name or "").strip()
    if len(name) > max_chars:
        raise UploadError(422, f"{what} is longer than {max_chars} characters")
    bad = next((c for c in name if unicodedata.category(c) in ("Cc", "Cf", "Cs", "Co", "Cn", "Zl", "Zp")), None)
    if bad is not None:
        raise UploadError(422, f"{what} contains a control or formatting character (U+{ord(bad):04X})")
    return name
