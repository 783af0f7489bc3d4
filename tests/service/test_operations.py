"""What an operator and a privacy-minded user expect of the service: photos stored without EXIF and turned
upright, health without internals, metrics, the database URL off the command line, interrupted uploads refunded,
migrations, backups, tokens. Real app, real database, real photos (realmini-dev)."""

from __future__ import annotations

import io
import os
import stat
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from mapfree.data import Dataset
from mapfree.data.orientation import orient_intrinsics, orient_pixels
from mapfree.geometry import rotation_angle_deg

METHOD = "sift_pnp_sensor"
QUERY = "seq1/frame_00010.jpg"


@pytest.fixture(scope="module")
def scene(realmini_dir):
    return Dataset(realmini_dir).scene("val", "s00000")


def _form(K) -> dict:
    return {"fx": str(K.fx), "fy": str(K.fy), "cx": str(K.cx), "cy": str(K.cy)}


def _tagged_jpeg(rgb: np.ndarray, orientation: int = 1, serial: str = "SN-0042-SECRET") -> bytes:
    """A JPEG with the metadata a phone writes: orientation, GPS position and the camera's serial number."""
    exif = Image.Exif()
    exif[0x0112] = orientation
    exif[0x010F] = "PhoneMaker"
    exif.get_ifd(0x8769)[0xA431] = serial  # BodySerialNumber
    exif.get_ifd(0x8825).update({1: "N", 2: (51.0, 30.0, 12.5), 3: "W", 4: (0.0, 7.0, 39.0)})  # GPS
    buf = io.BytesIO()
    Image.fromarray(rgb).save(buf, format="JPEG", quality=95, exif=exif)
    return buf.getvalue()


def _png(depth_m: np.ndarray) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(np.rint(depth_m * 1000).astype(np.uint16)).save(buf, format="PNG")
    return buf.getvalue()


def _decode(data: bytes) -> np.ndarray:
    with Image.open(io.BytesIO(data)) as im:
        return np.asarray(im.convert("RGB"))


def test_anchor_photos_are_stored_upright_without_exif(make_app, scene):  # noqa: F811
    """GPS and serial never leave the server; an upright photo keeps its pixels exactly; a phone photo stored
    sideways with orientation 6 (and intrinsics/depth for its stored grid, as the phone gives them) is accepted,
    served upright, and localizes a query as well as the original."""
    app = make_app()
    c, auth = app.client, app.auth("ann")
    ref, q = scene.reference, scene.frame(QUERY)
    plain = _tagged_jpeg(ref.image())
    r = c.post(
        "/anchors",
        headers=auth,
        data={**_form(ref.intrinsics), "method": METHOD},
        files={"image": ("ref.jpg", plain, "image/jpeg"), "depth": ("ref.png", _png(ref.depth("sensor")), "image/png")},
    )
    assert r.status_code == 201, r.text
    served = c.get(f"/anchors/{r.json()['id']}/photos/0", headers=auth).content
    assert b"Exif" not in served and b"SN-0042" not in served and b"PhoneMaker" not in served
    assert np.array_equal(_decode(served), _decode(plain))  # same pixels: only the metadata went

    sideways = _tagged_jpeg(orient_pixels(ref.image(), 8), orientation=6)  # displays as the original
    r = c.post(
        "/anchors",
        headers=auth,
        data={**_form(orient_intrinsics(ref.intrinsics, 8)), "method": METHOD},
        files={
            "image": ("ref.jpg", sideways, "image/jpeg"),
            "depth": ("ref.png", _png(orient_pixels(ref.depth("sensor"), 8)), "image/png"),
        },
    )
    assert r.status_code == 201, r.text
    turned = r.json()
    assert turned["intrinsics"]["width"] == ref.intrinsics.width
    assert turned["intrinsics"]["cx"] == pytest.approx(ref.intrinsics.cx)
    served = c.get(f"/anchors/{turned['id']}/photos/0", headers=auth).content
    assert b"Exif" not in served and b"SN-0042" not in served
    assert _decode(served).shape == ref.image().shape
    assert np.abs(_decode(served).astype(int) - ref.image()).mean() < 4  # upright (JPEG noise only)

    est = c.post(
        f"/anchors/{turned['id']}/localize",
        headers=auth,
        data=_form(q.intrinsics),
        files={"image": ("q.jpg", q.image_path.read_bytes(), "image/jpeg")},
    ).json()
    assert est["ok"], est
    center = -np.array(est["R"]).T @ np.array(est["t"])
    assert np.linalg.norm(center - q.pose.center) < 0.15 and rotation_angle_deg(np.array(est["R"]), q.pose.R) < 5, est


def test_a_sideways_query_gives_the_pose_of_the_upright_one(make_app, scene):  # noqa: F811
    """Orientation 3, 6 and 8 queries, with intrinsics for the stored grid: the pose of the original query (not
    "corrupt", not a pose rotated by the tag)."""
    app = make_app()
    c, auth = app.client, app.auth("ann")
    ref, q = scene.reference, scene.frame(QUERY)
    r = c.post(
        "/anchors",
        headers=auth,
        data={**_form(ref.intrinsics), "method": METHOD},
        files={
            "image": ("ref.jpg", ref.image_path.read_bytes(), "image/jpeg"),
            "depth": ("ref.png", ref.depth_path("sensor").read_bytes(), "image/png"),
        },
    )
    aid = r.json()["id"]

    def pose_of(data: bytes, K) -> tuple[np.ndarray, np.ndarray]:
        est = c.post(
            f"/anchors/{aid}/localize", headers=auth, data=_form(K), files={"image": ("q.jpg", data, "image/jpeg")}
        ).json()
        assert est.get("ok"), est
        return np.array(est["R"]), -np.array(est["R"]).T @ np.array(est["t"])

    R0, c0 = pose_of(_tagged_jpeg(q.image()), q.intrinsics)
    assert np.linalg.norm(c0 - q.pose.center) < 0.15
    for o, undo in ((6, 8), (8, 6), (3, 3)):  # a camera turned about its axis keeps its centre: R is compared too
        R, center = pose_of(_tagged_jpeg(orient_pixels(q.image(), undo), o), orient_intrinsics(q.intrinsics, undo))
        assert np.linalg.norm(center - c0) < 0.06 and rotation_angle_deg(R, R0) < 1.0, o
    mirrored = c.post(
        f"/anchors/{aid}/localize",
        headers=auth,
        data=_form(q.intrinsics),
        files={"image": ("q.jpg", _tagged_jpeg(q.image(), 2), "image/jpeg")},
    )
    assert mirrored.status_code == 422 and "mirrored" in mirrored.json()["detail"]


def test_public_health_says_only_the_status_and_head_is_answered(make_app):  # noqa: F811
    """/health tells anyone whether the service lives, nothing about hosts, processes or queues; the detail is
    for admins and the operator token. HEAD is answered wherever GET is, with GET's headers and no body."""
    import socket

    from mapfree.service.database.models import WorkerRow, make_engine, session_factory

    from .conftest import OPERATOR, create_users

    app = make_app()
    c = app.client
    engine = make_engine(app.settings.db_url)
    with session_factory(engine).begin() as db:
        db.add(WorkerRow(id="w-probe", host=socket.gethostname()[:128], pid=os.getpid()))
    engine.dispose()
    public = c.get("/health")
    assert public.status_code == 200 and public.json() == {"status": "ok"}, public.text
    for secret in (socket.gethostname(), str(os.getpid()), "w-probe", "jobs", "workers"):
        assert secret not in public.text
    assert c.get("/health/detail").status_code == 401
    assert c.get("/health/detail", headers=app.auth("ann")).status_code == 403  # signed in, not an admin
    assert c.get("/health/detail", headers={"Authorization": "Bearer mf_wrong"}).status_code == 401
    detail = c.get("/health/detail", headers=OPERATOR).json()
    assert [w["id"] for w in detail["workers"]] == ["w-probe"] and "jobs" in detail, detail
    admin = create_users(app.settings.db_url, {"root": None}, admin=True)["root"]
    assert c.get("/health/detail", headers={"Authorization": f"Bearer {admin}"}).json()["workers"], detail

    for path in ("/health", "/", "/leaderboard/val", "/api/leaderboard/val", "/openapi.json"):
        got, head = c.get(path), c.head(path)
        assert head.status_code == got.status_code == 200, (path, head.status_code, got.status_code)
        assert head.content == b"" and head.headers.get("content-type") == got.headers.get("content-type"), path
        assert head.headers.get("content-length") == str(len(got.content)), path
    assert c.head("/api/submissions", headers=app.auth("ann")).status_code == 200
    assert c.head("/health/detail").status_code == 401
    scraped = c.get("/metrics", headers=OPERATOR).text
    assert 'mapfree_http_request_duration_seconds_count{method="HEAD",route="/health",status="200"} 1.0' in scraped


def test_the_database_url_is_not_on_any_workers_command_line(sqlite_server):
    """``ps`` shows every user of the host each process's command line: the workers get the URL (and with it a
    PostgreSQL password) through their environment, which only their owner can read."""
    from .conftest import health_detail

    workers = health_detail(sqlite_server.url)["workers"]
    assert len(workers) >= 2
    secret = sqlite_server.db_url.split("///")[-1]
    for w in workers:
        cmdline = Path(f"/proc/{w['pid']}/cmdline").read_bytes().decode().split("\0")
        assert "mapfree.service.leaderboard.worker" in cmdline and not any(secret in part for part in cmdline), cmdline
        assert secret in Path(f"/proc/{w['pid']}/environ").read_bytes().decode()  # how it got there


_KILLED_MID_UPLOAD = """
import io, os, signal, sys
from sqlalchemy import select
from mapfree.service.leaderboard import storage, submissions
from mapfree.service.config import Settings
from mapfree.service.database.models import User, make_engine, session_factory

class DiesWhileCopied(io.BytesIO):
    def read(self, n=-1):
        if n == storage.CHUNK_BYTES:  # the copy into the database has begun: this process is killed
            os.kill(os.getpid(), signal.SIGKILL)
        return super().read(n)

url, data_root, gt_root, zip_path = sys.argv[1:]
settings = Settings(db_url=url, data_root=data_root, gt_root=gt_root)
engine = make_engine(url)
with session_factory(engine)() as db:
    user = db.scalar(select(User).where(User.name == "ann"))
    submissions.accept(db, settings, user, "test", "cut off", False, DiesWhileCopied(open(zip_path, "rb").read()))
"""


def test_an_upload_cut_off_by_a_killed_server_is_removed_and_refunded(make_app, split_data, tmp_path):  # noqa: F811
    """The process storing a test submission is SIGKILLed mid-copy: its ``uploading`` row stops renewing its
    lease, and the next server start removes it, giving the test evaluation back."""
    import subprocess
    import sys
    import time

    from sqlalchemy import func, select

    from mapfree.service import Settings, create_app
    from mapfree.service.database.models import Submission, make_engine, session_factory
    from mapfree.service.leaderboard import storage

    from .conftest import make_submission

    app = make_app(test_daily_limit=2)
    auth = app.auth("ann")
    assert app.client.get("/api/me", headers=auth).json()["test_evaluations_left_today"] == 2
    zip_path = tmp_path / "test.zip"
    zip_path.write_bytes(make_submission(split_data.root / "test"))
    proc = subprocess.run(
        [
            sys.executable,
            "-c",
            _KILLED_MID_UPLOAD,
            app.settings.db_url,
            str(split_data.root),
            str(split_data.gt),
            str(zip_path),
        ],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == -9, proc.stderr[-2000:]
    engine = make_engine(app.settings.db_url)
    count = select(func.count()).select_from(Submission).where(Submission.status == "uploading")
    with session_factory(engine)() as db:
        assert db.scalar(count) == 1
        lease = db.scalar(select(Submission.lease_until))
    assert app.client.get("/api/me", headers=auth).json()["test_evaluations_left_today"] == 1  # spent
    assert lease is not None and lease - time.time() <= storage.UPLOAD_LEASE_SECONDS
    settings = Settings(
        db_url=app.settings.db_url, data_root=split_data.root, gt_root=split_data.gt, test_daily_limit=2
    )
    other = create_app(settings)  # another API process starting meanwhile: the lease still runs, could be alive
    with session_factory(engine)() as db:
        assert db.scalar(count) == 1
    other.state.engine.dispose()
    with session_factory(engine).begin() as db:  # the lease lapses (instead of waiting two minutes)
        db.execute(Submission.__table__.update().values(lease_until=time.time() - 1))
    restarted = create_app(settings)
    with session_factory(engine)() as db:
        assert db.scalar(count) == 0
    assert app.client.get("/api/me", headers=auth).json()["test_evaluations_left_today"] == 2  # refunded
    restarted.state.engine.dispose()
    engine.dispose()


def test_a_ground_truth_folder_missing_a_test_scene_is_refused_at_start(split_data, tmp_path):
    """``serve`` (and a worker started alone) with a ``--gt`` that lacks a test scene stops at once, naming it,
    instead of accepting test submissions it can never score."""
    import shutil
    import subprocess
    import sys

    gt = tmp_path / "gt"
    shutil.copytree(split_data.gt, gt)
    scenes = sorted(p.name for p in (gt / "test").iterdir())
    shutil.rmtree(gt / "test" / scenes[-1])
    db = f"sqlite:///{tmp_path / 'gt.db'}"
    for cmd in (["mapfree.cli.serve", "--workers", "1", "--port", "1"], ["mapfree.service.leaderboard.worker"]):
        r = subprocess.run(
            [sys.executable, "-m", *cmd, "--db", db, "--data", str(split_data.root), "--gt", str(gt)],
            capture_output=True,
            text=True,
            timeout=120,
        )
        assert r.returncode == 2, (cmd, r.stderr[-2000:])
        assert scenes[-1] in r.stderr and scenes[0] not in r.stderr and "lacks 1 of" in r.stderr, r.stderr


def test_implausible_focals_and_empty_depth_are_refused_and_the_anchor_photo_itself_is_the_identity(make_app, scene):  # noqa: F811
    app = make_app()
    c, auth = app.client, app.auth("ann")
    ref = scene.reference
    files = {
        "image": ("ref.jpg", ref.image_path.read_bytes(), "image/jpeg"),
        "depth": ("ref.png", ref.depth_path("sensor").read_bytes(), "image/png"),
    }
    for fx in ("1e-300", "0.5", "50"):  # 50 px on a 540 px photo: a 158-degree view, not a pinhole camera
        r = c.post("/anchors", headers=auth, files=files, data={**_form(ref.intrinsics), "fx": fx, "method": METHOD})
        assert r.status_code == 422 and "focal lengths must lie between 54 and 54000 px" in r.json()["detail"], r.text
    zero = {**files, "depth": ("ref.png", _png(np.zeros_like(ref.depth("sensor"))), "image/png")}
    r = c.post("/anchors", headers=auth, files=zero, data={**_form(ref.intrinsics), "method": METHOD})
    assert r.status_code == 422 and "every pixel is 0" in r.json()["detail"], r.text

    r = c.post("/anchors", headers=auth, files=files, data={**_form(ref.intrinsics), "method": METHOD})
    assert r.status_code == 201, r.text
    est = c.post(
        f"/anchors/{r.json()['id']}/localize",
        headers=auth,
        data=_form(ref.intrinsics),
        files={"image": ("same.jpg", ref.image_path.read_bytes(), "image/jpeg")},
    ).json()
    assert est["ok"] and est["confidence"] > 100, est  # not "no parallax": taken where the anchor photo was
    assert np.allclose(est["R"], np.eye(3)) and np.allclose(est["t"], 0), est


def _scrape(url: str, **kw) -> dict:
    """``/metrics`` parsed: {sample name with sorted labels: value}."""
    import httpx
    from prometheus_client.parser import text_string_to_metric_families

    from .conftest import OPERATOR

    r = httpx.get(url + "/metrics", headers=OPERATOR, timeout=10, **kw)
    assert r.status_code == 200 and r.headers["content-type"].startswith("text/plain"), r.text
    out = {}
    for fam in text_string_to_metric_families(r.text):
        for s in fam.samples:
            out[s.name + "".join(f"|{k}={v}" for k, v in sorted(s.labels.items()))] = s.value
    return out


def test_metrics_and_json_access_logs(sqlite_server):
    """A real server scraped like Prometheus does: request latency by route template, queue, live workers and
    scoring time; the access log is JSON lines with the client address and the request id it answered with."""
    import json

    import httpx

    from .conftest import make_submission
    from .test_api import upload

    url = sqlite_server.url
    assert httpx.get(url + "/metrics").status_code == 401  # queue and workers are not public
    with sqlite_server.client("bob") as c:
        assert c.get("/metrics").status_code == 403
        r = upload(c, make_submission(sqlite_server.data.root / "val", noise=0.1), "val", "metrics-run")
        assert r.status_code == 202, r.text
        rid = r.headers["X-Request-ID"]
    sqlite_server.wait_done(r.json()["id"], "bob")
    m = _scrape(url)
    assert m["mapfree_http_request_duration_seconds_count|method=POST|route=/api/submissions|status=202"] >= 1
    assert m["mapfree_workers_alive"] >= 2 and m["mapfree_queue_depth"] >= 0
    assert m["mapfree_queue_oldest_age_seconds"] >= 0 and m["mapfree_jobs|status=done"] >= 1
    assert m["mapfree_scored_submissions_total"] >= 1 and m["mapfree_scoring_seconds_total"] > 0
    assert any(k.startswith("mapfree_worker_last_seen_age_seconds|worker=") for k in m)
    lines = [json.loads(x) for x in sqlite_server.log().splitlines() if x.startswith("{")]
    mine = [x for x in lines if x.get("request_id") == rid and x.get("msg") == "request"]
    assert len(mine) == 1 and mine[0]["client"] == "127.0.0.1" and mine[0]["route"] == "/api/submissions", mine
    assert mine[0]["status"] == 202 and mine[0]["ms"] > 0 and mine[0]["user_id"] is not None


def test_junk_requests_add_no_metric_series(sqlite_server):
    """Anonymous requests with made-up methods on unknown paths used to add a label value each (20,000 of them:
    340,000 series, a 38 MB scrape of 10.7 s). Now any method but the standard ones is ``other`` and any path
    no route matches is ``unmatched``, so they add nothing past the first."""
    import httpx

    from mapfree.service.operations.metrics import METHODS

    with httpx.Client(base_url=sqlite_server.url, timeout=10) as c:
        c.request("JUNK0", "/nope/0")
        _scrape(sqlite_server.url)  # the scrape's own series
        before = len(_scrape(sqlite_server.url))
        for i in range(1, 40):
            assert c.request(f"JUNK{i}", f"/nope/{i}/{'x' * i}").status_code in (404, 405)
        m = _scrape(sqlite_server.url)
    methods = {k.split("|method=")[1].split("|")[0] for k in m if "|method=" in k}
    assert methods <= {*METHODS, "other"} and "other" in methods, methods
    assert not [k for k in m if "/nope" in k]
    assert len(m) == before  # no series per junk request


def test_metrics_show_a_waiting_queue(make_app, split_data):  # noqa: F811
    """No worker runs in-process: an upload waits, and the queue depth and its oldest job's age say so."""
    import time

    from prometheus_client.parser import text_string_to_metric_families

    from .conftest import OPERATOR, make_submission
    from .test_api import upload

    app = make_app()
    with app.client as c:
        c.headers.update(app.auth("ann"))
        assert upload(c, make_submission(split_data.root / "val"), "val").status_code == 202
        time.sleep(0.3)
        text = c.get("/metrics", headers=OPERATOR).text
    m = {s.name: s.value for f in text_string_to_metric_families(text) for s in f.samples if not s.labels}
    assert m["mapfree_queue_depth"] == 1 and 0.3 <= m["mapfree_queue_oldest_age_seconds"] < 60, m
    assert m["mapfree_workers_alive"] == 0 and m["mapfree_database_up"] == 1

    from sqlalchemy import create_engine

    from mapfree.service.operations.metrics import Metrics

    down = Metrics(create_engine(f"sqlite:///{app.settings.db_url.split('///')[-1]}.missing/x.db"))
    down.observe("GET", "/health", 200, 0.01)
    text = down.render().decode()
    assert "mapfree_database_up 0.0" in text and "mapfree_http_request_duration_seconds_count" in text


def test_tokens_expire_and_tokens_and_sessions_are_listed_and_revoked_one_by_one(make_app, tmp_path):  # noqa: F811
    """An expired token is a 401 saying so; a user lists their tokens and sessions and revokes one without the
    others; the admin CLI does the same for any account."""
    import time

    from .conftest import mapfree
    from .test_anchor_photos import _web_session

    app = make_app()
    c, ann = app.client, app.auth("ann")
    r = c.post("/api/tokens", headers=ann, data={"expires_in_days": str(1.5 / 86400), "label": "short"})
    assert r.status_code == 201, r.text
    short = r.json()
    assert short["label"] == "short" and short["expires_at"] - time.time() < 2 and short["token"].startswith("mf_")
    assert c.get("/api/me", headers={"Authorization": f"Bearer {short['token']}"}).status_code == 200
    time.sleep(1.6)
    r = c.get("/api/me", headers={"Authorization": f"Bearer {short['token']}"})
    assert r.status_code == 401 and "expired on" in r.json()["detail"] and short["prefix"] in r.json()["detail"]
    assert c.post("/api/tokens", headers=ann, data={"expires_in_days": "400"}).status_code == 422

    second = c.post("/api/tokens", headers=ann, data={"expires_in_days": "30", "label": "laptop"}).json()
    listed = c.get("/api/tokens", headers=ann).json()
    assert [t["label"] for t in listed] == ["", "short", "laptop"] and [t["current"] for t in listed] == [
        True,
        False,
        False,
    ]
    assert listed[1]["expired"] and not listed[2]["expired"] and "token" not in listed[2]
    assert c.delete(f"/api/tokens/{second['id']}", headers=ann).json()["revoked"]
    assert c.get("/api/me", headers={"Authorization": f"Bearer {second['token']}"}).status_code == 401
    assert c.get("/api/me", headers=ann).status_code == 200  # the others still work
    assert c.delete(f"/api/tokens/{listed[0]['id']}", headers=app.auth("ben")).status_code == 404  # not ben's

    web1, csrf1 = _web_session(app)
    web2, _ = _web_session(app)
    sessions = web1.get("/api/sessions").json()
    assert len(sessions) == 2 and [s["current"] for s in sessions] == [True, False], sessions
    other = sessions[1]["id"]
    assert web1.delete(f"/api/sessions/{other}", headers={"X-CSRF-Token": csrf1}).status_code == 200
    assert web2.get("/api/me").status_code == 401 and web1.get("/api/me").status_code == 200

    url = app.settings.db_url
    out = mapfree("admin", "--db", url, "list-tokens", "ann")
    assert "laptop" in out and "revoked" in out and "expired" in out and "active" in out, out
    token = mapfree("admin", "--db", url, "new-token", "ann", "--expires-in", "30d", "--label", "ci").splitlines()[-1]
    assert c.get("/api/me", headers={"Authorization": f"Bearer {token}"}).status_code == 200
    tid = next(t["id"] for t in c.get("/api/tokens", headers=ann).json() if t["label"] == "ci")
    assert (
        29.9 * 86400
        < next(t["expires_at"] for t in c.get("/api/tokens", headers=ann).json() if t["label"] == "ci") - time.time()
        <= 30 * 86400
    )
    mapfree("admin", "--db", url, "revoke-token", str(tid))
    assert c.get("/api/me", headers={"Authorization": f"Bearer {token}"}).status_code == 401
    sid = mapfree("admin", "--db", url, "list-sessions", "ann").splitlines()[-1].split("\t")[0]
    mapfree("admin", "--db", url, "revoke-session", sid)
    assert web1.get("/api/me").status_code == 401


def test_private_anchor_photos_are_for_the_owner_only(make_app, scene):  # noqa: F811
    """A private anchor answers everyone's queries, but only its owner (and admins) get its photos."""
    from .conftest import create_users

    app = make_app()
    c = app.client
    ref, q = scene.reference, scene.frame(QUERY)
    files = {
        "image": ("ref.jpg", ref.image_path.read_bytes(), "image/jpeg"),
        "depth": ("ref.png", ref.depth_path("sensor").read_bytes(), "image/png"),
    }
    r = c.post(
        "/anchors",
        headers=app.auth("ann"),
        files=files,
        data={**_form(ref.intrinsics), "method": METHOD, "private": "true"},
    )
    assert r.status_code == 201 and r.json()["private"], r.text
    aid = r.json()["id"]
    public = c.post("/anchors", headers=app.auth("ann"), files=files, data={**_form(ref.intrinsics), "method": METHOD})
    assert not public.json()["private"]
    root = {"Authorization": "Bearer " + create_users(app.settings.db_url, {"root": None}, admin=True)["root"]}
    assert c.get(f"/anchors/{aid}/photos/0", headers=app.auth("ann")).status_code == 200
    assert c.get(f"/anchors/{aid}/photos/0", headers=root).status_code == 200
    r = c.get(f"/anchors/{aid}/photos/0", headers=app.auth("ben"))
    assert r.status_code == 403 and "private" in r.json()["detail"]
    assert c.get(f"/anchors/{public.json()['id']}/photos/0", headers=app.auth("ben")).status_code == 200
    est = c.post(
        f"/anchors/{aid}/localize",
        headers=app.auth("ben"),
        data=_form(q.intrinsics),
        files={"image": ("q.jpg", q.image_path.read_bytes(), "image/jpeg")},
    ).json()
    assert est["ok"], est
    page = c.post(
        "/relocalize/anchor",
        headers=app.auth("ben"),
        data={"anchor": aid, **{f"q_{k}": v for k, v in _form(q.intrinsics).items()}},
        files={"query": ("q.jpg", q.image_path.read_bytes(), "image/jpeg")},
    )
    assert page.status_code == 200 and "private-figure" in page.text and 'id="figure"' not in page.text
    assert f"/anchors/{aid}/photos/0" not in c.get(f"/relocalize/anchors/{aid}", headers=app.auth("ben")).text

    from .test_anchor_photos import _camera_line, _page_files

    r = c.post(
        "/relocalize/anchors",
        headers=app.auth("ann"),
        files=_page_files(ref),
        follow_redirects=False,
        data={"name": "from the page", "method": METHOD, "cameras": _camera_line(ref, False), "private": "1"},
    )
    assert r.status_code == 303, r.text
    page_aid = r.headers["location"].rsplit("/", 1)[-1]
    assert c.get(f"/anchors/{page_aid}", headers=app.auth("ben")).json()["private"]
    assert c.get(f"/anchors/{page_aid}/photos/0", headers=app.auth("ben")).status_code == 403


def test_delete_user_takes_their_tokens_sessions_anchors_and_submissions(make_app, split_data, scene):  # noqa: F811
    """``mapfree admin delete-user`` says what it would delete, then deletes the account and all it owns (their
    leaderboard entries too); other accounts keep theirs; the only admin cannot be deleted."""
    from sqlalchemy import func, select

    from mapfree.service.database.models import (
        Anchor,
        ApiToken,
        Submission,
        SubmissionFile,
        User,
        WebSession,
        make_engine,
        session_factory,
    )

    from .conftest import create_users, make_submission
    from .test_anchor_photos import _web_session
    from .test_api import upload

    app = make_app()
    c = app.client
    ref = scene.reference
    for user in ("ann", "ben"):
        c.headers.update(app.auth(user))
        assert upload(c, make_submission(split_data.root / "val"), "val", f"{user}-run").status_code == 202
        r = c.post(
            "/anchors",
            files={
                "image": ("r.jpg", ref.image_path.read_bytes(), "image/jpeg"),
                "depth": ("r.png", ref.depth_path("sensor").read_bytes(), "image/png"),
            },
            data={**_form(ref.intrinsics), "method": METHOD},
        )
        assert r.status_code == 201
    c.headers.pop("Authorization")
    _web_session(app)  # ann signs in with a browser too
    url = app.settings.db_url
    engine = make_engine(url)

    def owned(name: str) -> dict:
        with session_factory(engine)() as db:
            uid = db.scalar(select(User.id).where(User.name == name))
            n = {
                t.__name__: db.scalar(select(func.count()).select_from(t).where(t.user_id == uid))
                for t in (ApiToken, WebSession, Anchor, Submission)
            }
            n["zips"] = db.scalar(select(func.count()).select_from(SubmissionFile))
            n["exists"] = uid is not None
            return n

    assert owned("ann") == {"ApiToken": 1, "WebSession": 1, "Anchor": 1, "Submission": 1, "zips": 2, "exists": True}
    import subprocess
    import sys

    dry = subprocess.run(
        [sys.executable, "-m", "mapfree.cli.admin", "--db", url, "delete-user", "ann"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert (
        dry.returncode == 1
        and "would delete user 'ann' with 1 tokens, 1 sessions, 1 anchors, 1 submissions" in dry.stderr
    ), dry.stderr
    assert owned("ann")["exists"]
    done = subprocess.run(
        [sys.executable, "-m", "mapfree.cli.admin", "--db", url, "delete-user", "ann", "--yes"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 0, done.stderr
    assert owned("ann") == {"ApiToken": 0, "WebSession": 0, "Anchor": 0, "Submission": 0, "zips": 1, "exists": False}
    assert owned("ben")["Anchor"] == 1 and owned("ben")["Submission"] == 1
    assert c.get("/api/me", headers=app.auth("ann")).status_code == 401
    assert c.get("/api/me", headers=app.auth("ben")).status_code == 200
    create_users(url, {"root": None}, admin=True)
    only = subprocess.run(
        [sys.executable, "-m", "mapfree.cli.admin", "--db", url, "delete-user", "root", "--yes"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert only.returncode == 1 and "only admin" in only.stderr
    engine.dispose()


def test_backup_of_a_live_sqlite_database_is_consistent(make_app, tmp_path):  # noqa: F811
    """``mapfree admin backup`` copies the database while another connection keeps writing (in WAL mode, the
    newest rows live in the -wal file a file copy would miss): the copy opens, passes its integrity check and
    holds every row committed before it started. PostgreSQL gets pg_dump advice, its password not echoed."""
    import sqlite3
    import subprocess
    import sys
    import threading

    from mapfree.service.database.models import make_engine

    app = make_app()
    engine = make_engine(app.settings.db_url)
    with engine.begin() as conn:
        conn.exec_driver_sql("CREATE TABLE ticks (n INTEGER)")
        conn.exec_driver_sql("INSERT INTO ticks VALUES (0)")
    stop = threading.Event()

    def write():
        n = 1
        while not stop.is_set() and n < 5000:
            with engine.begin() as conn:
                conn.exec_driver_sql(f"INSERT INTO ticks VALUES ({n})")
            n += 1

    writer = threading.Thread(target=write)
    writer.start()
    try:
        r = subprocess.run(
            [
                sys.executable,
                "-m",
                "mapfree.cli.admin",
                "--db",
                app.settings.db_url,
                "backup",
                str(tmp_path / "copy.db"),
            ],
            capture_output=True,
            text=True,
            timeout=120,
        )
    finally:
        stop.set()
        writer.join(30)
    assert r.returncode == 0 and "integrity checked" in r.stdout, r.stderr
    assert (tmp_path / "copy.db").stat().st_mode & 0o777 == 0o600
    copy = sqlite3.connect(tmp_path / "copy.db")
    assert copy.execute("PRAGMA integrity_check").fetchone()[0] == "ok"
    n, top = copy.execute("SELECT count(*), max(n) FROM ticks").fetchone()
    assert n == top + 1  # a prefix of the inserts: one moment's state
    assert copy.execute("SELECT count(*) FROM users").fetchone()[0] == 2
    assert copy.execute("SELECT version_num FROM alembic_version").fetchone()[0]
    copy.close()
    again = subprocess.run(
        [sys.executable, "-m", "mapfree.cli.admin", "--db", app.settings.db_url, "backup", str(tmp_path / "copy.db")],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert again.returncode == 1 and "exists" in again.stderr  # never overwritten
    pg = subprocess.run(
        [
            sys.executable,
            "-m",
            "mapfree.cli.admin",
            "--db",
            "postgresql://svc:s3cret@db.example:5433/mf",
            "backup",
            "/backups/mf.dump",
        ],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert pg.returncode == 0 and "pg_dump -h db.example -p 5433 -U svc -Fc -f /backups/mf.dump mf" in pg.stdout
    assert "s3cret" not in pg.stdout
    engine.dispose()


def test_the_access_page_revokes_a_token_and_signs_out_another_browser(make_app):  # noqa: F811
    from .test_anchor_photos import _web_session

    app = make_app()
    web, _ = _web_session(app)
    other, _ = _web_session(app)
    page = web.get("/me/access")
    assert page.status_code == 200 and "(this one)" in page.text and page.text.count('id="end-session-') == 2
    csrf = page.text.split('name="csrf_token" value="')[1].split('"')[0]
    tid = page.text.split('id="revoke-token-')[1].split('"')[0]
    assert 'href="/me/access"' in web.get("/me").text
    sid = [s["id"] for s in web.get("/api/sessions").json() if not s["current"]][0]
    assert web.post(f"/me/sessions/{sid}/end", data={"csrf_token": csrf}).status_code == 303
    assert other.get("/api/me").status_code == 401
    assert web.post(f"/me/tokens/{tid}/revoke", data={"csrf_token": "wrong"}).status_code == 403
    assert web.post(f"/me/tokens/{tid}/revoke", data={"csrf_token": csrf}).status_code == 303
    assert app.client.get("/api/me", headers=app.auth("ann")).status_code == 401
    assert web.get("/me/access").status_code == 401  # the session signed in with that token ended with it


def test_metadata_stripping_keeps_pixels_and_drops_every_metadata_segment():
    """Comments, XMP, colour profiles and EXIF go; the image data stays byte for byte; a file whose segments
    cannot be walked (cut short) is re-encoded rather than served with its metadata."""
    import cv2

    from mapfree.service.anchors.exif import clean_photo, strip_metadata

    rgb = (np.random.default_rng(1).random((24, 32, 3)) * 255).astype(np.uint8)
    jpeg = _tagged_jpeg(rgb)
    soi, rest = jpeg[:2], jpeg[2:]
    xmp = b"http://ns.adobe.com/xap/1.0/\x00<x:xmpmeta>GPSLatitude 51,30</x:xmpmeta>"
    com = b"shot by SN-0042-SECRET"
    seg = lambda marker, body: bytes([0xFF, marker]) + (len(body) + 2).to_bytes(2, "big") + body  # noqa: E731
    rich = soi + seg(0xE1, xmp) + seg(0xFE, com) + seg(0xE2, b"ICC_PROFILE\x00\x01\x01device") + rest
    clean = clean_photo(rich)
    for secret in (b"SN-0042", b"GPSLatitude", b"Exif", b"ICC_PROFILE", b"PhoneMaker"):
        assert secret not in clean
    assert clean.endswith(jpeg[jpeg.index(b"\xff\xda") :])  # the entropy-coded data untouched
    assert np.array_equal(_decode(clean), _decode(jpeg))
    broken = soi + seg(0xFE, com)[:6]  # a segment that claims more bytes than the file has
    assert strip_metadata(broken) is None
    png = io.BytesIO()
    info = __import__("PIL.PngImagePlugin", fromlist=["PngInfo"]).PngInfo()
    info.add_text("Comment", "SN-0042-SECRET")
    Image.fromarray(rgb).save(png, format="PNG", pnginfo=info)
    cleaned = clean_photo(png.getvalue())
    assert b"SN-0042" not in cleaned and np.array_equal(_decode(cleaned), rgb)
    assert cv2.imdecode(np.frombuffer(cleaned, np.uint8), cv2.IMREAD_COLOR) is not None


def test_sqlite_database_is_private(tmp_path):
    from mapfree.service.database.models import init_db, make_engine

    engine = make_engine(f"sqlite:///{tmp_path / 'private.db'}")
    init_db(engine)
    engine.dispose()
    for p in tmp_path.glob("private.db*"):
        assert stat.S_IMODE(p.stat().st_mode) & 0o077 == 0, (p.name, oct(p.stat().st_mode))
