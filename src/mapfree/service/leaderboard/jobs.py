"""Evaluation jobs: atomic claiming with leases, heartbeats, and results written exactly once.

A claim is a conditional ``UPDATE … WHERE status = 'queued' (or an expired lease)`` whose row count must be 1,
inside a transaction that already holds the candidate row: ``SELECT … FOR UPDATE SKIP LOCKED`` on PostgreSQL,
``BEGIN IMMEDIATE`` (the database write lock) on SQLite. A worker that dies stops renewing its lease, and the
next claim after the lease expires takes the job again (up to ``max_attempts``). Finishing is conditional on
still owning the job (same worker and attempt), and the result row's primary key is the submission id.
"""

from __future__ import annotations

from dataclasses import dataclass

from sqlalchemy import and_, or_, select, update
from sqlalchemy.orm import Session, sessionmaker

from ..database.models import Result, Submission, WorkerRow, changed_rows, now


@dataclass(frozen=True)
class Claim:
    submission_id: str
    attempt: int
    split: str


def _claimable(t: float):
    return or_(Submission.status == "queued", and_(Submission.status == "running", Submission.lease_until < t))


def claim(sessions: sessionmaker, worker_id: str, lease_seconds: float, max_attempts: int) -> Claim | None:
    """Take the oldest claimable job for ``worker_id``, or None when there is none."""
    while True:
        with sessions.begin() as db:
            t = now()
            cand = db.execute(
                select(Submission.id, Submission.attempts, Submission.split)
                .where(_claimable(t))
                .order_by(Submission.created_at, Submission.id)
                .limit(1)
                .with_for_update(skip_locked=True)
            ).first()
            if cand is None:
                return None
            sid, attempts, split = cand
            if attempts >= max_attempts:  # died too often: give up on it, look for another
                db.execute(
                    update(Submission)
                    .where(Submission.id == sid, _claimable(t))
                    .values(
                        status="failed",
                        finished_at=t,
                        lease_until=None,
                        error=f"evaluation interrupted {attempts} times (worker lost); giving up",
                    )
                )
                continue
            res = db.execute(
                update(Submission)
                .where(Submission.id == sid, _claimable(t))
                .values(
                    status="running",
                    worker_id=worker_id,
                    lease_until=t + lease_seconds,
                    attempts=Submission.attempts + 1,
                    started_at=t,
                )
            )
            if changed_rows(res) == 1:
                return Claim(sid, attempts + 1, split)
        # somebody else got it between our read and write (cannot happen under the locks above): retry


def _owned(c: Claim, worker_id: str):
    return and_(
        Submission.id == c.submission_id,
        Submission.status == "running",
        Submission.worker_id == worker_id,
        Submission.attempts == c.attempt,
    )


def heartbeat(sessions: sessionmaker, c: Claim, worker_id: str, lease_seconds: float) -> bool:
    """Extend the lease; False means the job is no longer ours."""
    with sessions.begin() as db:
        res = db.execute(update(Submission).where(_owned(c, worker_id)).values(lease_until=now() + lease_seconds))
        return changed_rows(res) == 1


def finish(
    sessions: sessionmaker, c: Claim, worker_id: str, result: dict, plot_data: bytes | None, eval_seconds: float
) -> bool:
    """Store the result once, atomically with the status change; False if the job was taken from us."""
    with sessions.begin() as db:
        res = db.execute(
            update(Submission)
            .where(_owned(c, worker_id))
            .values(status="done", finished_at=now(), lease_until=None, error=None)
        )
        if changed_rows(res) != 1:
            return False  # nothing changed; the transaction commits empty
        db.add(
            Result(
                submission_id=c.submission_id,
                metrics=result["metrics"],
                per_scene=result.get("per_scene"),
                problems=result.get("problems", []),
                plot_data=plot_data,
                worker_id=worker_id,
                attempt=c.attempt,
                eval_seconds=eval_seconds,
            )
        )
        db.execute(
            update(WorkerRow)
            .where(WorkerRow.id == worker_id)
            .values(jobs_done=WorkerRow.jobs_done + 1, last_seen=now())
        )
    return True


def fail(sessions: sessionmaker, c: Claim, worker_id: str, error: str) -> bool:
    """A deterministic failure (the submission cannot be scored): recorded once, not retried."""
    with sessions.begin() as db:
        res = db.execute(
            update(Submission)
            .where(_owned(c, worker_id))
            .values(status="failed", finished_at=now(), lease_until=None, error=error[:2000])
        )
        return changed_rows(res) == 1


def counts(db: Session) -> dict[str, int]:
    from sqlalchemy import func

    rows = db.execute(select(Submission.status, func.count()).group_by(Submission.status)).all()
    return {s: int(n) for s, n in rows}
