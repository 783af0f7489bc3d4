"""Relocalization: one pair (``Relocalizer``) or a whole split (``run_split``) into a submission."""

from .. import methods as _methods
from .pipeline import MIN_PARALLAX_PX, Anchor, Localizer, Relocalizer, View, ViewLike, as_view, build_matching
from .run import RunResult, failures_path, frames_to_run, journal_path, read_journal, run_split

_methods.register_kind("matching", build_matching)

__all__ = [
    "Relocalizer",
    "Localizer",
    "Anchor",
    "View",
    "ViewLike",
    "as_view",
    "MIN_PARALLAX_PX",
    "run_split",
    "RunResult",
    "journal_path",
    "failures_path",
    "read_journal",
    "frames_to_run",
]
