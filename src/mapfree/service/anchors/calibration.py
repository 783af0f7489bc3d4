"""An anchor's calibration: which ``mapfree.calibration.Calibration`` turns its estimates into ``p_correct``.

By default an anchor uses the calibration shipped with its method (``mapfree.calibration.shipped``; a cascade's
stages each theirs), and answers without ``p_correct`` where none ships. Its owner may upload ``.calib.json``
files (``mapfree calibrate``) instead: one for the anchor's method, or one per stage of a cascade. They are
checked as ``mapfree run --calibration`` checks them and stored with the anchor, as is an optional ``accept``
threshold: answers then say ``accepted`` (``p_correct >= accept``).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from pathlib import PurePath
from typing import Any

from fastapi import UploadFile
from sqlalchemy.orm import Session

from ... import methods
from ...calibration import Calibrated, Calibration, CalibrationError, calibration_for, shipped
from ...estimate import Estimate
from ...localizer import Localizer
from ...relocalize.cascade import Cascade
from ..database.models import Anchor
from ..inputs import UploadError, check_name, read_upload

#: The largest calibration file accepted (a fitted file is a few kB: coefficients and isotonic knots).
MAX_CALIBRATION_BYTES = 1 << 20
#: Where an anchor's calibration of a method comes from.
UPLOADED, SHIPPED, NONE = "uploaded", "shipped", "none"


def calibrated_methods(method: str) -> list[str]:
    """The methods an anchor's calibrations are for: its method, or each stage of a cascade.

    Args:
        method: The anchor's (registered) method name.

    Returns:
        Registered method names, in order; ``[method]`` for a name the registry no longer knows (an operator's
        config removed since the anchor was made).
    """
    try:
        m = methods.get(method)
        if m.kind == methods.CASCADE:
            return [methods.get(s).name for s in m.options["stages"]]
    except (KeyError, ValueError, FileNotFoundError, OSError):
        return [method]
    return [m.name]


def _file_name(f: UploadFile) -> str:
    name = PurePath((f.filename or "calibration").replace("\\", "/")).name or "calibration"
    return check_name(name[:128], 128, "calibration file name")


def read_calibrations(files: list[UploadFile], method: str) -> list[dict[str, Any]] | None:
    """Check uploaded calibration files for an anchor's method: what is stored with the anchor.

    Args:
        files: The ``calibration`` parts (empty ones skipped).
        method: The anchor's method name.

    Returns:
        ``[{"name": file name, "file": the calibration's JSON}]``, or None when no file was given (the shipped
        calibrations then).

    Raises:
        UploadError: A file over the size limit (413); one that is not readable JSON, not a calibration, of
            another format version, corrupt, or fitted for another method, or two for one method (422); the
            message names the file.
    """
    allowed = calibrated_methods(method)
    out: list[dict[str, Any]] = []
    seen: set[str] = set()
    for f in files:
        data = read_upload(f, MAX_CALIBRATION_BYTES, "calibration")
        if data is None:
            continue
        name = _file_name(f)
        try:  # one method: exactly the check of `mapfree run --calibration`
            cal = Calibration.from_json(data, name, allowed[0] if len(allowed) == 1 else None)
        except CalibrationError as e:
            raise UploadError(422, f"calibration: {e}") from None
        if cal.method not in allowed:
            raise UploadError(
                422,
                f"calibration: calibration {name} was fitted for method {cal.method!r}, which is not a stage "
                f"of the cascade {method!r} ({', '.join(allowed)})",
            )
        if cal.method in seen:
            raise UploadError(422, f"calibration: two files for method {cal.method!r}; give one per method")
        seen.add(cal.method)
        out.append({"name": name, "file": cal.to_dict()})
    return out or None


def check_accept(accept: float | None) -> float | None:
    """The ``accept`` threshold of an anchor: a probability in [0, 1], or None (answers then carry no
    ``accepted``).

    Raises:
        UploadError: 422 for anything else.
    """
    if accept is not None and not (math.isfinite(accept) and 0.0 <= accept <= 1.0):
        raise UploadError(422, f"accept: {accept!r} is not a probability in [0, 1]")
    return accept


def uploaded(a: Anchor) -> dict[str, Calibration]:
    """An anchor's uploaded calibrations by method name (checked when uploaded)."""
    return {
        cal.method: cal for cal in (Calibration.from_dict(c["file"], str(c["name"])) for c in (a.calibration or []))
    }


def _entry(method: str, files: Mapping[str, dict]) -> dict[str, Any]:
    if method in files:
        cal, source, name = Calibration.from_dict(files[method]["file"], ""), UPLOADED, str(files[method]["name"])
    else:
        path = shipped(method)
        if path is None:
            return {"method": method, "source": NONE, "name": None, "frames": None, "ece": None}
        cal, source, name = Calibration.load(path, method), SHIPPED, path.name
    ece = cal.figures.get("p_correct", {}).get("ece")
    return {
        "method": method,
        "source": source,
        "name": name,
        "frames": cal.frames,
        "ece": None if ece is None else float(ece),
    }


def calibration_json(a: Anchor) -> dict[str, Any]:
    """What an anchor's JSON says of its calibration (``AnchorOut.calibrations`` and ``accept``).

    Returns:
        ``calibrations``: per method it runs (a cascade: per stage) its ``source`` (uploaded, shipped or none),
        the file's ``name``, the ``frames`` it was fitted on and its held-out ``ece``; ``accept``.
    """
    files = {str(c["file"]["method"]): c for c in (a.calibration or [])}
    return {"calibrations": [_entry(m, files) for m in calibrated_methods(a.method)], "accept": a.accept}


def calibrate(loc: Localizer[Any], ran: str, calibrations: Mapping[str, Calibration]) -> Localizer[Any]:
    """The localizer whose estimates carry ``p_correct``: the method's uploaded calibration, else the shipped one
    (a cascade: each stage's); unchanged when the method that ran has neither.

    Args:
        loc: The method's localizer (from the pool: shared, never changed here).
        ran: The method that runs (``localizers.effective_method``).
        calibrations: The anchor's uploaded calibrations by method.

    Returns:
        A localizer for this request.
    """
    if isinstance(loc, Cascade):
        return loc.with_calibrations(calibrations) if calibrations else loc
    cal = calibrations.get(ran) or calibration_for(ran)
    return loc if cal is None else Calibrated(loc, cal)


def source_of(est: Estimate, ran: str, calibrations: Mapping[str, Calibration]) -> str | None:
    """Where an estimate's ``p_correct`` came from (uploaded or shipped); None without one."""
    if est.p_correct is None:
        return None
    answered = methods.get(est.stage).name if est.stage else ran
    return UPLOADED if answered in calibrations else SHIPPED


def accepted(est: Estimate, accept: float | None) -> bool | None:
    """Whether an answer is accepted at an anchor's threshold: a pose whose ``p_correct`` is at least ``accept``
    (False without a pose or a probability); None when the anchor has no threshold."""
    if accept is None:
        return None
    return bool(est.ok and est.p_correct is not None and est.p_correct >= accept)


def set_calibration(db: Session, a: Anchor, files: list[UploadFile], accept: float | None) -> None:
    """Give an anchor its calibrations and accept threshold, replacing both: the uploaded files
    (``read_calibrations``), or none for its method's shipped ones. Every API process reads them from the database
    at each localize, so nothing cached needs forgetting.

    Args:
        db: The request's database session; committed.
        a: The anchor (the caller may change it: its owner or an admin).
        files: ``.calib.json`` uploads: one for the anchor's method, or one per stage of a cascade.
        accept: The threshold on ``p_correct`` answers are ``accepted`` at; None: none.

    Raises:
        UploadError: A file or threshold that cannot be used (413, 422); nothing is changed.
    """
    a.calibration, a.accept = read_calibrations(files, a.method), check_accept(accept)
    db.commit()
