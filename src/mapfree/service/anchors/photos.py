"""One photo from upload to method. An upload is read here once: decoded at its full size, turned upright by its
EXIF orientation (read once), its intrinsics and depth map checked for the file's stored pixel grid and turned
with it; what is stored comes from the same decode (upright, without metadata); then the photo is brought to
the working size (``worksize.fit_photo``) and the full-size pixels are dropped. What a method gets is a
``Photo``: the relocalize package's ``View``, with the photo's pose in the anchor's frame. Every endpoint that
takes a photo reads it here, anchors' photos and queries alike."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ...data.intrinsics import default_intrinsics, exif_focal
from ...data.orientation import displayed_size, orient_intrinsics, orient_pixels
from ...geometry import Intrinsics, Pose
from ...relocalize import View
from ..config import Limits
from .decode import IntrinsicsForm, decode_depth, decode_photo, parse_intrinsics
from .exif import clean_photo, depth_png
from .worksize import fit_photo


@dataclass
class Photo(View):
    """A photo as methods take it (a ``View``: pixels, intrinsics, optional metric depth), with its world-to-
    camera pose in the anchor's frame (the first photo's camera: identity for that one, and for a query)."""

    pose: Pose = field(default_factory=Pose.identity)


def intrinsics_of(d: dict) -> Intrinsics:
    """Stored intrinsics (``fx fy cx cy width height``) as ``Intrinsics``."""
    return Intrinsics(d["fx"], d["fy"], d["cx"], d["cy"], int(d["width"]), int(d["height"]))


def stored_intrinsics(k: Intrinsics, source: str) -> dict:
    """``Intrinsics`` and where they came from (given, exif or default) as the database stores them."""
    return {"fx": k.fx, "fy": k.fy, "cx": k.cx, "cy": k.cy, "width": k.width, "height": k.height, "source": source}


def stored_shape(upright: np.ndarray, orientation: int) -> tuple[int, int]:
    """(rows, cols) of the stored grid of an upright photo: what the client's intrinsics and depth describe."""
    w, h = displayed_size(upright.shape[1], upright.shape[0], orientation)  # a quarter turn is its own size swap
    return h, w


def upright_intrinsics(intr: Intrinsics, orientation: int) -> Intrinsics:
    """Checked intrinsics of the stored grid (``parse_intrinsics``) -> those of the upright photo."""
    return intr if orientation == 1 else orient_intrinsics(intr, orientation)


def found_intrinsics(data: bytes, width: int, height: int) -> tuple[IntrinsicsForm, str]:
    """``fx fy cx cy`` of the stored grid of a photo sent without intrinsics: from its EXIF focal length
    (``mapfree.data.intrinsics``, the project's one convention), else the default camera; and which it was
    (``exif`` or ``default``)."""
    found = exif_focal(data)
    if found is not None:
        f = found[0]
        return IntrinsicsForm(f, f, (width - 1) / 2, (height - 1) / 2), "exif"
    k = default_intrinsics(width, height)
    return IntrinsicsForm(k.fx, k.fy, k.cx, k.cy), "default"


@dataclass
class Upload:
    """One checked uploaded photo: the ``Photo`` a method gets (at the working size), and what is stored of it
    (``store``): the image upright and without metadata, its depth map upright (uint16 PNG), and the intrinsics
    of the upright photo at its full size (``intrinsics``) with where they came from (``source``: given, exif or
    default)."""

    photo: Photo
    intrinsics: Intrinsics
    source: str = "given"
    image: bytes = b""
    depth: bytes | None = None
    depth_measured: bool = False  # the depth map has a non-zero pixel (at its full size)
    pose: list[float] | None = None  # an anchor's photo: [qw, qx, qy, qz, tx, ty, tz] as stored (``photo.pose``)

    @property
    def nbytes(self) -> int:
        """What storing it counts against the owner's storage quota."""
        return len(self.image) + len(self.depth or b"")

    @property
    def stored_intrinsics(self) -> dict:
        """The intrinsics as the database stores them (``stored_intrinsics``)."""
        return stored_intrinsics(self.intrinsics, self.source)


def read_upload(
    data: bytes,
    lim: Limits,
    fields: IntrinsicsForm,
    depth: bytes | None = None,
    *,
    store: bool = False,
    what: str = "image",
    intr_what: str = "intrinsics",
    depth_what: str = "depth",
) -> Upload:
    """Uploaded bytes, the client's intrinsics (``fields``) and optional uint16 depth PNG, both for the file's stored
    grid -> the checked ``Upload`` (each problem an ``UploadError`` naming ``what``, ``intr_what`` or
    ``depth_what``). ``store``: also what is kept of it (an anchor's photo; a query keeps nothing). All four
    intrinsics left out (or empty) are found from the photo's EXIF focal length, else the default camera
    (``found_intrinsics``); the stored intrinsics and the ``Photo`` say which (``source``)."""
    image, orientation = decode_photo(data, lim, what)
    h, w = stored_shape(image, orientation)
    source = "given"
    if fields.empty():
        fields, source = found_intrinsics(data, w, h)
    intr = upright_intrinsics(parse_intrinsics(fields, w, h, intr_what), orientation)
    d = orient_pixels(decode_depth(depth, lim, (h, w), depth_what), orientation) if depth is not None else None
    stored, stored_depth = b"", None
    if store:
        stored = clean_photo(data, image, orientation)  # no metadata, upright: what is kept and served
        stored_depth = depth_png(d) if d is not None and orientation != 1 else depth  # upright, like its photo
    photo = fit_photo(Photo(image, intr, d, intrinsics_source=source), lim.work_max_side)
    return Upload(photo, intr, source, stored, stored_depth, bool(d is not None and d.any()))


def decode_stored(
    image: bytes, intrinsics: dict, depth: bytes | None, pose: list[float], lim: Limits, what: str
) -> Photo:
    """A stored photo (upright, without metadata; its intrinsics and depth as stored) -> its ``Photo`` at the
    working size, with ``pose`` (``[qw, qx, qy, qz, tx, ty, tz]``)."""
    img, _ = decode_photo(image, lim, what)
    d = decode_depth(depth, lim, img.shape[:2], f"{what} depth") if depth is not None else None
    return fit_photo(
        Photo(
            img,
            intrinsics_of(intrinsics),
            d,
            pose=Pose.from_qt(pose[:4], pose[4:]),
            intrinsics_source=intrinsics.get("source", "given"),  # rows stored before sources were: given
        ),
        lim.work_max_side,
    )  # one full-size photo in memory at a time
