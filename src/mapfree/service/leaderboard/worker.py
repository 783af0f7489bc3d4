"""Evaluation worker: claim a job, score it with the benchmark, write the result once; repeat.

Run as ``python -m mapfree.service.leaderboard.worker --db URL --data ROOT [--gt ROOT]`` (``mapfree serve`` starts N of
them). SIGTERM finishes the current job first; SIGKILL loses nothing (the lease expires and another worker
retries the job).
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import socket
import tempfile
import threading
import time
from pathlib import Path

from sqlalchemy import delete, update

from ..config import Limits, Settings
from ..database.models import WorkerRow, init_db, make_engine, new_id, now, session_factory
from . import jobs, storage
from .scoring import SubmissionRejected, check_ground_truth, score

log = logging.getLogger("mapfree.worker")


#: How often a worker says it is alive (``workers.last_seen``), busy or idle; ``/health`` forgets it after 3 misses.
SEEN_SECONDS = 5.0
#: How often a worker deletes stored ZIPs past their retention.
SWEEP_SECONDS = 600.0


def seen(sessions, worker_id: str) -> None:
    with sessions.begin() as db:
        db.execute(update(WorkerRow).where(WorkerRow.id == worker_id).values(last_seen=now()))


class _Heartbeat(threading.Thread):
    """Renews a claim's lease every third of its length until stopped."""

    def __init__(self, sessions, claim: jobs.Claim, worker_id: str, lease: float):
        super().__init__(daemon=True)
        self.args, self.stopped, self.lost = (sessions, claim, worker_id, lease), threading.Event(), False

    def run(self) -> None:
        sessions, claim, worker_id, lease = self.args
        while not self.stopped.wait(min(lease / 3, SEEN_SECONDS)):
            try:
                if not jobs.heartbeat(sessions, claim, worker_id, lease):
                    self.lost = True
                    return
                seen(sessions, worker_id)
            except Exception:  # a DB hiccup: try again next beat
                log.warning("heartbeat failed", exc_info=True)


def process(sessions, settings: Settings, claim: jobs.Claim, worker_id: str) -> str:
    """Evaluate one claimed job -> final status ('done', 'failed' or 'lost')."""
    beat = _Heartbeat(sessions, claim, worker_id, settings.lease_seconds)
    beat.start()
    t0 = time.perf_counter()
    try:
        with tempfile.TemporaryDirectory(prefix="mapfree-job-") as d:
            path = Path(d) / "submission.zip"
            with open(path, "wb") as f, sessions() as db:
                n = sum(f.write(chunk) for chunk in storage.chunks(db, claim.submission_id))
            if n == 0:
                raise SubmissionRejected("submission file is missing")
            result, plot_data = score(settings, claim.split, path)
        ok = jobs.finish(sessions, claim, worker_id, result, plot_data, time.perf_counter() - t0)
        status = "done" if ok else "lost"
    except SubmissionRejected as e:
        status = "failed" if jobs.fail(sessions, claim, worker_id, f"cannot score submission: {e}") else "lost"
    except Exception as e:
        log.exception("evaluation crashed", extra={"submission": claim.submission_id})
        status = (
            "failed"
            if jobs.fail(sessions, claim, worker_id, f"internal error while scoring: {type(e).__name__}")
            else "lost"
        )
    finally:
        beat.stopped.set()
    log.info(
        "job finished",
        extra={
            "submission": claim.submission_id,
            "status": status,
            "attempt": claim.attempt,
            "seconds": round(time.perf_counter() - t0, 3),
            "worker": worker_id,
        },
    )
    return status


def run(
    settings: Settings, worker_id: str | None = None, stop: threading.Event | None = None, max_jobs: int | None = None
) -> int:
    """Work until ``stop`` is set (or ``max_jobs`` are done); returns the number of jobs processed."""
    engine = make_engine(settings.db_url)
    init_db(engine)
    sessions = session_factory(engine)
    worker_id = worker_id or f"{socket.gethostname()[:40]}-{os.getpid()}-{new_id()[:6]}"
    stop = stop or threading.Event()
    with sessions.begin() as db:
        db.merge(
            WorkerRow(
                id=worker_id,
                host=socket.gethostname()[:128],
                pid=os.getpid(),
                started_at=now(),
                last_seen=now(),
                jobs_done=0,
            )
        )
    log.info("worker started", extra={"worker": worker_id, "pid": os.getpid()})
    done, last_seen, last_sweep = 0, 0.0, 0.0
    while not stop.is_set() and (max_jobs is None or done < max_jobs):
        if time.time() - last_sweep > SWEEP_SECONDS:
            last_sweep = time.time()
            try:
                with sessions.begin() as db:
                    if n := storage.sweep(db, settings.zip_retention_days):
                        log.info("stored ZIPs deleted (retention)", extra={"submissions": n})
            except Exception:
                log.warning("retention sweep failed", exc_info=True)
        try:
            claim = jobs.claim(sessions, worker_id, settings.lease_seconds, settings.max_attempts)
        except Exception:
            log.warning("claim failed; retrying", exc_info=True)
            stop.wait(settings.poll_seconds * 4)
            continue
        if claim is None:
            if time.time() - last_seen > SEEN_SECONDS:
                last_seen = time.time()
                try:
                    seen(sessions, worker_id)
                except Exception:
                    log.warning("worker heartbeat failed", exc_info=True)
            stop.wait(settings.poll_seconds)
            continue
        process(sessions, settings, claim, worker_id)
        done += 1
    try:  # a clean stop leaves no row behind for /health to list
        with sessions.begin() as db:
            db.execute(delete(WorkerRow).where(WorkerRow.id == worker_id))
    except Exception:
        log.warning("could not remove the worker row", exc_info=True)
    log.info("worker stopped", extra={"worker": worker_id, "jobs": done})
    engine.dispose()
    return done


def main(argv: list[str] | None = None) -> int:
    from ..http.logs import setup_logging

    p = argparse.ArgumentParser(prog="python -m mapfree.service.leaderboard.worker", description=__doc__)
    p.add_argument(
        "--db",
        default=os.environ.get("MAPFREE_DB"),
        help="database URL (default: $MAPFREE_DB, which keeps a password off the command line)",
    )
    p.add_argument("--data", type=Path)
    p.add_argument("--gt", type=Path)
    p.add_argument("--lease-seconds", type=float, default=60.0)
    p.add_argument("--max-attempts", type=int, default=3)
    p.add_argument("--poll-seconds", type=float, default=0.5)
    p.add_argument("--zip-retention-days", type=float, default=Settings.zip_retention_days)
    p.add_argument("--limits", default="{}", help="JSON of service Limits (the upload check's, for the reader)")
    p.add_argument("--log-level", default="info")
    p.add_argument("--exit-with-parent", action="store_true", help="stop when the launching process dies")
    a = p.parse_args(argv)
    setup_logging(a.log_level)
    if not a.db:
        p.error("no database: pass --db or set MAPFREE_DB")
    settings = Settings(
        db_url=a.db,
        data_root=a.data,
        gt_root=a.gt,
        lease_seconds=a.lease_seconds,
        max_attempts=a.max_attempts,
        poll_seconds=a.poll_seconds,
        zip_retention_days=a.zip_retention_days,
        limits=Limits(**json.loads(a.limits)),
    )
    try:
        check_ground_truth(settings)
    except ValueError as e:
        p.error(str(e))
    from ..process import die_with_parent, parent_from_env, stop_on_signals

    stop = threading.Event()
    stop_on_signals(stop)  # SIGTERM / SIGINT: the job is finished first, then the worker stops
    if a.exit_with_parent:  # SIGTERM when it dies, also mid-job (`serve` sets it before exec too)
        die_with_parent(parent_from_env() or os.getppid())
    run(settings, stop=stop)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
