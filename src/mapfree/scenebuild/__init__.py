"""``mapfree build``: a Map-free dataset from your own scans (paper §4.2).

Two or more scans of a place (image folders or videos, optional intrinsics and phone tracking poses) ->
pycolmap SfM of all scans in one frame -> metric scale from the device track (or depth maps) -> the
Map-free layout with ``overlaps.npz``, optional sparse depth and training correspondences, and a report.
Places are independent: a local process pool or Ray tasks build them in parallel. This package is a
top-level consumer (like ``relocalize``): ``data`` never imports it.
"""

from .correspondences import CorrespondenceOptions, read_correspondences
from .inputs import Place, Scan, read_place
from .place import BuildError, BuildOptions, PlaceResult, build_place
from .sfm import SfmOptions

__all__ = [
    "BuildOptions",
    "BuildError",
    "PlaceResult",
    "build_place",
    "SfmOptions",
    "CorrespondenceOptions",
    "read_correspondences",
    "Place",
    "Scan",
    "read_place",
]
