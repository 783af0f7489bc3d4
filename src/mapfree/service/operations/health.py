"""What ``/health`` answers from: a snapshot of the database's state (reachable, queue counts, recently seen
workers) refreshed by a background thread every ``period`` seconds, so that a health check never queries the
database itself. Under heavy writes (three 38 MB uploads copied in at once) a query in the request could wait
hundreds of milliseconds on the disk and the thread pool; answering from memory keeps probes fast. Whether a
worker on this host is still alive is checked at request time (its process), so a killed one vanishes at once.
"""

from __future__ import annotations

import logging
import os
import socket
import threading
import time
from dataclasses import dataclass, field

from sqlalchemy import select, text
from sqlalchemy.engine import Engine
from sqlalchemy.orm import Session

from ..database.models import READ_ONLY, WorkerRow, now
from ..leaderboard import jobs
from ..leaderboard.worker import SEEN_SECONDS

log = logging.getLogger("mapfree.health")

#: A snapshot older than this (the database stopped answering the refresher) makes ``/health`` fail.
STALE_SECONDS = 10.0
#: A read slower than this is logged (at info): the database is struggling.
SLOW_READ_SECONDS = 0.1


@dataclass(frozen=True)
class Worker:
    id: str
    pid: int
    host: str
    jobs_done: int
    last_seen: float


@dataclass(frozen=True)
class Snapshot:
    """The database as the refresher last saw it (``error``: why it could not read it, then nothing else)."""

    taken_at: float  # time.monotonic() when the read finished
    counts: dict[str, int] = field(default_factory=dict)
    workers: tuple[Worker, ...] = ()
    error: str | None = None
    read_ms: float = 0.0  # how long the database took to answer


def read_snapshot(engine: Engine) -> Snapshot:
    """One short read-only transaction (on SQLite a WAL snapshot, no write lock): queue counts and the workers
    seen recently."""
    t0 = time.monotonic()
    try:
        with engine.connect().execution_options(**{READ_ONLY: True}) as conn, Session(conn) as rdb:
            rdb.execute(text("SELECT 1"))
            counts = jobs.counts(rdb)
            rows = rdb.scalars(select(WorkerRow).where(WorkerRow.last_seen > now() - 3 * SEEN_SECONDS)).all()
            workers = tuple(Worker(w.id, w.pid, w.host, w.jobs_done, w.last_seen) for w in rows)
            rdb.rollback()
    except Exception as e:
        log.warning("health check failed", extra={"error": type(e).__name__})
        return Snapshot(time.monotonic(), error=type(e).__name__)
    t1 = time.monotonic()
    if t1 - t0 > SLOW_READ_SECONDS:
        log.info("slow health read", extra={"ms": round((t1 - t0) * 1000, 1)})
    return Snapshot(t1, counts, workers, read_ms=round((t1 - t0) * 1000, 1))


def alive(w: Worker) -> bool:
    """A worker on this host is alive only if its process is (a SIGKILLed one leaves its row behind)."""
    if w.host != socket.gethostname()[:128]:
        return True
    try:
        os.kill(w.pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


class HealthMonitor:
    """Keeps a fresh ``Snapshot`` of one engine. The refresher thread starts on the first request and stops
    after ``idle_stop`` seconds without one (an app nobody probes does not poll its database)."""

    def __init__(self, engine: Engine, period: float = 0.25, idle_stop: float = 60.0):
        self.engine, self.period, self.idle_stop = engine, period, idle_stop
        self._snap: Snapshot | None = None
        self._asked = time.monotonic()
        self._lock = threading.Lock()
        self._thread: threading.Thread | None = None

    def current(self) -> Snapshot | None:
        """The latest snapshot, keeping the refresher running; None when there is none or the refresher was
        idle (then read one now: ``refresh``). A refresher that is slow under load does not make the caller
        wait: its last snapshot answers, until ``STALE_SECONDS`` turn it into an error."""
        self._asked = time.monotonic()
        with self._lock:
            if self._thread is None:
                self._thread = threading.Thread(target=self._run, name="mapfree-health", daemon=True)
                self._thread.start()
                return None
        return self._snap

    def refresh(self) -> Snapshot:
        self._snap = read_snapshot(self.engine)
        return self._snap

    def _run(self) -> None:
        while True:
            with self._lock:
                if time.monotonic() - self._asked > self.idle_stop:
                    self._thread = None
                    return
            self.refresh()
            time.sleep(self.period)

    def answer(self, snap: Snapshot) -> tuple[int, dict]:
        """(HTTP status, body) of ``/health`` for ``snap``: 503 when the database could not be read (or has not
        answered for ``STALE_SECONDS``); ``degraded`` when no worker is alive."""
        age = time.monotonic() - snap.taken_at
        if snap.error is not None or age > STALE_SECONDS:
            return 503, {"status": "error", "db": "unreachable"}
        t = now()
        workers = [
            {"id": w.id, "pid": w.pid, "host": w.host, "jobs_done": w.jobs_done}
            for w in snap.workers
            if w.last_seen > t - 3 * SEEN_SECONDS and alive(w)
        ]
        return 200, {
            "status": "ok" if workers else "degraded",
            "db": self.engine.dialect.name,
            "jobs": snap.counts,
            "workers": workers,
            "age_ms": round(age * 1000, 1),
            "db_ms": snap.read_ms,
        }
