"""Stored submission ZIPs, streamed in chunks: an upload is copied from its spooled file into the database in
1 MiB rows (a few per transaction, so no request waits long for SQLite's write lock), and a worker copies them
back to a file; neither holds a whole ZIP in memory. Retention of the stored ZIPs, and the sweep of uploads cut
off mid-copy."""

from __future__ import annotations

import hashlib
from collections.abc import Iterator
from typing import BinaryIO

from sqlalchemy import and_, delete, exists, insert, or_, select, update
from sqlalchemy.orm import Session

from ..database.models import Submission, SubmissionFile, ZipChunk, changed_rows, now

CHUNK_BYTES = 1 << 20


CHUNKS_PER_TRANSACTION = 4


#: An upload still being copied after this long was cut off (its API process died): swept with its rows. Rows
#: written since uploads hold a lease are swept as soon as it lapses.
STALE_UPLOAD_SECONDS = 3600.0


#: An upload renews its lease (``Submission.lease_until``) with every few chunks it stores; one whose lease
#: lapsed was cut off (its API process killed mid-copy) and is removed, which refunds its test evaluation.
UPLOAD_LEASE_SECONDS = 120.0


def copy_in(db: Session, sid: str, f: BinaryIO) -> tuple[int, str]:
    """Store the file ``f`` as submission ``sid``'s ZIP (the submission row is committed already), committing
    every few chunks -> (bytes, sha256)."""
    f.seek(0)
    sha, size, seq = hashlib.sha256(), 0, 0
    while True:
        chunk = f.read(CHUNK_BYTES)
        if seq > 0 and not chunk:
            break
        sha.update(chunk)
        size += len(chunk)
        # Core inserts: the ORM would keep every chunk alive in the session until the commit
        db.execute(
            insert(SubmissionFile).values(submission_id=sid, data=chunk)
            if seq == 0
            else insert(ZipChunk).values(submission_id=sid, seq=seq, data=chunk)
        )
        seq += 1
        if seq % CHUNKS_PER_TRANSACTION == 0 or len(chunk) < CHUNK_BYTES:
            db.execute(update(Submission).where(Submission.id == sid).values(lease_until=now() + UPLOAD_LEASE_SECONDS))
            db.commit()
        if len(chunk) < CHUNK_BYTES:
            break
    db.commit()
    return size, sha.hexdigest()


def chunks(db: Session, sid: str) -> Iterator[bytes]:
    """The stored ZIP of ``sid`` chunk by chunk (nothing when it is not stored), one short read transaction per
    chunk. A ZIP stored whole in ``submission_files`` (before chunking) comes out as one chunk."""
    first = db.scalar(select(SubmissionFile.data).where(SubmissionFile.submission_id == sid))
    db.commit()
    if first is None:
        return
    yield first
    seq = 1
    while (
        data := db.scalar(select(ZipChunk.data).where(ZipChunk.submission_id == sid, ZipChunk.seq == seq))
    ) is not None:
        db.commit()
        yield data
        seq += 1
    db.commit()


def is_stored(db: Session, sid: str) -> bool:
    """Whether submission ``sid``'s ZIP is still stored."""
    return db.scalar(select(exists().where(SubmissionFile.submission_id == sid))) or False


def stream_zip(sessions, sid: str) -> Iterator[bytes]:
    """The stored ZIP of ``sid`` for a download, chunk by chunk, each read in a session of its own: a download
    holds one chunk in memory, not the ZIP (40 parallel downloads of one 49 MB submission took the API to
    1.9 GB when each was joined whole)."""
    with sessions() as db:
        yield from chunks(db, sid)


def sweep(db: Session, retention_days: float) -> int:
    """Delete the ZIPs of submissions finished more than ``retention_days`` ago (0: keep them), and uploads cut
    off mid-copy; returns how many submissions lost their ZIP. Results and scores stay."""
    t = now()
    gone = 0
    if retention_days > 0:
        old = select(Submission.id).where(
            Submission.status.in_(("done", "failed")), Submission.finished_at < t - retention_days * 86400
        )
        gone += changed_rows(db.execute(delete(SubmissionFile).where(SubmissionFile.submission_id.in_(old))))
    return gone + drop_interrupted_uploads(db)


def drop_interrupted_uploads(db: Session) -> int:
    """Delete the submissions whose upload was cut off mid-copy (lease lapsed; rows from before upload leases:
    an hour old), with their chunks: the quota and the test evaluation they counted against are refunded."""
    t = now()
    stale = select(Submission.id).where(
        Submission.status == "uploading",
        or_(
            Submission.lease_until < t,
            and_(Submission.lease_until.is_(None), Submission.created_at < t - STALE_UPLOAD_SECONDS),
        ),
    )
    return changed_rows(db.execute(delete(Submission).where(Submission.id.in_(stale))))
