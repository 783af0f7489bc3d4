"""The service over real HTTP (uvicorn + worker processes), on SQLite and PostgreSQL: the submission flow,
what ``test`` hides, auth, privacy, the daily limit, and the relocalization anchors."""

from __future__ import annotations

import math

import pytest

from .conftest import OPERATOR, make_submission

VCRE_AUC = "AUC @ VCRE < 90px"


def upload(c, data: bytes, split: str = "val", name: str = "run", public: bool = True):
    return c.post(
        "/api/submissions",
        files={"file": ("sub.zip", data, "application/zip")},
        data={"split": split, "name": name, "public": str(public).lower()},
    )


def expected_metrics(server, data: bytes, split: str, tmp_path) -> dict:
    """What the benchmark core says, computed in this process on the same ZIP, as the server shows it (test: no
    medians nor AUCs, rounded)."""
    from mapfree.benchmark import evaluate
    from mapfree.service.leaderboard.submissions import shown_metrics

    p = tmp_path / "expected.zip"
    p.write_bytes(data)
    gt = server.data.gt if split == "test" else None
    return shown_metrics(split, evaluate(p, server.data.root, split, gt_root=gt).to_dict()["metrics"])


def test_health_and_openapi(server):
    with server.client() as c:
        h = c.get("/health/detail", headers=OPERATOR).json()
        assert h["status"] == "ok" and h["db"] == server.backend and len(h["workers"]) >= 2
        paths = c.get("/openapi.json").json()["paths"]
    for p in (
        "/api/submissions",
        "/api/leaderboard/{split}",
        "/anchors",
        "/anchors/{aid}/localize",
        "/anchors/{aid}",
        "/health",
    ):
        assert p in paths


def test_val_submission_flow(server, tmp_path):
    data = make_submission(server.data.root / "val", noise=0.3, seed=1, drop_every=4)
    with server.client("alice") as c:
        r = upload(c, data, "val", "alice-noisy")
        assert r.status_code == 202, r.text
        sid = r.json()["id"]
        assert r.json()["status"] == "queued"  # stored and queued before the answer
    d = server.wait_done(sid, "alice")
    assert d["status"] == "done", d
    want = expected_metrics(server, data, "val", tmp_path)
    for k, v in want.items():
        got = d["metrics"][k]
        assert (got is None and (v is None or not math.isfinite(v))) or got == pytest.approx(v, abs=1e-9), k
    assert 0 < d["metrics"][VCRE_AUC] < 1  # the noise makes some frames fail
    assert d["per_scene"] and len(d["per_scene"]) == len(list((server.data.root / "val").iterdir()))
    assert d["plots"], "val results come with plots"
    with server.client() as anon:
        png = anon.get(d["plots"][0])
        assert png.status_code == 200 and png.content.startswith(b"\x89PNG")
        answer = anon.get("/api/leaderboard/val").json()
        board = answer["entries"]
        assert any(e["id"] == sid for e in board)
        assert any(r["name"].startswith("RPR") for r in answer["reference"])  # apart, never ranked
        vals = [e["metrics"]["vcre_auc"] for e in board if e["metrics"]["vcre_auc"] is not None]
        assert vals == sorted(vals, reverse=True)
        by_trans = anon.get("/api/leaderboard/val", params={"sort": "med_trans"}).json()["entries"]
        t = [e["metrics"]["med_trans"] for e in by_trans if e["metrics"]["med_trans"] is not None]
        assert t == sorted(t)
        assert anon.get("/api/leaderboard/val", params={"sort": "bogus"}).status_code == 422
        page = anon.get(f"/submissions/{sid}", headers={"accept": "text/html"})
        assert page.status_code == 200 and "alice-noisy" in page.text
    with server.client("alice") as c:
        assert sid in [s["id"] for s in c.get("/api/submissions").json()]


def test_test_split_ground_truth_stays_private(server, tmp_path):
    data = make_submission(server.data.gt / "test", noise=0.0, seed=2)
    with server.client("bob") as c:
        r = upload(c, data, "test", "bob-exact")
        assert r.status_code == 202, r.text
        sid = r.json()["id"]
    d = server.wait_done(sid, "bob")
    assert d["status"] == "done", d
    assert d["metrics"]["Precision @ VCRE < 90px"] == pytest.approx(1.0)  # scored against the private poses
    assert d["metrics"][VCRE_AUC] is None  # no AUC on test
    assert d["metrics"] == pytest.approx(expected_metrics(server, data, "test", tmp_path))
    assert "per_scene" not in d and d["plots"] == []
    with server.client("bob") as c:
        assert c.get(f"/submissions/{sid}/plots/vcre.png").status_code == 404
        html = c.get(f"/submissions/{sid}").text
        assert "per-scene" not in html and "Per scene" not in html
        # no route serves dataset files, whatever the path trick
        for path in (
            "/data/test/s00525/poses.txt",
            "/static/../../test/s00525/poses.txt",
            "/static/%2e%2e/%2e%2e/config.py",
            "/test/s00525/poses.txt",
            "/gt/test",
            "/api/submissions/" + sid + "/per_scene",
        ):
            r = c.get(path)
            assert r.status_code == 404, path
            assert "0.0000" not in r.text
    gt_text = next((server.data.gt / "test").iterdir()).joinpath("poses.txt").read_text().split()[9]
    assert gt_text not in str(d)


def test_daily_test_limit(server):
    data = make_submission(server.data.gt / "test", noise=0.5, seed=3)
    with server.client("carol") as c:  # carol's limit is 2 per 24 h
        assert c.get("/api/me").json()["test_evaluations_left_today"] == 2
        assert upload(c, data, "test", "c1", public=False).status_code == 202
        assert upload(c, data, "test", "c2", public=False).status_code == 202
        r = upload(c, data, "test", "c3", public=False)
        assert r.status_code == 429 and "daily limit" in r.json()["detail"]
        val = make_submission(server.data.root / "val")
        assert upload(c, val, "val", "val-is-not-limited", public=False).status_code == 202


def test_auth_required_on_every_write(server):
    data = make_submission(server.data.root / "val")
    with server.client() as anon:
        assert upload(anon, data).status_code == 401
        assert (
            anon.post(
                "/anchors", data={"fx": 1, "fy": 1, "cx": 0, "cy": 0}, files={"image": ("a.png", b"x")}
            ).status_code
            == 401
        )
        assert (
            anon.post(
                "/anchors/abc/localize", data={"fx": 1, "fy": 1, "cx": 0, "cy": 0}, files={"image": ("a.png", b"x")}
            ).status_code
            == 401
        )
        assert anon.delete("/anchors/abc").status_code == 401
        assert anon.patch("/api/submissions/abc", json={"public": True}).status_code == 401
        assert anon.get("/api/submissions").status_code == 401
        assert anon.get("/api/me").status_code == 401
    with server.client(headers={"Authorization": "Bearer mf_not-a-real-token"}) as bad:
        assert upload(bad, data).status_code == 401
        assert bad.get("/api/me").status_code == 401
    with server.client(headers={"Authorization": "Basic YWxpY2U6eA=="}) as basic:
        assert upload(basic, data).status_code == 401


def test_cookie_writes_need_csrf(server):
    with server.client(follow_redirects=False) as c:
        login = c.get("/login")
        csrf = login.text.split('name="csrf_token" value="')[1].split('"')[0]
        assert c.post("/login", data={"token": server.tokens["alice"], "csrf_token": "wrong"}).status_code == 403
        r = c.post("/login", data={"token": server.tokens["alice"], "csrf_token": csrf})
        assert r.status_code == 303 and "mapfree_session" in r.headers.get("set-cookie", "")
        assert "httponly" in r.headers["set-cookie"].lower() and "samesite=lax" in r.headers["set-cookie"].lower()
        data = make_submission(server.data.root / "val")
        r = upload(c, data)  # cookie but no CSRF token: refused
        assert r.status_code == 403 and "CSRF" in r.json()["detail"]
        page = c.get("/submit").text
        session_csrf = page.split('name="csrf_token" value="')[1].split('"')[0]
        r = c.post(
            "/api/submissions",
            files={"file": ("s.zip", data)},
            data={"split": "val", "name": "cookie", "csrf_token": session_csrf},
        )
        assert r.status_code == 202, r.text


def test_private_submissions(server):
    data = make_submission(server.data.root / "val", noise=0.1, seed=5)
    with server.client("bob") as bob:
        sid = upload(bob, data, "val", "bob-private", public=False).json()["id"]
    server.wait_done(sid, "bob")
    with server.client("alice") as alice, server.client() as anon:
        for c in (alice, anon):
            assert c.get(f"/api/submissions/{sid}").status_code == 404
            assert c.get(f"/submissions/{sid}").status_code == 404
        assert sid not in str(anon.get("/api/leaderboard/val").json())
        assert alice.patch(f"/api/submissions/{sid}", json={"public": True}).status_code == 404
    with server.client("bob") as bob:
        assert bob.get(f"/api/submissions/{sid}").json()["public"] is False
        assert bob.patch(f"/api/submissions/{sid}", json={"public": True}).json()["public"] is True
    with server.client() as anon:
        assert anon.get(f"/api/submissions/{sid}").status_code == 200
        assert sid in str(anon.get("/api/leaderboard/val").json())
