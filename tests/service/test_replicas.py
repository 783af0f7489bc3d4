"""Two replicas of ``mapfree serve`` (each with its API process and workers) on one PostgreSQL database and one
data folder, as an operator scales it behind a load balancer (docs: Running several replicas). PostgreSQL only:
SQLite is one host's database."""

from __future__ import annotations

import os
import signal
import time
from concurrent.futures import ThreadPoolExecutor

import pytest
from sqlalchemy import func, select

from mapfree.data import Dataset

from .conftest import PG_URL, fresh_postgres, make_submission, start_server, stop_server

pytestmark = pytest.mark.skipif(
    not PG_URL, reason="MAPFREE_TEST_PG is not set (run .ci/services.sh to start PostgreSQL)"
)
SUBMISSIONS = 12


def _results(db_url: str) -> tuple[dict[str, str], int]:
    """(status by submission, result rows) as the database holds them."""
    from mapfree.service.database.models import Result, Submission, make_engine, session_factory

    engine = make_engine(db_url)
    with session_factory(engine)() as db:
        statuses = dict(db.execute(select(Submission.id, Submission.status)).all())
        results = db.scalar(select(func.count()).select_from(Result))
    engine.dispose()
    return statuses, int(results or 0)


def test_two_replicas_on_one_database(split_data, realmini_dir, tmp_path):
    """Every submission is scored exactly once while one replica is killed with kill -9 mid-run; a daily test
    limit holds across both; an anchor created or deleted through one is served or refused by the other at once
    (no stale anchor from its cache)."""
    db_url = fresh_postgres("replicas")
    a = start_server(db_url, "postgresql", split_data, tmp_path, workers=1)
    b = start_server(db_url, "postgresql", split_data, tmp_path, workers=1, tokens=a.tokens)
    try:
        # an anchor made through A is served by B; deleted through A, B refuses it at once
        ref = Dataset(realmini_dir).scene("val", "s00000").reference
        query = Dataset(realmini_dir).scene("val", "s00000").frame("seq1/frame_00009.jpg")
        form = {
            "fx": str(ref.intrinsics.fx),
            "fy": str(ref.intrinsics.fy),
            "cx": str(ref.intrinsics.cx),
            "cy": str(ref.intrinsics.cy),
            "method": "sift_pnp_sensor",
        }
        q_form = {k: str(getattr(query.intrinsics, k)) for k in ("fx", "fy", "cx", "cy")}
        q_file = {"image": ("q.jpg", query.image_path.read_bytes(), "image/jpeg")}
        with a.client("alice") as ca, b.client("bob") as cb:
            r = ca.post(
                "/anchors",
                data=form,
                files={
                    "image": ("r.jpg", ref.image_path.read_bytes(), "image/jpeg"),
                    "depth": ("r.png", ref.depth_path("sensor").read_bytes()),
                },
            )
            assert r.status_code == 201, r.text
            aid = r.json()["id"]
            assert cb.post(f"/anchors/{aid}/localize", data=q_form, files=q_file).json()["ok"]
            assert ca.delete(f"/anchors/{aid}").status_code == 204
            t0 = time.time()
            assert cb.post(f"/anchors/{aid}/localize", data=q_form, files=q_file).status_code == 404
            assert cb.get(f"/anchors/{aid}").status_code == 404 and time.time() - t0 < 1.0

        # carol's daily test limit (2) holds across both replicas, four uploads at once
        test_zip = make_submission(split_data.gt / "test", noise=0.2)

        def upload(srv, name):
            with srv.client("carol") as c:
                return c.post(
                    "/api/submissions", files={"file": ("s.zip", test_zip)}, data={"split": "test", "name": name}
                ).status_code

        with ThreadPoolExecutor(4) as ex:
            codes = sorted(ex.map(upload, [a, b, a, b], ["t0", "t1", "t2", "t3"]))
        assert codes == [202, 202, 429, 429], codes

        # submissions through both; A killed with kill -9 mid-run: B's workers take over its jobs
        val_zip = make_submission(split_data.root / "val", noise=0.2)

        def submit(i):
            with (a if i % 2 else b).client("bob") as c:
                r = c.post(
                    "/api/submissions", files={"file": ("s.zip", val_zip)}, data={"split": "val", "name": f"v{i}"}
                )
                return r.status_code

        with ThreadPoolExecutor(4) as ex:
            assert set(ex.map(submit, range(SUBMISSIONS))) == {202}
        time.sleep(0.3)
        os.killpg(a.proc.pid, signal.SIGKILL)  # its API process and its workers, whatever they were doing
        a.proc.wait()
        deadline = time.time() + 120
        while time.time() < deadline:
            statuses, results = _results(db_url)
            if all(s in ("done", "failed") for s in statuses.values()):
                break
            time.sleep(0.5)
        statuses, results = _results(db_url)
        assert list(statuses.values()).count("done") == SUBMISSIONS + 2, statuses
        assert results == SUBMISSIONS + 2  # one result each: none lost, none scored twice
    finally:
        stop_server(b.proc)
        if a.proc.poll() is None:
            stop_server(a.proc)
