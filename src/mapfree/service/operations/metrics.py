"""Prometheus metrics at ``/metrics``: request latency (this API process), and the queue, the workers and the
scoring times as the database knows them (the same in every API process, so any one may be scraped).

Request latency is a histogram per method (the standard ones; anything else is ``other``), route template
(never the raw path: ids would explode the series; ``unmatched`` when no route matched) and status. The
database gauges are read at scrape time in one short read-only transaction.
"""

from __future__ import annotations

import logging
from collections.abc import Iterator

from prometheus_client import CONTENT_TYPE_LATEST, CollectorRegistry, Histogram, generate_latest
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, Metric
from sqlalchemy import func, select
from sqlalchemy.engine import Engine
from sqlalchemy.orm import Session

from ..database.models import READ_ONLY, Result, Submission, WorkerRow, now
from ..leaderboard.worker import SEEN_SECONDS

__all__ = ["Metrics", "CONTENT_TYPE_LATEST"]

log = logging.getLogger("mapfree.metrics")

#: Latency buckets (seconds): page loads and API reads in the first half, localization and uploads after.
BUCKETS = (0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0, 60.0)
STATUSES = ("uploading", "queued", "running", "done", "failed", "withdrawn")
#: HTTP methods with a label value of their own; any other (made-up ones included) is counted as ``other``.
METHODS = ("GET", "HEAD", "POST", "PUT", "PATCH", "DELETE", "OPTIONS")


class _Database:
    """Gauges read from the database at scrape time."""

    def __init__(self, engine: Engine):
        self.engine = engine

    def describe(self) -> list[Metric]:  # no collect() at registration time: the database may not be there yet
        return []

    def collect(self) -> Iterator[Metric]:
        t = now()
        try:
            with self.engine.connect().execution_options(**{READ_ONLY: True}) as conn, Session(conn) as db:
                by_status = dict(db.execute(select(Submission.status, func.count()).group_by(Submission.status)).all())
                oldest = db.scalar(select(func.min(Submission.created_at)).where(Submission.status == "queued"))
                workers = db.execute(select(WorkerRow.id, WorkerRow.last_seen, WorkerRow.jobs_done)).all()
                n_scored, scoring_s = db.execute(
                    select(func.count(), func.coalesce(func.sum(Result.eval_seconds), 0.0))
                ).one()
                db.rollback()
        except Exception:  # the database is down: say so, and still serve the request metrics
            log.warning("metrics: database unreadable", exc_info=True)
            yield GaugeMetricFamily("mapfree_database_up", "Whether the database answered this scrape", value=0.0)
            return
        yield GaugeMetricFamily("mapfree_database_up", "Whether the database answered this scrape", value=1.0)
        jobs = GaugeMetricFamily("mapfree_jobs", "Submissions by status", labels=["status"])
        for s in sorted(set(STATUSES) | set(by_status)):
            jobs.add_metric([s], float(by_status.get(s, 0)))
        yield jobs
        yield GaugeMetricFamily(
            "mapfree_queue_depth", "Submissions waiting for a worker (queued)", value=float(by_status.get("queued", 0))
        )
        yield GaugeMetricFamily(
            "mapfree_queue_oldest_age_seconds",
            "Age of the oldest queued submission (0: none)",
            value=max(0.0, t - oldest) if oldest is not None else 0.0,
        )
        alive = [w for w in workers if w.last_seen > t - 3 * SEEN_SECONDS]
        yield GaugeMetricFamily(
            "mapfree_workers_alive",
            f"Evaluation workers that reported in the last {3 * SEEN_SECONDS:g} s",
            value=float(len(alive)),
        )
        seen = GaugeMetricFamily(
            "mapfree_worker_last_seen_age_seconds", "Seconds since each live worker reported", labels=["worker"]
        )
        done = CounterMetricFamily("mapfree_worker_jobs", "Jobs finished by each live worker", labels=["worker"])
        for w in alive:
            seen.add_metric([w.id], max(0.0, t - w.last_seen))
            done.add_metric([w.id], float(w.jobs_done))
        yield seen
        yield done
        scoring = CounterMetricFamily("mapfree_scoring_seconds", "Time workers spent scoring stored results")
        scoring.add_metric([], float(scoring_s))
        yield scoring
        yield CounterMetricFamily(
            "mapfree_scored_submissions", "Stored results (scored submissions)", value=float(n_scored)
        )


class Metrics:
    """One app's registry: its request histogram and the database gauges."""

    def __init__(self, engine: Engine):
        self.registry = CollectorRegistry(auto_describe=False)
        self.latency = Histogram(
            "mapfree_http_request_duration_seconds",
            "HTTP request latency (this API process)",
            ["method", "route", "status"],
            buckets=BUCKETS,
            registry=self.registry,
        )
        self.registry.register(_Database(engine))

    def observe(self, method: str, route: str, status: int, seconds: float) -> None:
        """One request: ``route`` is its route's template (``unmatched`` when none matched); a method outside
        ``METHODS`` counts as ``other``, so that junk requests cannot add label values (20,000 made-up methods
        had made 340,000 series and a 38 MB scrape)."""
        self.latency.labels(method if method in METHODS else "other", route, str(status)).observe(seconds)

    def render(self) -> bytes:
        return generate_latest(self.registry)
