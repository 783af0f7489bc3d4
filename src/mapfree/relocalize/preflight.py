"""What ``run_split`` checks before any work: the output path, the submission confidence, and that a resumed
journal was written for the same frames; each refusal is one ``ValueError`` line naming the flag or path."""

from __future__ import annotations

import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

from ..data import Scene
from ..solvers.confidence import CONFIDENCE_MODES

#: ``--confidence calibrated``: submit the calibrated probability ``p_correct`` (``mapfree.calibration``).
CALIBRATED = "calibrated"

__all__ = ["CALIBRATED", "check_output", "check_confidence", "selection_of", "check_same_selection"]


def check_output(output: Path) -> None:
    """Refuse an output path that cannot take the submission (a folder, a folder that cannot be made or written
    in) before any work, naming it: not after the whole split was computed, with the system's errno text."""
    if output.is_dir():
        raise ValueError(
            f"the output {output} is a folder: give the submission ZIP's path (e.g. {output / 'submission.zip'})"
        )
    blocker = next((p for p in output.parents if p.exists()), None)
    if blocker is not None and not blocker.is_dir():
        raise ValueError(f"the output {output} cannot be written: {blocker} is a file, not a folder")
    try:
        output.parent.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile(dir=output.parent):
            pass
    except OSError as e:
        raise ValueError(f"the output {output} cannot be written in {output.parent} ({e.strerror or e})") from None


def check_confidence(confidence: str | None, m: Any) -> None:
    """Refuse a submission confidence (``--confidence``) the method's estimates do not carry, naming the known
    ones: an unknown name once fell back to the method's own confidence without a word."""
    if confidence is None:
        return
    if confidence == CALIBRATED:
        from ..calibration import calibration_for

        if m.kind != "cascade" and calibration_for(m.name, m.options) is None:
            raise ValueError(
                f"--confidence calibrated: method {m.name!r} has no calibration: fit one with `mapfree calibrate "
                f"DATA --method {m.name} -o {m.name}.calib.json` and pass --calibration {m.name}.calib.json"
            )
        return

    known = [f"confidence_{c}" for c in CONFIDENCE_MODES]
    if m.kind != "matching":
        raise ValueError(
            f"--confidence {confidence}: method {m.name!r} ({m.kind}) has its own confidence only "
            f"(the alternatives {', '.join(known)} come from a matching method's solver)"
        )
    if confidence not in known:
        import difflib

        close = [k for k in known if k == f"confidence_{confidence}"] or difflib.get_close_matches(confidence, known, 1)
        hint = f"did you mean {close[0]!r}? " if close else ""
        raise ValueError(f"unknown --confidence {confidence!r}: {hint}known: {', '.join([*known, CALIBRATED])}")


def selection_of(all_frames: bool, select: Callable[[Scene], list[str]] | None) -> str:
    """Which frames a run relocalizes, as its journal records it."""
    if select is not None:
        return getattr(select, "__name__", "selected")
    return "all" if all_frames else "scored"


_SELECTION_WORDS = {"all": "every query (--all-frames)", "scored": "the scored queries (no --all-frames)"}


def check_same_selection(jpath: Path, header: dict, selection: str) -> None:
    """A resumed run must relocalize the frames the journal's run did: resuming a run of every query without
    --all-frames (or the other way round) would write a mix of both sets."""
    had = header.get("frames")
    if had is None:  # a journal written before the selection was recorded: its all_frames flag says it
        if selection not in _SELECTION_WORDS:
            return
        had = "all" if header.get("all_frames") else "scored"
    if had != selection:
        was, now = (_SELECTION_WORDS.get(x, x) for x in (had, selection))
        raise ValueError(
            f"{jpath} holds a run of {was}, this one asks for {now}: resuming would mix the two; "
            f"run it as it was, or use --overwrite or another output path"
        )
