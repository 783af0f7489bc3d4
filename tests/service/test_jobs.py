"""Job claiming on a real database (SQLite file, and PostgreSQL when configured): concurrent claims never
share a job, a dead worker's job is retried after its lease, a stale worker cannot write, results are written
once; and a real worker process picks up an abandoned job."""

from __future__ import annotations

import threading
import time

import pytest
from sqlalchemy import func, select

from mapfree.service.accounts import tokens as auth
from mapfree.service.config import Settings
from mapfree.service.database.models import Result, Submission, SubmissionFile, init_db, make_engine, session_factory
from mapfree.service.leaderboard import jobs

from .conftest import BACKENDS, db_url_for, make_submission


@pytest.fixture(params=BACKENDS)
def sessions(request, tmp_path):
    url = db_url_for(request.param, tmp_path)
    engine = make_engine(url)
    init_db(engine)
    yield url, session_factory(engine)
    engine.dispose()


def _enqueue(sessions, n: int, data: bytes = b"zip", split: str = "val") -> list[str]:
    with sessions.begin() as db:
        user, _ = auth.create_user(db, f"u{time.time_ns()}")
        subs = [
            Submission(user_id=user.id, split=split, name=f"j{i}", sha256="0" * 64, created_at=time.time() + i * 1e-3)
            for i in range(n)
        ]
        db.add_all(subs)
        db.flush()
        db.add_all(SubmissionFile(submission_id=s.id, data=data) for s in subs)
        return [s.id for s in subs]


def test_concurrent_claims_are_exclusive(sessions):
    _, S = sessions
    ids = _enqueue(S, 40)
    claimed: list[list[str]] = [[] for _ in range(4)]

    def work(k: int) -> None:
        while (c := jobs.claim(S, f"w{k}", 30, 3)) is not None:
            claimed[k].append(c.submission_id)
            assert jobs.finish(S, c, f"w{k}", {"metrics": {}}, None, 0.0)

    threads = [threading.Thread(target=work, args=(k,)) for k in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    flat = [x for c in claimed for x in c]
    assert sorted(flat) == sorted(ids) and len(set(flat)) == len(flat)
    with S() as db:
        assert db.scalar(select(func.count()).select_from(Result)) == 40


def test_expired_lease_is_retried_and_stale_worker_cannot_write(sessions, monkeypatch):
    _, S = sessions
    (sid,) = _enqueue(S, 1)
    clock = [time.time()]  # the jobs' clock, moved on by hand: no race with a loaded machine's scheduler
    monkeypatch.setattr(jobs, "now", lambda: clock[0])
    dead = jobs.claim(S, "dead", 0.5, 3)
    assert dead.submission_id == sid and dead.attempt == 1
    assert jobs.claim(S, "other", 0.5, 3) is None  # leased
    clock[0] += 0.7
    retry = jobs.claim(S, "alive", 30, 3)
    assert retry.submission_id == sid and retry.attempt == 2
    assert not jobs.heartbeat(S, dead, "dead", 30)
    assert not jobs.finish(S, dead, "dead", {"metrics": {"x": 1.0}}, None, 0.0)  # too late
    assert jobs.finish(S, retry, "alive", {"metrics": {"x": 2.0}}, None, 0.0)
    assert not jobs.finish(S, retry, "alive", {"metrics": {"x": 3.0}}, None, 0.0)  # only once
    with S() as db:
        assert db.get(Result, sid).metrics == {"x": 2.0} and db.get(Submission, sid).status == "done"


def test_job_abandoned_too_often_fails_cleanly(sessions):
    _, S = sessions
    (sid,) = _enqueue(S, 1)
    for _ in range(2):
        assert jobs.claim(S, "flaky", 0.01, 2) is not None
        time.sleep(0.05)
    assert jobs.claim(S, "w", 0.01, 2) is None
    with S() as db:
        sub = db.get(Submission, sid)
        assert sub.status == "failed" and "interrupted" in sub.error


def test_worker_process_finishes_an_abandoned_job(sessions, split_data):
    from mapfree.service.leaderboard import worker

    url, S = sessions
    (sid,) = _enqueue(S, 1, make_submission(split_data.root / "val", noise=0.2))
    assert jobs.claim(S, "killed-worker", 0.3, 3) is not None  # claimed, then its worker "dies"
    time.sleep(0.4)
    settings = Settings(
        db_url=url, data_root=split_data.root, gt_root=split_data.gt, lease_seconds=5, poll_seconds=0.05
    )
    assert worker.run(settings, worker_id="rescuer", max_jobs=1) == 1
    with S() as db:
        sub, res = db.get(Submission, sid), db.get(Result, sid)
        assert sub.status == "done" and sub.attempts == 2 and res.worker_id == "rescuer"
        assert res.metrics["AUC @ VCRE < 90px"] is not None
