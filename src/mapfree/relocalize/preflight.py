"""What ``run_split`` checks before any work: the output path, the submission confidence, the scenes named and
the depth maps a method reads; each refusal is one ``ValueError`` line naming the flag or path (a resumed journal's
checks are ``journal.check_resumable``)."""

from __future__ import annotations

import tempfile
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from ..data import REFERENCE_NAME, Scene
from ..data.io import depth_suffixes
from ..methods import Method
from ..solvers.confidence import CONFIDENCE_MODES

#: ``--confidence calibrated``: submit the calibrated probability ``p_correct`` (``mapfree.calibration``).
CALIBRATED = "calibrated"

__all__ = ["CALIBRATED", "check_output", "check_confidence", "selection_of", "pick_scenes", "check_depth_files"]


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


def pick_scenes(scene_list: list[Scene], names: Sequence[str], split: str) -> list[Scene]:
    """The scenes named, in split order; a name the split does not hold is refused (with the nearest ones)."""
    import difflib

    have = [s.name for s in scene_list]
    unknown = [n for n in dict.fromkeys(names) if n not in have]
    if unknown:
        hints = []
        for n in unknown:
            close = difflib.get_close_matches(n, have, n=2, cutoff=0.6)
            hints.append(f"{n} (did you mean {' or '.join(close)}?)" if close else n)
        raise ValueError(
            f"the {split} split has no scene {', '.join(hints)}; it holds {len(have)} scene(s)"
            + (f": {', '.join(have[:8])}{' …' if len(have) > 8 else ''}" if have else "")
        )
    wanted = set(names)
    return [s for s in scene_list if s.name in wanted]


def check_depth_files(m: Method, scene_list: list[Scene], split: str) -> None:
    """A ``files:SUFFIX`` method whose depth maps exist at no scene's reference is a typo in the suffix (or the
    wrong split), not a run of failures: refuse it before any work, naming the suffixes that do exist."""
    if m.kind != "matching" or not m.depth.startswith("files:") or not scene_list:
        return
    suffix = m.depth.split(":", 1)[1]
    refs = [s.frames[REFERENCE_NAME] for s in scene_list if REFERENCE_NAME in s.frames]
    if not refs or any(f.has_depth(suffix) for f in refs):
        return
    found = sorted({s for f in refs for s in depth_suffixes(f.image_path)})
    raise ValueError(
        f"method {m.name!r} reads depth maps *.{suffix}.png, but no reference image of the {split} "
        f"split has one (e.g. {refs[0].depth_path(suffix)}); depth suffixes there: "
        f"{', '.join(found) or 'none'} (pick one with NAME@SUFFIX or the method's last part)"
    )
