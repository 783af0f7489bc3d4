"""Submissions: accept an upload (validated, stored and queued before it is acknowledged), show results,
and render plots. Shared by the JSON API and the web pages (leaderboards: ``leaderboard.py``)."""

from __future__ import annotations

import hashlib
import threading

from sqlalchemy import func, select
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from .config import Settings
from .db import Plot, Result, Submission, SubmissionFile, User, now
from .evaluation import PLOT_NAMES, SubmissionRejected, known_scenes, precheck, render_plots, unpack_report
from .uploads import UploadError, check_submission_zip


def daily_test_limit(settings: Settings, user: User) -> int:
    return user.test_daily_limit if user.test_daily_limit is not None else settings.test_daily_limit


def accept(db: Session, settings: Settings, user: User, split: str, name: str, public: bool,
           data: bytes) -> Submission:
    """Validate and store a submission with its queued job, in one committed transaction."""
    if split not in settings.splits:
        raise UploadError(422, f"split must be one of {', '.join(settings.splits)}; got {split!r}")
    name = (name or "").strip() or "unnamed"
    if len(name) > settings.limits.max_name_chars:
        raise UploadError(422, f"name is longer than {settings.limits.max_name_chars} characters")
    if any(ord(c) < 32 for c in name):
        raise UploadError(422, "name contains control characters")
    check_submission_zip(data, settings.limits, split, known_scenes(settings, split))
    try:
        precheck(data, split)
    except SubmissionRejected as e:
        raise UploadError(422, f"malformed submission: {e}") from None
    if split == "test":  # counted inside the write transaction (SQLite: BEGIN IMMEDIATE; PG: row lock on user)
        if db.get_bind().dialect.name == "postgresql":
            db.execute(select(User.id).where(User.id == user.id).with_for_update())
        since = now() - 86400
        used = db.scalar(select(func.count()).select_from(Submission).where(
            Submission.user_id == user.id, Submission.split == "test", Submission.created_at > since)) or 0
        limit = daily_test_limit(settings, user)
        if used >= limit:
            first = db.scalar(select(func.min(Submission.created_at)).where(
                Submission.user_id == user.id, Submission.split == "test", Submission.created_at > since))
            wait = int((first or now()) + 86400 - now()) + 1
            raise UploadError(429, f"daily limit reached: {limit} test evaluations per 24 h; "
                                   f"the next one is possible in {wait} s")
    sub = Submission(user_id=user.id, split=split, name=name, public=bool(public), status="queued",
                     size_bytes=len(data), sha256=hashlib.sha256(data).hexdigest(), created_at=now())
    db.add(sub)
    db.flush()
    db.add(SubmissionFile(submission_id=sub.id, data=data))
    db.commit()
    return sub


def visible(sub: Submission | None, user: User | None) -> bool:
    if sub is None or sub.status == "withdrawn":
        return False
    return sub.public or (user is not None and (user.id == sub.user_id or user.is_admin))


def to_json(db: Session, sub: Submission, owner_name: str | None = None) -> dict:
    """What a viewer may see of a submission (test: aggregates only, no per-scene data, no plots)."""
    res = db.get(Result, sub.id)
    plots: list[str] = []
    if sub.split != "test" and res is not None:
        plots = list(db.scalars(select(Plot.name).where(Plot.submission_id == sub.id)).all())
        if not plots and db.scalar(select(Result.plot_data.is_not(None)).where(Result.submission_id == sub.id)):
            plots = list(PLOT_NAMES)  # rendered on first view
    owner = owner_name or db.scalar(select(User.name).where(User.id == sub.user_id))
    out = {
        "id": sub.id, "name": sub.name, "split": sub.split, "public": sub.public, "user": owner,
        "status": sub.status, "attempts": sub.attempts, "error": sub.error,
        "created_at": sub.created_at, "started_at": sub.started_at, "finished_at": sub.finished_at,
        "size_bytes": sub.size_bytes, "sha256": sub.sha256,
        "url": f"/submissions/{sub.id}", "api_url": f"/api/submissions/{sub.id}",
        "metrics": res.metrics if res else None, "problems": res.problems if res else [],
        "plots": [f"/submissions/{sub.id}/plots/{n}.png" for n in sorted(plots)],
    }
    if sub.split != "test":
        out["per_scene"] = res.per_scene if res else None
    if res:
        out["eval_seconds"] = res.eval_seconds
    return out


_PLOT_LOCK = threading.Lock()


def plot_png(db: Session, sub: Submission, name: str) -> bytes | None:
    """A figure of a (non-test) submission: stored PNG, or rendered from the packed report on first view."""
    if sub.split == "test":
        return None
    png = db.scalar(select(Plot.png).where(Plot.submission_id == sub.id, Plot.name == name))
    db.commit()  # never wait on the lock inside a transaction (SQLite: it would hold the write lock)
    if png is not None or name not in PLOT_NAMES:
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
        try:
            for n, p in pngs.items():
                db.add(Plot(submission_id=sub.id, name=n, png=p))
            db.commit()
        except IntegrityError:  # another API process stored them first
            db.rollback()
        return pngs.get(name)
