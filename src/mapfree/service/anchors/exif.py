"""Uploaded photos stored upright (``photos.py`` turns them) and without metadata (GPS position, camera serial,
time, software...).

A photo whose orientation is 1 keeps its pixels byte for byte: only the metadata segments (JPEG APP1-APP13,
APP15, comments; PNG text, time and eXIf chunks) and whatever follows the image's end (a motion photo's MP4
clip, vendor trailers) are dropped. A turned photo is re-encoded upright (JPEG at
quality 95, PNG losslessly), so that every reader, ours and a browser, shows the same pixels.
"""

from __future__ import annotations

import struct

import cv2
import numpy as np

from ...data.orientation import ROTATIONS, OrientationError, check_orientation, exif_orientation, orient_pixels

__all__ = ["strip_metadata", "clean_photo", "photo_orientation", "depth_png"]

#: JPEG segments kept: APP0 (JFIF) and APP14 (Adobe colour transform, needed to decode some files right).
_JPEG_KEEP_APP = {0xE0, 0xEE}
#: PNG chunks dropped: free text, time stamps, EXIF, colour profiles (which name the device that made them).
_PNG_DROP = {b"tEXt", b"zTXt", b"iTXt", b"tIME", b"eXIf", b"iCCP"}
_PNG_SIG = b"\x89PNG\r\n\x1a\n"


def photo_orientation(data: bytes, what: str) -> int:
    """The EXIF orientation of uploaded bytes, refused with a 422 naming ``what`` when it is mirrored."""
    from ..inputs import UploadError

    try:
        return check_orientation(exif_orientation(data), what)
    except OrientationError as e:
        raise UploadError(422, str(e)) from None


def depth_png(depth_m: np.ndarray) -> bytes:
    """A decoded (turned) depth map back to the uint16 millimetre PNG it came from."""
    ok, buf = cv2.imencode(".png", np.rint(depth_m * 1000.0).astype(np.uint16))
    if not ok:  # pragma: no cover
        raise ValueError("could not encode the depth map")
    return buf.tobytes()


def _scan_end(data: bytes, i: int) -> int:
    """The end of the entropy-coded data that starts at ``i``: the position of the next marker (an 0xFF not
    followed by a stuffed 0x00 or a restart marker), or -1 when there is none."""
    while True:
        i = data.find(b"\xff", i)
        if i < 0 or i + 1 >= len(data):
            return -1
        nxt = data[i + 1]
        if nxt == 0x00 or 0xD0 <= nxt <= 0xD7 or nxt == 0xFF:
            i += 1 if nxt == 0xFF else 2
            continue
        return i


def _strip_jpeg(data: bytes) -> bytes | None:
    """The JPEG up to its end-of-image marker without metadata segments: whatever a phone appends after it (a
    motion photo's MP4 clip, a vendor trailer) goes too. None when the layout is not one we walk."""
    out, i = [data[:2]], 2
    while i + 2 <= len(data) and data[i] == 0xFF:
        marker = data[i + 1]
        if marker == 0xFF:  # fill byte
            i += 1
            continue
        if marker == 0xD9:  # end of image: nothing after it is kept
            out.append(data[i : i + 2])
            return b"".join(out)
        length = struct.unpack(">H", data[i + 2 : i + 4])[0] if i + 4 <= len(data) else 0
        if length < 2 or i + 2 + length > len(data):
            return None
        if marker == 0xDA:  # start of scan: its header, then entropy-coded data up to the next marker
            end = _scan_end(data, i + 2 + length)
            if end < 0:
                return None
            out.append(data[i:end])
            i = end
            continue
        if not ((0xE1 <= marker <= 0xEF and marker not in _JPEG_KEEP_APP) or marker == 0xFE):
            out.append(data[i : i + 2 + length])
        i += 2 + length
    return None  # not a layout we walk: the caller re-encodes


def _strip_png(data: bytes) -> bytes | None:
    out, i = [_PNG_SIG], len(_PNG_SIG)
    while i + 12 <= len(data):
        (length,) = struct.unpack(">I", data[i : i + 4])
        kind = data[i + 4 : i + 8]
        end = i + 12 + length
        if end > len(data):
            return None
        if kind not in _PNG_DROP:
            out.append(data[i:end])
        i = end
        if kind == b"IEND":
            return b"".join(out)
    return None


def strip_metadata(data: bytes) -> bytes | None:
    """JPEG or PNG bytes without their metadata segments, pixels untouched; None when the file's layout is not
    one we can walk (then re-encode it)."""
    if data.startswith(b"\xff\xd8"):
        return _strip_jpeg(data)
    if data.startswith(_PNG_SIG):
        return _strip_png(data)
    return None


def clean_photo(data: bytes, upright: np.ndarray | None = None, orientation: int | None = None) -> bytes:
    """What is stored and served for an uploaded photo: upright, without metadata. ``upright`` (RGB) and its
    EXIF ``orientation`` save decoding and reading the metadata again when the caller has them."""
    if orientation is None:
        orientation = exif_orientation(data)
    if orientation not in ROTATIONS:  # mirrored (stored before those were refused): shown as stored
        orientation = 1
    if orientation == 1 and (stripped := strip_metadata(data)) is not None:
        return stripped
    if upright is None:
        img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR | cv2.IMREAD_IGNORE_ORIENTATION)
        if img is None:
            raise ValueError("not a decodable photo")  # never stored: uploads are decoded before
        upright = orient_pixels(cv2.cvtColor(img, cv2.COLOR_BGR2RGB), orientation)
    png = data.startswith(_PNG_SIG)
    ok, buf = cv2.imencode(
        ".png" if png else ".jpg",
        cv2.cvtColor(upright, cv2.COLOR_RGB2BGR),
        [] if png else [cv2.IMWRITE_JPEG_QUALITY, 95],
    )
    if not ok:  # pragma: no cover - encoding a decoded image does not fail
        raise ValueError("could not re-encode the photo")
    return buf.tobytes()
