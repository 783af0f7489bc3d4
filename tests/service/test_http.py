"""The HTTP layer: malformed forms and ids past the database's integer are 422s, a body announced too large is refused
before it is read, an unexpected error is a logged JSON 500 with a request id, and /health answers from a live
snapshot."""

from __future__ import annotations

import logging
import os
import subprocess
import sys
import time

from .conftest import OPERATOR, make_submission


def test_malformed_forms(server):
    data = make_submission(server.data.root / "val")
    with server.client("alice") as c:
        r = c.post("/api/submissions", data={"split": "val"})
        assert r.status_code == 422 and "file" in r.json()["detail"]
        r = c.post("/api/submissions", files={"file": ("s.zip", data)}, data={"split": "train"})
        assert r.status_code == 422 and "split" in r.json()["detail"]
        r = c.post("/api/submissions", files={"file": ("s.zip", data)}, data={"split": "val", "name": "x" * 500})
        assert r.status_code == 422 and "name" in r.json()["detail"]
        r = c.post("/api/submissions", content=b"{not json", headers={"content-type": "application/json"})
        assert r.status_code == 422
        assert c.get("/api/submissions/" + "a" * 5000).status_code in (404, 414)
        assert c.patch("/api/submissions/x", json={"public": "maybe"}).status_code == 422


def test_oversized_request_is_refused_before_reading(server):
    """A body announced larger than the server's request limit is answered 413 without being read."""
    import socket
    from urllib.parse import urlparse

    u = urlparse(server.url)
    with socket.create_connection((u.hostname, u.port), timeout=30) as s:
        s.sendall(
            b"POST /api/submissions HTTP/1.1\r\nHost: x\r\nAuthorization: Bearer "
            + server.tokens["alice"].encode()
            + b"\r\nContent-Type: multipart/form-data; boundary=b\r\n"
            b"Content-Length: 10000000000\r\n\r\n"
        )
        head = s.recv(4096).decode(errors="replace")
    assert head.startswith("HTTP/1.1 413"), head


def test_out_of_range_ids_are_refused_not_a_500(server):
    """An id past the database's integer (2^63 on SQLite, 2^31 on PostgreSQL) in a path used to be a 500 from
    the driver; now a 422 naming the largest id (JSON for the API, the error page for forms)."""
    huge = "99999999999999999999"
    with server.client("bob") as c:
        for method, path in (
            ("DELETE", f"/api/tokens/{huge}"),
            ("DELETE", f"/api/sessions/{2**31}"),
            ("POST", f"/me/tokens/{huge}/revoke"),
            ("POST", f"/me/sessions/{2**31}/end"),
            ("GET", f"/anchors/x/photos/{huge}"),
            ("DELETE", f"/anchors/x/photos/{2**40}"),
        ):
            r = c.request(method, path)
            assert r.status_code == 422 and "2147483647" in r.text, (method, path, r.status_code, r.text[:200])
        assert c.delete("/api/tokens/2147483647").status_code == 404
    out = subprocess.run(
        [sys.executable, "-m", "mapfree.cli.admin", "--db", server.db_url, "revoke-token", huge],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert out.returncode == 2 and "no such id" in out.stderr and "Traceback" not in out.stderr, out.stderr


def test_unexpected_error_is_a_logged_json_500_with_a_request_id(make_app, caplog):
    app = make_app()

    @app.client.app.get("/boom")
    def boom():
        raise RuntimeError("a bug")

    with caplog.at_level(logging.INFO):
        r = app.client.get("/boom")
    assert r.status_code == 500 and r.headers["content-type"].startswith("application/json")
    rid = r.json()["request_id"]
    assert rid and r.headers["x-request-id"] == rid and rid in r.json()["detail"]
    access = [rec for rec in caplog.records if rec.getMessage() == "request" and getattr(rec, "status", 0) == 500]
    assert access and access[0].request_id == rid
    assert any(
        rec.getMessage() == "unhandled error" and getattr(rec, "request_id", None) == rid for rec in caplog.records
    )


def test_health_answers_from_a_live_snapshot_and_fails_when_the_database_does(make_app, tmp_path):
    """/health answers from state a background thread re-reads (a new worker row shows within a second); a
    database that cannot be read, or a snapshot gone stale, is a 503; the refresher stops when nobody asks."""
    import socket

    from sqlalchemy import create_engine

    from mapfree.service.database.models import WorkerRow, make_engine, session_factory
    from mapfree.service.operations.health import STALE_SECONDS, HealthMonitor, Snapshot

    app = make_app()
    h = app.client.get("/health/detail", headers=OPERATOR).json()
    assert h["status"] == "degraded" and h["workers"] == [] and h["db"] == "sqlite" and h["age_ms"] >= 0, h
    engine = make_engine(app.settings.db_url)
    with session_factory(engine).begin() as db:
        db.add(WorkerRow(id="w-test", host=socket.gethostname()[:128], pid=os.getpid()))
    deadline = time.time() + 3
    while time.time() < deadline and h["status"] != "ok":
        time.sleep(0.1)
        h = app.client.get("/health/detail", headers=OPERATOR).json()
    assert h["status"] == "ok" and [w["id"] for w in h["workers"]] == ["w-test"], h
    engine.dispose()

    broken = HealthMonitor(create_engine(f"sqlite:///{tmp_path / 'no-such-dir' / 'x.db'}"))
    assert broken.answer(broken.refresh()) == (503, {"status": "error", "db": "unreachable"})
    assert broken.answer(Snapshot(time.monotonic() - STALE_SECONDS - 1))[0] == 503

    m = HealthMonitor(make_engine(app.settings.db_url), period=0.05, idle_stop=0.4)
    assert m.current() is None  # no snapshot yet: the caller reads one itself
    time.sleep(0.3)
    snap = m.current()
    assert snap is not None and snap.error is None and m.answer(snap)[0] == 200
    time.sleep(1.0)  # nobody asked for 0.4 s: the refresher stopped, the next caller reads afresh
    assert m.current() is None
    m.engine.dispose()


def test_an_anonymous_sign_in_body_is_refused_from_its_headers_unless_a_small_form(server):
    """``POST /login``, the one anonymous write, used to parse any body before its handler ran: a
    ``multipart/form-data`` body with the token sent as a file part was spooled to disk while the client held
    its last byte. Now anything but a small urlencoded form is answered from the headers, before the body."""
    import socket
    from urllib.parse import urlparse

    u = urlparse(server.url)
    part = b'--b\r\nContent-Disposition: form-data; name="token"; filename="t"\r\n\r\n' + b"x" * 1024
    for kind, length, want in (
        (b"multipart/form-data; boundary=b", 60_000_000, "415"),
        (b"application/x-www-form-urlencoded", 60_000_000, "413"),
        (b"application/json", 100, "415"),
    ):
        with socket.create_connection((u.hostname, u.port), timeout=10) as s:
            s.sendall(
                b"POST /login HTTP/1.1\r\nHost: x\r\nContent-Type: "
                + kind
                + b"\r\nContent-Length: "
                + str(length).encode()
                + b"\r\n\r\n"
                + part[: min(length, len(part))]
            )
            head = s.recv(4096).decode(errors="replace")  # the body is never finished: a reply comes from headers
        assert head.startswith(f"HTTP/1.1 {want}"), (kind, head[:200])
        assert "connection: close" in head.lower()
    with server.client() as c:  # the form itself still signs in (its CSRF check answers, not the gate)
        r = c.post("/login", data={"token": "wrong", "csrf_token": "x"})
        assert r.status_code == 403


def test_a_405_lists_every_method_of_the_path(make_app):
    """Starlette's 405 named only the first route's method (``Allow: GET`` where DELETE is allowed too)."""
    app = make_app()
    for path, want in (
        ("/anchors/abc", {"GET", "HEAD", "DELETE"}),
        ("/api/submissions/x", {"GET", "HEAD", "PATCH", "DELETE"}),
        ("/api/tokens/1", {"DELETE"}),
    ):
        r = app.client.request("PUT", path, headers=app.auth("ann"))
        assert r.status_code == 405, (path, r.text)
        assert set(r.headers["allow"].split(", ")) == want, (path, r.headers["allow"])


def test_request_heads_past_the_documented_size_are_refused(server):
    """``--h11-max-incomplete-event-size`` (16 KiB) held only for a head arriving in pieces: 100 KB of headers
    sent at once were served. Now a head over the limit is answered 431, one under it as before."""
    import socket
    from urllib.parse import urlparse

    u = urlparse(server.url)
    for size, want in ((100_000, "431"), (8_000, "200")):
        with socket.create_connection((u.hostname, u.port), timeout=30) as s:
            s.sendall(b"GET /health HTTP/1.1\r\nHost: x\r\nX-Pad: " + b"a" * size + b"\r\n\r\n")
            head = s.recv(4096).decode(errors="replace")
        assert head.startswith(f"HTTP/1.1 {want}"), (size, head[:200])
