"""Leaderboard features over real HTTP (SQLite, and PostgreSQL when configured): equal scores share a rank,
each account's best, per-scene boards, CSV export, comparing two submissions, method metadata, withdrawing
and downloading one's own submission, and the published rows kept apart."""

from __future__ import annotations

import csv
import io
import uuid

import pytest

from mapfree.service.leaderboard.boards import competition_ranks

from .conftest import create_users, make_submission
from .test_api import upload

VCRE_AUC = "AUC @ VCRE < 90px"


def fresh_users(server, *names: str) -> list[str]:
    """New accounts on the running server (unique names), so counts on the board are exact."""
    tag = uuid.uuid4().hex[:6]
    made = create_users(server.db_url, {f"{n}-{tag}": None for n in names})
    server.tokens.update(made)
    return list(made)


def submit_done(server, user: str, data: bytes, name: str, split: str = "val", public: bool = True) -> dict:
    with server.client(user) as c:
        r = upload(c, data, split, name, public)
        assert r.status_code == 202, r.text
    d = server.wait_done(r.json()["id"], user)
    assert d["status"] == "done", d
    return d


def test_competition_ranks():
    assert competition_ranks([0.9, 0.9, 0.5, 0.5, 0.5, 0.1, None]) == [1, 1, 3, 3, 3, 6, None]
    assert competition_ranks([]) == []


@pytest.fixture(scope="module")
def board_data(server):
    """Two accounts: the same ZIP from both (a tie), and a worse one from the first."""
    u1, u2 = fresh_users(server, "tie-a", "tie-b")
    val = server.data.root / "val"
    good, worse = make_submission(val, noise=0.15, seed=11), make_submission(val, noise=0.6, seed=12, drop_every=2)
    a = submit_done(server, u1, good, f"{u1}-good")
    b = submit_done(server, u2, good, f"{u2}-same")
    c = submit_done(server, u1, worse, f"{u1}-worse")
    return {"users": (u1, u2), "a": a, "b": b, "c": c}


def test_ties_share_a_rank_and_best_per_account(server, board_data):
    u1, u2 = board_data["users"]
    with server.client() as anon:
        answer = anon.get("/api/leaderboard/val").json()
    mine = {e["id"]: e for e in answer["entries"] if e["user"] in (u1, u2)}
    a, b, c = (mine[board_data[k]["id"]] for k in "abc")
    assert a["metrics"] == b["metrics"] and a["rank"] == b["rank"]
    assert c["metrics"]["vcre_auc"] < a["metrics"]["vcre_auc"] and c["rank"] > a["rank"] + 1
    ranks = [e["rank"] for e in answer["entries"]]
    assert ranks == competition_ranks([e["metrics"]["vcre_auc"] for e in answer["entries"]])
    assert a["created_at"] <= c["created_at"] and a["method"]["extra_data"] is False
    # the published rows are apart, on the real Map-free data, and MicKey's precision is a number
    assert all("reference" not in e for e in answer["entries"])
    mickey = next(r for r in answer["reference"] if r["name"].startswith("MicKey"))
    assert mickey["dataset"].startswith("Map-free val") and mickey["metrics"]["vcre_prec"] == 0.45
    with server.client() as anon:
        best = anon.get("/api/leaderboard/val", params={"view": "best"}).json()["entries"]
        assert anon.get("/api/leaderboard/val", params={"view": "bogus"}).status_code == 422
    users = [e["user"] for e in best]
    assert len(users) == len(set(users))
    assert board_data["c"]["id"] not in {e["id"] for e in best}  # u1's worse run hides behind the better one


def test_per_scene_board_and_csv(server, board_data):
    scene = sorted(board_data["a"]["per_scene"])[0]
    want = board_data["a"]["per_scene"][scene][VCRE_AUC]
    with server.client() as anon:
        per_scene = anon.get("/api/leaderboard/val", params={"scene": scene, "sort": "med_trans"}).json()
        assert anon.get("/api/leaderboard/test", params={"scene": "s00525"}).status_code == 422
        r = anon.get("/api/leaderboard/val.csv", params={"view": "best"})
    e = next(e for e in per_scene["entries"] if e["id"] == board_data["a"]["id"])
    assert e["metrics"]["vcre_auc"] == want
    trans = [e["metrics"]["med_trans"] for e in per_scene["entries"] if e["metrics"]["med_trans"] is not None]
    assert trans == sorted(trans)
    assert r.status_code == 200 and r.headers["content-type"].startswith("text/csv")
    assert "attachment" in r.headers["content-disposition"]
    rows = list(csv.DictReader(io.StringIO(r.text)))
    row = next(x for x in rows if x["name"] == board_data["a"]["name"] or x["name"] == board_data["b"]["name"])
    assert float(row[VCRE_AUC]) == pytest.approx(board_data["a"]["metrics"][VCRE_AUC], abs=1e-12)
    assert row["submitted_utc"].endswith("Z") and int(row["rank"]) >= 1


def test_compare_two_submissions(server, board_data):
    a, c = board_data["a"], board_data["c"]
    with server.client() as anon:
        cmp = anon.get("/api/compare", params={"a": a["id"], "b": c["id"]}).json()
        assert anon.get("/api/compare", params={"a": a["id"], "b": "nope"}).status_code == 404
    row = next(r for r in cmp["metrics"] if r["metric"] == VCRE_AUC)
    assert row["diff"] == pytest.approx(c["metrics"][VCRE_AUC] - a["metrics"][VCRE_AUC])
    assert row["better"] == "a"
    trans = next(r for r in cmp["metrics"] if r["metric"] == "Average Median Translation Error")
    assert trans["better"] == ("a" if a["metrics"][trans["metric"]] < c["metrics"][trans["metric"]] else "b")
    assert len(cmp["metrics"]) == len(a["metrics"])  # every figure, the 50 cm / 45 px ones too
    assert set(cmp["per_scene"]) == set(a["per_scene"])


def test_method_metadata(server, board_data):
    u1, u2 = board_data["users"]
    sid = board_data["a"]["id"]
    meta = {
        "description": "SIFT + PnP, tuned",
        "paper_url": "https://arxiv.org/abs/2210.05494",
        "code_url": "https://github.com/example/reloc",
        "runtime_ms": 85.5,
        "extra_data": True,
    }
    with server.client(u1) as c, server.client(u2) as other:
        assert c.put(f"/api/submissions/{sid}/method", json=meta).json() == meta
        assert other.put(f"/api/submissions/{sid}/method", json=meta).status_code == 404
        for bad, field in (
            ({"paper_url": "javascript:alert(1)"}, "paper_url"),
            ({"code_url": "ftp://x/y"}, "code_url"),
            ({"description": "evil \u202e txt"}, "description"),
            ({"runtime_ms": -3}, "runtime_ms"),
        ):
            r = c.put(f"/api/submissions/{sid}/method", json={**meta, **bad})
            assert r.status_code == 422 and field in r.json()["detail"], r.text
    with server.client() as anon:
        e = next(e for e in anon.get("/api/leaderboard/val").json()["entries"] if e["id"] == sid)
    assert e["method"] == meta


def test_method_metadata_with_the_upload(server):
    """``POST /api/submissions`` takes the same optional method fields as the web form and ``PUT …/method``,
    checked the same way; a bad field refuses the whole upload before anything is stored or counted."""
    (u,) = fresh_users(server, "meta-up")
    data = make_submission(server.data.root / "val", noise=0.2, seed=21)
    meta = {
        "description": "LoFTR + PnP\nwith sensor depth",
        "paper_url": "https://arxiv.org/abs/2210.05494",
        "code_url": "https://github.com/example/reloc",
        "runtime_ms": 120.0,
        "extra_data": True,
    }
    form = {**meta, "runtime_ms": "120", "extra_data": "true"}
    with server.client(u) as c:
        for bad, field in (
            ({"paper_url": "javascript:alert(1)"}, "paper_url"),
            ({"code_url": "ftp://x/y"}, "code_url"),
            ({"description": "evil \u202e txt"}, "description"),
            ({"runtime_ms": "-3"}, "runtime_ms"),
            ({"runtime_ms": "fast"}, "runtime_ms"),
        ):
            r = c.post(
                "/api/submissions",
                files={"file": ("sub.zip", data, "application/zip")},
                data={"split": "val", "name": "bad-meta", **form, **bad},
            )
            assert r.status_code == 422 and field in r.json()["detail"], r.text
        assert c.get("/api/submissions").json() == []  # nothing stored, nothing counted
        r = c.post(
            "/api/submissions",
            files={"file": ("sub.zip", data, "application/zip")},
            data={"split": "val", "name": "with-meta", "public": "true", **form},
        )
        assert r.status_code == 202, r.text
        assert r.json()["method"] == meta
        plain = upload(c, data, "val", "no-meta")
        assert plain.status_code == 202 and plain.json()["method"] == {
            "description": "",
            "paper_url": "",
            "code_url": "",
            "runtime_ms": None,
            "extra_data": False,
        }
    sid = r.json()["id"]
    assert server.wait_done(sid, u)["status"] == "done"
    with server.client() as anon:
        e = next(e for e in anon.get("/api/leaderboard/val").json()["entries"] if e["id"] == sid)
    assert e["method"] == meta


def test_withdraw_and_download(server):
    (owner,) = fresh_users(server, "withdrawer")
    server.tokens.update(create_users(server.db_url, {(admin := f"root-{owner}"): None}, admin=True))
    data = make_submission(server.data.gt / "test", noise=0.3, seed=21)
    with server.client(owner) as c:
        before = c.get("/api/me").json()["test_evaluations_left_today"]
    d = submit_done(server, owner, data, "to-withdraw", split="test")
    sid = d["id"]
    with server.client(owner) as c, server.client("bob") as bob, server.client() as anon:
        z = c.get(f"/api/submissions/{sid}/zip")
        assert z.status_code == 200 and z.content == data and "attachment" in z.headers["content-disposition"]
        assert bob.get(f"/api/submissions/{sid}/zip").status_code == 404
        assert anon.get(f"/api/submissions/{sid}/zip").status_code == 401
        assert bob.delete(f"/api/submissions/{sid}").status_code == 404
        (entry,) = [e for e in anon.get("/api/leaderboard/test").json()["entries"] if e["id"] == sid]
        assert entry["metrics"]["vcre_auc"] is None and entry["metrics"]["vcre_prec"] is not None  # no AUC on test
        assert c.delete(f"/api/submissions/{sid}").status_code == 204
        # the owner (and admins) still get the record their list shows; everyone else 404
        got = c.get(f"/api/submissions/{sid}").json()
        assert got["status"] == "withdrawn" and got["metrics"] is None and got["plots"] == [], got
        assert got["withdrawn_at"] == got["finished_at"] and got["withdrawn_at"] >= got["created_at"], got
        assert c.get(f"/submissions/{sid}").status_code == 200  # its page says withdrawn (browser test)
        assert f'href="/submissions/{sid}"' in c.get("/me").text  # and the owner's history links to it
        with server.client(admin) as adm:
            assert adm.get(f"/api/submissions/{sid}").json()["status"] == "withdrawn"
        assert bob.get(f"/api/submissions/{sid}").status_code == 404
        assert anon.get(f"/api/submissions/{sid}").status_code == 404
        assert c.get(f"/api/submissions/{sid}/zip").status_code == 409  # withdrawn: said so, not "no such"
        assert c.delete(f"/api/submissions/{sid}").status_code == 409
        assert sid not in str(anon.get("/api/leaderboard/test").json())
        mine = {s["id"]: s for s in c.get("/api/submissions").json()}
        assert mine[sid]["status"] == "withdrawn" and mine[sid]["metrics"] is None
        # withdrawing does not give the test evaluation back (else the daily limit could be dodged)
        assert c.get("/api/me").json()["test_evaluations_left_today"] == before - 1


def test_a_withdrawn_submission_is_final(server, board_data):
    """Once withdrawn, every change its owner asks for is a 409 saying so (the visibility PATCH used to answer
    200 and mark it public), others still get 404, and no board, CSV or comparison ever shows it again."""
    (owner,) = fresh_users(server, "final")
    d = submit_done(server, owner, make_submission(server.data.root / "val", noise=0.2, seed=61), "gone-for-good")
    sid, other = d["id"], board_data["a"]["id"]
    meta = {"description": "x", "paper_url": "", "code_url": "", "runtime_ms": None, "extra_data": False}
    with server.client(owner) as c, server.client("bob") as bob, server.client() as anon:
        assert sid in str(anon.get("/api/leaderboard/val").json())
        assert c.delete(f"/api/submissions/{sid}").status_code == 204
        for r in (
            c.patch(f"/api/submissions/{sid}", json={"public": True}),
            c.put(f"/api/submissions/{sid}/method", json=meta),
            c.delete(f"/api/submissions/{sid}"),
            c.get(f"/api/submissions/{sid}/zip"),
        ):
            assert r.status_code == 409, (r.request.method, r.text)
            assert f"submission {sid} ('gone-for-good') was withdrawn on " in r.json()["detail"], r.text
        for r in (
            bob.patch(f"/api/submissions/{sid}", json={"public": True}),
            bob.put(f"/api/submissions/{sid}/method", json=meta),
            bob.delete(f"/api/submissions/{sid}"),
        ):
            assert r.status_code == 404, r.text  # not theirs: nothing to learn about it
        mine = {s["id"]: s for s in c.get("/api/submissions").json()}
        assert mine[sid]["status"] == "withdrawn" and mine[sid]["public"] is False
        for view in ("all", "best"):
            assert sid not in str(anon.get("/api/leaderboard/val", params={"view": view}).json())
            assert sid not in anon.get("/api/leaderboard/val.csv", params={"view": view}).text
        assert anon.get("/api/compare", params={"a": other, "b": sid}).status_code == 404
        assert c.get("/compare", params={"id": [other, sid]}).status_code == 404
        # the web form (a page opened before withdrawing): the history page with the reason above it
        r = c.post(f"/submissions/{sid}/visibility", data={"public": "true"}, headers={"Accept": "text/html"})
        assert r.status_code == 409 and 'id="history"' in r.text and "was withdrawn on" in r.text, r.text[-1500:]
        assert c.get(f"/submissions/{sid}/zip", headers={"Accept": "text/html"}).status_code == 409
        assert c.get("/api/submissions").json()[0]["public"] is False


def test_a_figures_first_view_is_drawn_on_the_heavy_threads(make_app):
    """Drawing a figure (its first view) ran on the shared thread pool, where 60 first renders stalled another
    user's ``GET /api/me`` for 22 s. Now it runs on the heavy pool: with room for one heavy request, concurrent
    first views of a fresh submission's figures get one drawing and 429s with ``Retry-After`` (the pool's
    answer), not four drawings side by side; a stored figure is then served to all from the shared pool."""
    import threading

    from mapfree.service.leaderboard import worker

    app = make_app(heavy_threads=1, heavy_queue=0)
    c, auth = app.client, app.auth("ann")
    data = make_submission(app.settings.data_root / "val", noise=0.2, seed=5)
    r = c.post("/api/submissions", headers=auth, files={"file": ("s.zip", data)}, data={"split": "val"})
    assert r.status_code == 202, r.text
    assert worker.run(app.settings, worker_id="inline", max_jobs=1) == 1
    plots = c.get(f"/api/submissions/{r.json()['id']}", headers=auth).json()["plots"]
    assert len(plots) >= 2
    start = threading.Barrier(4)
    answers: list[tuple[int, str | None]] = []

    def view(url: str) -> None:
        start.wait()
        got = c.get(url, headers=auth)
        answers.append((got.status_code, got.headers.get("retry-after")))

    threads = [threading.Thread(target=view, args=(plots[i % len(plots)],)) for i in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(120)
    codes = sorted(code for code, _ in answers)
    assert 200 in codes and 429 in codes and set(codes) <= {200, 429}, answers
    assert all(int(ra) >= 1 for code, ra in answers if code == 429)
    for url in plots:  # drawn once, stored: every view answers now
        got = c.get(url, headers=auth)
        if got.status_code == 429:  # a figure whose drawing was refused above is drawn on this view
            got = c.get(url, headers=auth)
        assert got.status_code == 200 and got.content.startswith(b"\x89PNG")
