"""Submissions: accept an upload (validated, stored and queued before it is acknowledged), show results,
and render plots. Shared by the JSON API and the web pages (leaderboards: ``boards.py``)."""

from __future__ import annotations

import io
import threading
from typing import BinaryIO, overload

from fastapi import HTTPException
from sqlalchemy import delete, func, select
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from ..accounts.quota import check_quota, daily_test_limit, lock_user, recent_count
from ..config import UNLIMITED, Settings
from ..database.models import READ_ONLY, Plot, Result, Submission, User, now
from ..inputs import UploadError, check_name
from .disclosure import without_withheld
from .scoring import PLOT_NAMES, known_scenes, render_plots, unpack_report
from .storage import UPLOAD_LEASE_SECONDS, copy_in
from .zipcheck import check_submission_zip


def _limit_reached(db: Session, user: User, split: str, window_s: float, limit: int, what: str) -> None:
    """A 429 when ``user`` already made ``limit`` submissions to ``split`` in the last ``window_s`` (0: any
    submission is refused; ``UNLIMITED``: no limit)."""
    if limit < 0:
        return
    if limit == 0:
        raise UploadError(
            429, f"{what} limit: this account may make no {split} submissions (its limit is 0; ask the operator)"
        )
    since = now() - window_s
    if recent_count(db, user, split, window_s) >= limit:
        first = db.scalar(
            select(func.min(Submission.created_at)).where(
                Submission.user_id == user.id, Submission.split == split, Submission.created_at > since
            )
        )
        wait = max(1, int((first or now()) + window_s - now()) + 1)
        raise UploadError(
            429,
            f"{what} limit reached: {limit} {split} submissions per {window_s / 3600:g} h; "
            f"the next one is possible in {wait} s",
        )


def accept(
    db: Session, settings: Settings, user: User, split: str, name: str, public: bool, data: bytes | BinaryIO
) -> Submission:
    """Check a submission cheaply, count it against the account's limits, and store it with its queued job; an
    evaluation worker scores it later. Only the ZIP's directory (entry names and sizes) is read here: parsing
    the pose lines is the workers' job.

    Args:
        db: The request's database session; committed.
        settings: The server's settings (splits, limits, quotas, the dataset's scenes).
        user: The submitting account.
        split: The split it is for (one of ``settings.splits``).
        name: Its name (checked; empty: "unnamed").
        public: Whether it shows on the leaderboard once scored.
        data: The ZIP: bytes, or a file (the spooled upload), copied into the database in chunks and never
            read whole.

    Returns:
        The stored submission, status ``queued``.

    Raises:
        UploadError: An unknown split (422), a ZIP that is empty, invalid or over the limits (400, 413, 422),
            the account's test or val submission limit (429), or its storage quota (413).
    """
    if split not in settings.splits:
        raise UploadError(422, f"split must be one of {', '.join(settings.splits)}; got {split!r}")
    name = check_name(name, settings.limits.max_name_chars) or "unnamed"
    f = io.BytesIO(data) if isinstance(data, (bytes, bytearray)) else data
    size = check_submission_zip(f, settings.limits, split, known_scenes(settings, split)).zip_bytes
    lock_user(db, user.id)  # the limits are counted inside the write transaction that stores the row
    if split == "test":
        _limit_reached(db, user, "test", 86400, daily_test_limit(settings, user), "daily")
    else:
        hourly = settings.val_hourly_limit if settings.val_hourly_limit > 0 else UNLIMITED  # 0: no limit
        _limit_reached(db, user, split, 3600, hourly, "hourly")
    check_quota(db, settings, user.id, size, "this submission")
    sub = Submission(
        user_id=user.id,
        split=split,
        name=name,
        public=bool(public),
        status="uploading",
        size_bytes=size,
        sha256="",
        created_at=now(),
        lease_until=now() + UPLOAD_LEASE_SECONDS,
    )
    db.add(sub)
    db.commit()
    try:
        _, sha = copy_in(db, sub.id, f)
    except BaseException:
        db.rollback()
        db.execute(delete(Submission).where(Submission.id == sub.id))
        db.commit()
        raise
    sub.sha256, sub.status, sub.lease_until = sha, "queued", None
    db.commit()
    return sub


@overload
def shown_metrics(split: str, metrics: dict) -> dict: ...
@overload
def shown_metrics(split: str, metrics: None) -> None: ...
@overload
def shown_metrics(split: str, metrics: dict | None) -> dict | None: ...
def shown_metrics(split: str, metrics: dict | None) -> dict | None:
    """Stored metrics as shown: for ``test`` without medians and AUCs, rounded, also where a result was stored
    before these rules (``disclosure.py``)."""
    return without_withheld(metrics) if split == "test" and metrics else metrics


def visible(sub: Submission | None, user: User | None, withdrawn: bool = False) -> bool:
    """Whether ``user`` may see ``sub``: public, or theirs (admins: any). A withdrawn one only where
    ``withdrawn`` is asked for, and then only by its owner or an admin (their history lists it)."""
    if sub is None:
        return False
    mine = user is not None and (user.id == sub.user_id or user.is_admin)
    if sub.status == "withdrawn":
        return withdrawn and mine
    return sub.public or mine


def visible_submission(
    db: Session, user: User | None, sid: str, what: str = "no such submission", withdrawn: bool = False
) -> Submission:
    """A submission the caller may see: public, or theirs (admins: any).

    Args:
        db: The request's database session.
        user: The caller's account; None: nobody signed in.
        sid: The submission's id.
        what: The start of the 404's message.
        withdrawn: Whether its owner (and admins) may see it once withdrawn, too.

    Returns:
        The submission.

    Raises:
        HTTPException: 404 ``"{what} (or it is private)"`` when there is none the caller may see.
    """
    sub = db.get(Submission, sid) if len(sid) <= 32 else None
    if sub is None or not visible(sub, user, withdrawn):
        raise HTTPException(404, f"{what} (or it is private)")
    return sub


def to_json(db: Session, sub: Submission, owner_name: str | None = None) -> dict:
    """What a viewer may see of a submission, as the API shows it (``SubmissionOut``): for ``test`` the
    aggregate scores only, rounded, without medians, per-scene data or plots.

    Args:
        db: The request's database session.
        sub: A submission the viewer may see (``visible_submission``).
        owner_name: Its owner's account name, when the caller has it already (else it is read).

    Returns:
        Its record (``id``, ``name``, ``split``, ``public``, ``user``, ``status``, times, ``size_bytes``,
        ``sha256``, URLs), its ``metrics`` once scored (else None), ``problems`` and ``plots``; besides for val
        ``per_scene``, and ``eval_seconds`` once scored.
    """
    res = db.get(Result, sub.id)
    plots: list[str] = []
    if sub.split != "test" and res is not None:
        plots = list(db.scalars(select(Plot.name).where(Plot.submission_id == sub.id)).all())
        if not plots and db.scalar(select(Result.plot_data.is_not(None)).where(Result.submission_id == sub.id)):
            plots = list(PLOT_NAMES)  # rendered on first view
    owner = owner_name or db.scalar(select(User.name).where(User.id == sub.user_id))
    out = {
        "id": sub.id,
        "name": sub.name,
        "split": sub.split,
        "public": sub.public,
        "user": owner,
        "status": sub.status,
        "attempts": sub.attempts,
        "error": sub.error,
        "created_at": sub.created_at,
        "started_at": sub.started_at,
        "finished_at": sub.finished_at,
        "withdrawn_at": sub.finished_at if sub.status == "withdrawn" else None,
        "size_bytes": sub.size_bytes,
        "sha256": sub.sha256,
        "url": f"/submissions/{sub.id}",
        "api_url": f"/api/submissions/{sub.id}",
        "metrics": shown_metrics(sub.split, res.metrics) if res else None,
        "problems": res.problems if res else [],
        "plots": [f"/submissions/{sub.id}/plots/{n}.png" for n in sorted(plots)],
    }
    if sub.split != "test":
        out["per_scene"] = res.per_scene if res else None
    if res:
        out["eval_seconds"] = res.eval_seconds
    return out


_PLOT_LOCK = threading.Lock()


def stored_plot(db: Session, sub: Submission, name: str) -> bytes | None:
    """A figure of a submission as stored (None: not drawn yet, or none for ``test``); the read is committed."""
    if sub.split == "test":
        return None
    png = db.scalar(select(Plot.png).where(Plot.submission_id == sub.id, Plot.name == name))
    db.commit()  # never wait on a lock inside a transaction (SQLite: it would hold the write lock)
    return png


def needs_drawing(sub: Submission, name: str) -> bool:
    """Whether a figure not stored yet can be drawn (a val figure of the benchmark's)."""
    return sub.split != "test" and name in PLOT_NAMES


def plot_png(db: Session, sub: Submission, name: str) -> bytes | None:
    """A figure of a scored val submission: the stored PNG, or rendered from the packed report on its first view
    (and then stored).

    Args:
        db: The request's database session; committed (no transaction is held while drawing).
        sub: A submission the viewer may see.
        name: The figure's name (``scoring.PLOT_NAMES``).

    Returns:
        The PNG bytes; None for ``test``, an unknown name, or a submission without a report.
    """
    png = stored_plot(db, sub, name)
    if png is not None or sub.split == "test" or name not in PLOT_NAMES:
        return png
    with _PLOT_LOCK:  # one rendering per process at a time; others then find the stored PNGs
        png = db.scalar(select(Plot.png).where(Plot.submission_id == sub.id, Plot.name == name))
        if png is not None:
            db.commit()
            return png
        data = db.scalar(select(Result.plot_data).where(Result.submission_id == sub.id))
        db.commit()  # do not hold a transaction (SQLite: the write lock) while drawing
        if data is None:
            return None
        pngs = render_plots(unpack_report(data))
        # stored by a write session of its own: ``db`` may be a GET's read-only one
        with Session(db.get_bind().execution_options(**{READ_ONLY: False})) as w:
            try:
                w.add_all(Plot(submission_id=sub.id, name=n, png=p) for n, p in pngs.items())
                w.commit()
            except IntegrityError:  # another API process stored them first
                w.rollback()
        return pngs.get(name)
