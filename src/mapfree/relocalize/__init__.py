"""Relocalization: one pair (``Relocalizer``) or a whole split (``run_split``) into a submission.

Every method kind builds a ``Localizer`` (``mapfree.localizer``); a ``View`` is one image on its way through
it (``mapfree.relocalize.views``).
"""

from ..localizer import Localizer, QueryLocalizer
from .pipeline import MIN_PARALLAX_PX, Relocalizer, build_localizer, build_matching
from .run import RunResult, failures_path, frames_to_run, journal_path, read_journal, run_split
from .views import Anchor, View, ViewLike, as_view, default_warning, photo_view, photo_views

__all__ = [
    "Relocalizer",
    "build_localizer",
    "Localizer",
    "QueryLocalizer",
    "Anchor",
    "View",
    "ViewLike",
    "as_view",
    "photo_view",
    "photo_views",
    "default_warning",
    "MIN_PARALLAX_PX",
    "build_matching",
    "run_split",
    "RunResult",
    "journal_path",
    "failures_path",
    "read_journal",
    "frames_to_run",
]
