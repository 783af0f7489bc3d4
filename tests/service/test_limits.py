"""Memory, threads and limits of the service: each test here failed on the service before its fix."""

from __future__ import annotations

import argparse

import cv2
import numpy as np
import pytest
from sqlalchemy import select

from mapfree.data import Dataset
from mapfree.geometry import Pose

from .conftest import BACKENDS

METHOD = "sift_pnp_sensor"


def _form(K) -> dict:
    return {"fx": repr(K.fx), "fy": repr(K.fy), "cx": repr(K.cx), "cy": repr(K.cy)}


def _upscaled(frame, long_side: int):
    """A realmini frame's JPEG, depth PNG (if any) and intrinsics, upscaled to ``long_side`` (4096: a phone photo)."""
    img = frame.image()
    h, w = img.shape[:2]
    nw, nh = round(w * long_side / max(h, w)), round(h * long_side / max(h, w))
    big = cv2.resize(img, (nw, nh), interpolation=cv2.INTER_CUBIC)
    ok, jpg = cv2.imencode(".jpg", cv2.cvtColor(big, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, 95])
    assert ok
    depth = None
    if frame.depth_path("sensor").exists():
        d = cv2.imread(str(frame.depth_path("sensor")), cv2.IMREAD_UNCHANGED)
        ok, png = cv2.imencode(".png", cv2.resize(d, (nw, nh), interpolation=cv2.INTER_NEAREST))
        depth = png.tobytes()
    return jpg.tobytes(), depth, frame.intrinsics.resized(nw, nh)


def _pose(d: dict) -> Pose:
    return Pose(np.array(d["R"]), np.array(d["t"]))


def _angle_deg(a: Pose, b: Pose) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(a.R.T @ b.R) - 1) / 2, -1, 1))))


def test_a_4096_photo_is_downscaled_before_extraction_and_keeps_its_pose(
    make_app,
    realmini_dir,  # noqa: F811
    monkeypatch,
):
    """A 4096-pixel anchor photo and query reach SIFT at the working size (it used to get them native, and
    upsample them: gigabytes), and the pose is the one of the same photos at their native 720 pixels."""
    from mapfree.matching.sift import SIFTMatcher

    seen: list[tuple[int, int]] = []
    extract = SIFTMatcher.extract

    def spy(self, image):
        seen.append(image.shape[:2])
        assert max(image.shape[:2]) <= 1024, f"SIFT got a {image.shape[1]}x{image.shape[0]} image"
        return extract(self, image)

    monkeypatch.setattr(SIFTMatcher, "extract", spy)
    app = make_app()
    assert app.settings.limits.work_max_side == 1024
    scene = Dataset(realmini_dir).scene("val", "s00000")
    ref, query = scene.reference, scene.frame("seq1/frame_00009.jpg")
    poses = {}
    for size in (None, 4096):
        if size is None:
            r_img, r_depth, r_K = ref.image_path.read_bytes(), ref.depth_path("sensor").read_bytes(), ref.intrinsics
            q_img, _, q_K = query.image_path.read_bytes(), None, query.intrinsics
        else:
            r_img, r_depth, r_K = _upscaled(ref, size)
            q_img, _, q_K = _upscaled(query, size)
        r = app.client.post(
            "/anchors",
            headers=app.auth("ann"),
            data={**_form(r_K), "method": METHOD},
            files={"image": ("r.jpg", r_img), "depth": ("d.png", r_depth)},
        )
        assert r.status_code == 201, r.text
        assert r.json()["intrinsics"]["width"] == r_K.width  # stored as uploaded
        r = app.client.post(
            f"/anchors/{r.json()['id']}/localize",
            headers=app.auth("ben"),
            data=_form(q_K),
            files={"image": ("q.jpg", q_img)},
        )
        assert r.status_code == 200 and r.json()["ok"], r.text
        poses[size] = _pose(r.json())
    assert max(max(s) for s in seen) == 1024  # the 4096 photos, downscaled
    native, big = poses[None], poses[4096]
    assert np.linalg.norm(native.center - big.center) < 0.05, (native.center, big.center)
    assert _angle_deg(native, big) < 1.0
    gt = query.pose
    assert np.linalg.norm(big.center - gt.center) < 0.25 and _angle_deg(big, gt) < 5


def test_heavy_requests_past_the_cap_get_429_with_retry_after(make_app, realmini_dir):  # noqa: F811
    """With every heavy slot taken, localize is refused at once (429 + Retry-After), cheap reads are not."""
    app = make_app(heavy_threads=1, heavy_queue=0)
    ref = Dataset(realmini_dir).scene("val", "s00000").reference
    files = {"image": ("r.jpg", ref.image_path.read_bytes()), "depth": ("d.png", ref.depth_path("sensor").read_bytes())}
    r = app.client.post(
        "/anchors", headers=app.auth("ann"), data={**_form(ref.intrinsics), "method": METHOD}, files=files
    )
    assert r.status_code == 201, r.text
    aid = r.json()["id"]
    pool = app.client.app.state.heavy
    pool._admit("someone")  # one request in: the pool is full
    try:
        r = app.client.post(
            f"/anchors/{aid}/localize",
            headers=app.auth("ben"),
            data=_form(ref.intrinsics),
            files={"image": ("q.jpg", ref.image_path.read_bytes())},
        )
        assert r.status_code == 429 and int(r.headers["retry-after"]) >= 1, r.text
        assert "busy" in r.json()["detail"]
        assert app.client.get("/api/me", headers=app.auth("ben")).status_code == 200
    finally:
        pool._done("someone", 0.0)
    r = app.client.post(
        f"/anchors/{aid}/localize",
        headers=app.auth("ben"),
        data=_form(ref.intrinsics),
        files={"image": ("q.jpg", ref.image_path.read_bytes())},
    )
    assert r.status_code == 200, r.text


def test_anchor_cache_is_bounded_in_bytes_and_answers_as_uncached(realmini_dir):
    """Prepared anchors hold features and working-size depth, no pixels; their measured size bounds the cache
    (the least recently used go first), and a cached anchor answers exactly as one prepared afresh."""
    from mapfree.service.anchors.localizers import Localizers, Photo

    scene = Dataset(realmini_dir).scene("val", "s00000")
    ref, q = scene.reference, scene.frame("seq1/frame_00009.jpg")
    img, depth = ref.image(), ref.depth("sensor")
    h, w = img.shape[:2]
    size = (round(w * 4096 / max(h, w)), round(h * 4096 / max(h, w)))  # a 4096-pixel photo and its depth
    big = [
        Photo(
            cv2.resize(img, size, interpolation=cv2.INTER_CUBIC),
            ref.intrinsics.resized(*size),
            cv2.resize(depth, size, interpolation=cv2.INTER_NEAREST),
        )
    ]
    fresh = Localizers(per_method=1, cache_bytes=0)  # nothing kept: every call prepares anew
    want = fresh.localize_photos("a", METHOD, 1, lambda: big, q.image(), q.intrinsics)
    assert len(fresh.anchors) == 0 and want.ok

    probe = Localizers(per_method=1)
    probe.check("p", METHOD, big, 1)
    entry = probe.anchors.get(("p", METHOD, 1))
    assert entry is not None
    ref_prepared = entry.photos[0].reference
    assert ref_prepared.view.image.size == 0  # no pixels
    assert max(ref_prepared.depth.shape) == 1024  # depth at the working size
    held = (
        ref_prepared.features.data["descriptors"].nbytes + ref_prepared.features.kpts.nbytes + ref_prepared.depth.nbytes
    )
    assert held <= entry.nbytes <= held + (1 << 20)  # measured, not guessed
    assert entry.nbytes < 5 << 20  # the decoded 4096-pixel photo and its depth: 113 MB

    loc = Localizers(per_method=1, cache_bytes=int(2.5 * entry.nbytes))  # room for two of these anchors
    for i in range(3):
        est = loc.localize_photos(f"a{i}", METHOD, 1, lambda: big, q.image(), q.intrinsics)
        assert loc.anchors.total <= loc.anchors.max_bytes
        assert len(loc.anchors) == min(i + 1, 2)
        np.testing.assert_array_equal(est.pose.R, want.pose.R)
        np.testing.assert_array_equal(est.pose.t, want.pose.t)
    again = loc.localize_photos("a2", METHOD, 1, lambda: pytest.fail("prepared again"), q.image(), q.intrinsics)
    np.testing.assert_array_equal(again.pose.t, want.pose.t)  # answered from the cache
    assert loc.anchors.get(("a0", METHOD, 1)) is None  # the least recently used went first


def test_a_test_limit_of_zero_means_none_and_unlimited_is_explicit(make_app, split_data):  # noqa: F811
    """``admin set-limit USER 0`` and ``serve --test-daily-limit 0`` refuse every test submission (0 used to
    mean unlimited while /api/me said 0 left); ``unlimited`` is its own word, shown as such by /api/me."""
    from mapfree.cli.serve import register, settings_from_args

    from .conftest import make_submission, mapfree

    parser = argparse.ArgumentParser()
    register(parser.add_subparsers())
    parse = lambda *a: settings_from_args(parser.parse_args(["serve", *a]))  # noqa: E731
    assert parse("--test-daily-limit", "0").test_daily_limit == 0
    assert parse("--test-daily-limit", "unlimited").test_daily_limit < 0
    assert parse().test_daily_limit == 5
    with pytest.raises(SystemExit):
        parse("--test-daily-limit", "lots")

    app = make_app(test_daily_limit=parse("--test-daily-limit", "0").test_daily_limit)
    data = make_submission(split_data.gt / "test", noise=0.5, seed=3)

    def up(user):
        return app.client.post(
            "/api/submissions",
            headers=app.auth(user),
            files={"file": ("s.zip", data)},
            data={"split": "test", "name": "t"},
        )

    def me(user):
        return app.client.get("/api/me", headers=app.auth(user)).json()

    assert me("ben")["test_daily_limit"] == 0 and me("ben")["test_evaluations_left_today"] == 0
    for _ in range(3):
        r = up("ben")
        assert r.status_code == 429 and "limit is 0" in r.json()["detail"], r.text
    db = ["--db", app.settings.db_url]
    mapfree("admin", *db, "set-limit", "ann", "unlimited")
    assert me("ann")["test_daily_limit"] == "unlimited" and me("ann")["test_evaluations_left_today"] == "unlimited"
    assert [up("ann").status_code for _ in range(3)] == [202] * 3
    mapfree("admin", *db, "set-limit", "ann", "0")
    assert me("ann")["test_daily_limit"] == 0 and me("ann")["test_evaluations_left_today"] == 0
    assert up("ann").status_code == 429
    mapfree("admin", *db, "set-limit", "ann", "default")  # the server's: 0 here
    assert up("ann").status_code == 429
    app.settings.test_daily_limit = 4
    assert me("ann")["test_evaluations_left_today"] == 1  # 3 used in the last 24 h
    assert up("ann").status_code == 202 and up("ann").status_code == 429
    assert "test_limit=default" in mapfree("admin", *db, "list-users")


@pytest.mark.parametrize("backend", BACKENDS)
def test_parallel_uploads_cannot_overrun_the_storage_quota(backend, split_data, tmp_path):
    """Ten 4.6 MB uploads at once against a 10 MiB quota: at most two are stored (all ten were on PostgreSQL,
    three on SQLite: an upload's bytes counted only once its copy had started, after the quota check)."""
    import zipfile
    from concurrent.futures import ThreadPoolExecutor

    import httpx

    from .conftest import db_url_for, start_server, stop_server, truth_poses, zip_of

    scene = sorted(p for p in (split_data.root / "val").iterdir() if p.is_dir())[0]
    name, v = truth_poses(scene)[0]
    line = f"{name} {' '.join(map(str, v))} 5\n".encode()
    data = zip_of({f"pose_{scene.name}.txt": line * (4_600_000 // len(line))}, zipfile.ZIP_STORED)
    assert 4.5e6 < len(data) < 4.7e6
    srv = start_server(
        db_url_for(backend, tmp_path),
        backend,
        split_data,
        tmp_path,
        workers=0,
        extra=("--storage-quota-mb", "10", "--max-upload-mb", "5"),
    )
    try:

        def upload(i: int) -> int:
            with httpx.Client(
                base_url=srv.url, timeout=60, headers={"Authorization": f"Bearer {srv.tokens['bob']}"}
            ) as c:
                return c.post(
                    "/api/submissions", files={"file": ("s.zip", data)}, data={"split": "val", "name": f"q{i}"}
                ).status_code

        with ThreadPoolExecutor(10) as ex:
            codes = list(ex.map(upload, range(10)))
        with srv.client("bob") as c:
            me = c.get("/api/me").json()
            stored = [s for s in c.get("/api/submissions").json() if s["status"] != "uploading"]
    finally:
        stop_server(srv.proc)
    assert codes.count(202) == len(stored) <= 2 and codes.count(202) >= 1, codes
    assert set(codes) <= {202, 413}, codes
    assert me["storage_used_bytes"] <= 10 << 20, me


def test_an_upload_reserves_its_bytes_before_its_copy_starts(make_app, split_data, monkeypatch):  # noqa: F811
    """While one upload is being copied in, a second one of the same account sees its bytes (it saw none until
    the first chunk was stored: the race that let parallel uploads pass the quota); a failed copy frees them."""
    from mapfree.service.accounts import quota as storage
    from mapfree.service.database.models import User
    from mapfree.service.leaderboard import submissions

    from .conftest import make_submission

    data = make_submission(split_data.root / "val")
    app = make_app(storage_quota_bytes=int(1.5 * len(data)))
    sessions = app.client.app.state.sessions
    seen, real_copy = [], submissions.copy_in

    def copy_in(db, sid, f):
        with sessions() as other:  # another request's connection, between the quota check and the copy
            uid = other.scalar(select(User.id).where(User.name == "ann"))
            seen.append(storage.stored_bytes(other, uid))
            other.commit()
        if len(seen) == 2:
            raise OSError("disk full")  # a copy that fails: its reservation must go with it
        return real_copy(db, sid, f)

    monkeypatch.setattr(submissions, "copy_in", copy_in)

    def up():
        return app.client.post(
            "/api/submissions",
            headers=app.auth("ann"),
            files={"file": ("s.zip", data)},
            data={"split": "val", "name": "x"},
        )

    assert up().status_code == 202
    assert seen == [len(data)]
    r = up()
    assert r.status_code == 413 and "storage quota" in r.json()["detail"], r.text
    monkeypatch.setattr(app.settings, "storage_quota_bytes", 3 * len(data))
    assert up().status_code == 500  # the failed copy
    assert seen[1] == 2 * len(data)
    with sessions() as db:
        uid = db.scalar(select(User.id).where(User.name == "ann"))
        assert storage.stored_bytes(db, uid) == len(data)  # released


def test_failed_token_checks_never_lock_out_a_valid_token(make_app):  # noqa: F811
    """Past the failures allowed from one address, wrong tokens get 429, but a valid token and a correct
    browser sign-in from the same address still go through (they got 429 too)."""
    app = make_app(auth_failures_per_minute=3)
    c = app.client
    for i in range(3):
        assert c.get("/api/me", headers={"Authorization": f"Bearer mf_guess{i}"}).status_code == 401
    r = c.get("/api/me", headers={"Authorization": "Bearer mf_guess3"})
    assert r.status_code == 429 and int(r.headers["retry-after"]) >= 1, r.text

    def sign_in(token: str):
        csrf = c.get("/login").text.split('name="csrf_token" value="')[1].split('"')[0]
        return c.post("/login", data={"token": token, "csrf_token": csrf}, follow_redirects=False)

    r = sign_in("mf_wrong")
    assert r.status_code == 429 and int(r.headers["retry-after"]) >= 1 and "too many" in r.text
    assert c.get("/api/me", headers=app.auth("ann")).json()["name"] == "ann"
    assert sign_in(app.tokens["ben"]).status_code == 303
    assert c.get("/api/me").json()["name"] == "ben"  # the session cookie works too


def test_leaderboards_are_paged_and_the_csv_streams(make_app):  # noqa: F811
    """At 20,000 entries one board request read and rendered them all (seconds, 10 MB); now a page of at most
    ``per_page`` rows (200 at most) answers quickly, ranks continue across pages, and the CSV streams."""
    import time as _time

    from sqlalchemy import insert

    from mapfree.service.database.models import Result, Submission, User
    from mapfree.service.leaderboard.scoring import METRIC_KEYS

    app = make_app()
    n = 20_000
    rng = np.random.default_rng(0)
    auc = np.round(rng.uniform(0, 1, n), 2)  # many ties: shared ranks across page boundaries
    with app.client.app.state.sessions.begin() as db:
        uids = list(db.scalars(select(User.id)))
        subs = [
            {
                "id": f"s{i:06d}",
                "user_id": uids[i % 2],
                "split": "val",
                "name": f"m{i}",
                "public": True,
                "status": "done",
                "sha256": "",
                "created_at": 1e9 + i,
            }
            for i in range(n)
        ]
        db.execute(insert(Submission), subs)
        db.execute(
            insert(Result),
            [
                {
                    "submission_id": s["id"],
                    "metrics": {METRIC_KEYS[0]: float(a), METRIC_KEYS[4]: 1.0 - float(a)},
                    "per_scene": {},
                    "problems": [],
                    "worker_id": "w",
                    "attempt": 1,
                    "eval_seconds": 0.1,
                }
                for s, a in zip(subs, auc)
            ],
        )
    want = sorted(range(n), key=lambda i: (-auc[i], i))
    c = app.client
    t0 = _time.perf_counter()
    r = c.get("/api/leaderboard/val", params={"per_page": 100, "page": 3})
    dt = _time.perf_counter() - t0
    assert r.status_code == 200, r.text
    d = r.json()
    assert d["total"] == n and d["pages"] == n // 100 and d["page"] == 3 and len(d["entries"]) == 100
    assert [e["id"] for e in d["entries"]] == [f"s{i:06d}" for i in want[200:300]]
    first = d["entries"][0]
    assert first["rank"] == 1 + int((auc > auc[want[200]]).sum())  # global competition rank
    assert dt < 1.5 and len(r.content) < 200_000, (dt, len(r.content))
    assert len(c.get("/api/leaderboard/val").json()["entries"]) == 50  # the default page
    assert c.get("/api/leaderboard/val", params={"per_page": 10_000}).status_code == 422
    best = c.get("/api/leaderboard/val", params={"view": "best"}).json()
    assert best["total"] == 2
    page = c.get("/leaderboard/val", params={"page": 2}, headers={"accept": "text/html"})
    assert page.status_code == 200 and "page 2 of 400" in page.text and 'id="page-next"' in page.text
    assert page.text.count('class="entry"') == 50
    with c.stream("GET", "/api/leaderboard/val.csv") as r:
        assert r.status_code == 200 and "content-length" not in r.headers  # streamed
        lines = "".join(r.iter_text()).splitlines()
    assert len(lines) == n + 1 and lines[1].split(",")[1] == f"m{want[0]}"
