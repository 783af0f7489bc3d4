"""What an account does with its own submissions: withdraw one (results, plots and ZIP deleted; the row stays so
that it still counts against the quotas), download its ZIP, describe its method (the test quota it has left is
``accounts.quota.test_quota``).

Withdrawing is final: every later action of the owner on that submission (visibility, method, withdrawing again,
downloading) is refused with a 409 ``Withdrawn`` that says so; only its owner (and admins) still see its record,
marked withdrawn (``GET /api/submissions/{id}``, its page); boards, compare and everyone else: 404."""

from __future__ import annotations

import time

from fastapi import HTTPException
from fastapi.responses import Response, StreamingResponse
from sqlalchemy import delete
from sqlalchemy.orm import Session, sessionmaker

from ..database.models import MethodInfo, Plot, Result, Submission, SubmissionFile, User, now
from .storage import is_stored, stream_zip

WITHDRAWN = "withdrawn"


class Withdrawn(HTTPException):
    """A 409: the owner asked to change (or download) a submission that was withdrawn. The web pages answer it
    with the owner's history page and this message above it."""

    def __init__(self, sub: Submission):
        when = time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime(sub.finished_at)) if sub.finished_at else "earlier"
        super().__init__(
            409,
            f"submission {sub.id} ({sub.name!r}) was withdrawn on {when}: its results and ZIP "
            "are deleted and it stays off every board for good, so its visibility, method "
            "description and ZIP can no longer be changed or downloaded (upload it again as a "
            "new submission)",
        )


def own_submission(db: Session, user: User, sid: str) -> Submission:
    """One of the caller's submissions (admins: any) that can still change.

    Args:
        db: The request's database session.
        user: The caller's account.
        sid: The submission's id.

    Returns:
        The submission.

    Raises:
        HTTPException: 404 when there is no such submission of theirs.
        Withdrawn: 409 when it was withdrawn.
    """
    sub = db.get(Submission, sid) if len(sid) <= 32 else None
    if sub is None or (sub.user_id != user.id and not user.is_admin):
        raise HTTPException(404, "no such submission of yours")
    if sub.status == WITHDRAWN:
        raise Withdrawn(sub)
    return sub


def withdraw(db: Session, sub: Submission) -> None:
    """Take a submission off every board for good: results, plots, method description and ZIP deleted, status
    ``withdrawn``. A job still queued is never run; one running is dropped (its worker no longer owns it). The
    row stays, so that the submission still counts against the account's limits.

    Args:
        db: The request's database session; committed.
        sub: The submission (``own_submission``).
    """
    for table in (Plot, Result, MethodInfo, SubmissionFile):
        db.execute(delete(table).where(table.submission_id == sub.id))
    sub.status, sub.public, sub.lease_until, sub.worker_id = WITHDRAWN, False, None, None
    sub.finished_at = now()
    db.commit()


def zip_response(sessions: sessionmaker[Session], db: Session, sub: Submission) -> Response:
    """The stored ZIP of a submission as a download, streamed chunk by chunk, each read in a short transaction of
    its own (``storage.stream_zip``).

    Args:
        sessions: The app's session factory (``state.SessionsDep``): each chunk is read in a session of its own.
        db: The request's database session; committed.
        sub: The submission (``own_submission``).

    Returns:
        A streaming ``application/zip`` attachment.

    Raises:
        HTTPException: 410 once the ZIP is no longer stored (``Settings.zip_retention_days``).
    """
    if not is_stored(db, sub.id):
        raise HTTPException(410, "the ZIP of this submission is no longer stored")
    db.commit()
    name = f"mapfree-{sub.split}-{sub.id}.zip"
    return StreamingResponse(
        stream_zip(sessions, sub.id),
        media_type="application/zip",
        headers={
            "Content-Disposition": f'attachment; filename="{name}"',
            "Content-Length": str(sub.size_bytes),
            "Cache-Control": "private",
        },
    )
