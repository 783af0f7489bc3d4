"""The storage quota of an account: stored submission ZIPs and anchor photos, counted in the transaction that stores
them, with the account's row locked."""

from __future__ import annotations

from typing import Any

from sqlalchemy import exists, func, or_, select
from sqlalchemy.orm import Session

from ..config import Settings
from ..database.models import Anchor, AnchorPhoto, Submission, SubmissionFile, User
from ..inputs import UploadError


def _blob_bytes(table) -> Any:
    """The bytes of a row's image and (optional) depth map, as a SQL expression."""
    return func.length(table.image) + func.coalesce(func.length(table.depth), 0)


def stored_bytes(db: Session, user_id: int) -> int:
    """Bytes ``user_id`` keeps stored, what the storage quota counts: submission ZIPs still stored or being
    copied in (an upload's bytes are reserved by its row, written in the transaction that checks the quota,
    and released with that row when the copy fails), and the image and depth bytes of every photo of their
    anchors."""
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
    """A 413 when storing ``adding`` more bytes (``what``: "this submission", "these photos") would take
    ``user_id`` past the storage quota (0: none). Locks the user's writes (``lock_user``): store the bytes in
    this same transaction, so that a concurrent upload counts them."""
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
