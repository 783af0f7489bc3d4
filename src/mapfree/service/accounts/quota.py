"""An account's quotas: the storage its submission ZIPs and anchor photos take, counted in the transaction that
stores them with the account's row locked; and the test evaluations it may make per day."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from sqlalchemy import exists, func, or_, select
from sqlalchemy.orm import Session

from ..config import UNLIMITED, Settings, shown_limit
from ..database.models import Anchor, AnchorPhoto, Submission, SubmissionFile, User, now
from ..inputs import UploadError


def _blob_bytes(table) -> Any:
    """The bytes of a row's image and (optional) depth map, as a SQL expression."""
    return func.length(table.image) + func.coalesce(func.length(table.depth), 0)


def stored_bytes(db: Session, user_id: int) -> int:
    """The bytes an account keeps stored, what the storage quota counts: submission ZIPs still stored or being
    copied in (an upload's bytes are reserved by its row, written in the transaction that checks the quota, and
    released with that row when the copy fails), and the image and depth bytes of every photo of its anchors.

    Args:
        db: The request's database session.
        user_id: The account.
    """
    stored = exists().where(SubmissionFile.submission_id == Submission.id)
    zips = db.scalar(
        select(func.coalesce(func.sum(Submission.size_bytes), 0)).where(
            Submission.user_id == user_id, or_(stored, Submission.status == "uploading")
        )
    )
    firsts = db.scalar(select(func.coalesce(func.sum(_blob_bytes(Anchor)), 0)).where(Anchor.user_id == user_id))
    photos = db.scalar(
        select(func.coalesce(func.sum(_blob_bytes(AnchorPhoto)), 0))
        .join(Anchor, Anchor.id == AnchorPhoto.anchor_id)
        .where(Anchor.user_id == user_id)
    )
    return int(zips or 0) + int(firsts or 0) + int(photos or 0)


def lock_user(db: Session, user_id: int) -> None:
    """Serialise the writes counted against ``user_id``'s limits until this transaction ends: on PostgreSQL the
    user row is locked (``SELECT … FOR UPDATE``); on SQLite every write transaction is ``BEGIN IMMEDIATE``
    already, one at a time. Without it two concurrent uploads could both pass the same check."""
    if db.get_bind().dialect.name == "postgresql":
        db.execute(select(User.id).where(User.id == user_id).with_for_update())


def check_quota(db: Session, settings: Settings, user_id: int, adding: int, what: str) -> None:
    """Refuse bytes that would take an account past its storage quota. Locks the account's writes
    (``lock_user``): store the bytes in this same transaction, so that a concurrent upload counts them.

    Args:
        db: The request's database session.
        settings: The server's settings (``storage_quota_bytes``; 0: no quota).
        user_id: The account.
        adding: The bytes about to be stored.
        what: What they are, for the message ("this submission", "this anchor's photos").

    Raises:
        UploadError: 413 naming the quota, what is stored and what would be added.
    """
    quota = settings.storage_quota_bytes
    if quota <= 0:
        return
    lock_user(db, user_id)
    used = stored_bytes(db, user_id)
    if used + adding > quota:
        raise UploadError(
            413,
            f"storage quota reached: your stored submission ZIPs and anchor photos may total "
            f"{quota} bytes; {used} are stored and {what} would add {adding}; withdraw old "
            "submissions, delete anchors or anchor photos, or wait for ZIPs older than "
            f"{settings.zip_retention_days:g} days to be deleted",
        )


# ---------------------------------------------------------------------------------- test evaluations


def daily_test_limit(settings: Settings, user: User) -> int:
    """The account's own limit when set, else the server's; ``UNLIMITED`` (negative): no limit, 0: none."""
    limit = user.test_daily_limit if user.test_daily_limit is not None else settings.test_daily_limit
    return UNLIMITED if limit < 0 else limit


def recent_count(db: Session, user: User, split: str, window_s: float) -> int:
    """How many submissions ``user`` made to ``split`` in the last ``window_s`` (withdrawn ones included)."""
    return int(
        db.scalar(
            select(func.count())
            .select_from(Submission)
            .where(Submission.user_id == user.id, Submission.split == split, Submission.created_at > now() - window_s)
        )
        or 0
    )


@dataclass
class Quota:
    """Test evaluations: used in the last 24 h (withdrawn ones included), the limit, and what is left; both
    ``"unlimited"`` when the account has no limit."""

    used: int
    limit: int  # UNLIMITED (negative): no limit

    @property
    def left(self) -> int | str:
        return shown_limit(self.limit) if self.limit < 0 else max(0, self.limit - self.used)

    @property
    def shown_limit(self) -> int | str:
        return shown_limit(self.limit)


def test_quota(db: Session, settings: Settings, user: User) -> Quota:
    """The test evaluations an account has used in the last 24 h and may still make.

    Args:
        db: The request's database session.
        settings: The server's settings (its daily test limit).
        user: The account (its own limit, when set, replaces the server's).
    """
    return Quota(recent_count(db, user, "test", 86400), int(daily_test_limit(settings, user)))
