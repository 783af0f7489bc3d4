"""Accounts, tokens and sessions: revoking a token ends what was made with it, a token never outlives its maker, token
guessing is limited per client, names are ASCII and unique ignoring case, and an account's tokens are bounded."""

from __future__ import annotations

import subprocess
import sys
import time

import httpx

from .conftest import create_users, make_submission, mapfree


def test_revoke_tokens_ends_browser_sessions(server):
    token = create_users(server.db_url, {"dave": None})["dave"]
    with server.client(follow_redirects=False) as c:
        login = c.get("/login")
        csrf = login.text.split('name="csrf_token" value="')[1].split('"')[0]
        assert c.post("/login", data={"token": token, "csrf_token": csrf}).status_code == 303
        assert c.get("/api/me").status_code == 200
        page = c.get("/submit").text
        session_csrf = page.split('name="csrf_token" value="')[1].split('"')[0]
        mapfree("admin", "--db", server.db_url, "revoke-tokens", "dave")
        assert c.get("/api/me").status_code == 401
        r = c.post(
            "/api/submissions",
            files={"file": ("s.zip", make_submission(server.data.root / "val"))},
            data={"split": "val", "name": "after-revoke", "csrf_token": session_csrf},
        )
        assert r.status_code == 401, r.text


def test_token_guessing_is_limited_per_client(make_app):
    app = make_app(auth_failures_per_minute=5)
    c = app.client
    for i in range(5):
        assert c.get("/api/me", headers={"Authorization": f"Bearer mf_guess{i}"}).status_code == 401
    r = c.get("/api/me", headers={"Authorization": "Bearer mf_guess5"})
    assert r.status_code == 429 and int(r.headers["retry-after"]) > 0, r.text
    assert c.get("/api/me", headers=app.auth("ann")).status_code == 200  # a valid token is never locked out
    assert c.get("/health").status_code == 200  # anonymous reads go on


def test_tokens_and_sessions_never_outlive_the_token_they_were_made_with(server):
    """A 3-second token minted a 365-day token that kept working, and a session signed in with a token outlived
    its revocation by 12 h. Now a token made with another expires with it at the latest, and revoking a token
    ends the tokens and sessions made with it (and says which)."""
    from mapfree.service.accounts import tokens as auth
    from mapfree.service.database.models import User, make_engine, session_factory

    create_users(server.db_url, {"erin": None})
    engine = make_engine(server.db_url)
    with session_factory(engine).begin() as db:
        short = auth.issue_token(db, db.query(User).filter_by(name="erin").one(), expires_in=3)
    engine.dispose()
    t0 = time.time()
    with server.client(headers={"Authorization": f"Bearer {short}"}) as c:
        r = c.post("/api/tokens", data={"expires_in_days": "365", "label": "long"})
        assert r.status_code == 201, r.text
        child = r.json()
        assert child["expires_at"] <= t0 + 4
    with server.client(headers={"Authorization": f"Bearer {child['token']}"}) as c:
        assert c.get("/api/me").status_code == 200
        time.sleep(max(0.0, t0 + 4 - time.time()))
        assert c.get("/api/me").status_code == 401

    token = create_users(server.db_url, {"fay": None})["fay"]
    with (
        server.client(follow_redirects=False) as web,
        server.client(headers={"Authorization": f"Bearer {token}"}) as api,
    ):
        csrf = web.get("/login").text.split('name="csrf_token" value="')[1].split('"')[0]
        assert web.post("/login", data={"token": token, "csrf_token": csrf}).status_code == 303
        page = web.get("/submit").text
        session_csrf = page.split('name="csrf_token" value="')[1].split('"')[0]
        made = web.post("/api/tokens", data={"expires_in_days": "365", "csrf_token": session_csrf}).json()
        assert web.get("/api/me").status_code == 200
        tid = next(t["id"] for t in api.get("/api/tokens").json() if t["current"])
        r = api.delete(f"/api/tokens/{tid}")
        assert r.status_code == 200 and r.json()["ended"]["tokens"] == [made["id"]], r.text
        assert len(r.json()["ended"]["sessions"]) == 1
        assert web.get("/api/me").status_code == 401
        assert (
            httpx.get(server.url + "/api/me", headers={"Authorization": f"Bearer {made['token']}"}).status_code == 401
        )
    with server.client(headers={"Authorization": f"Bearer {server.tokens['alice']}"}) as c:  # the admin's word
        parent = c.post("/api/tokens", data={"expires_in_days": "1"}).json()
        with server.client(headers={"Authorization": f"Bearer {parent['token']}"}) as p:
            grandchild = p.post("/api/tokens", data={"expires_in_days": "1"}).json()
    out = subprocess.run(
        [sys.executable, "-m", "mapfree.cli.admin", "--db", server.db_url, "revoke-token", str(parent["id"])],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert out.returncode == 0 and f"and ended 1 tokens made with it ({grandchild['id']})" in out.stderr, out.stderr


def test_look_alike_names_and_endless_tokens_are_refused(make_app, tmp_path):
    """'аlice' (Cyrillic а) beside 'alice' were two accounts the boards showed alike, so were the ASCII 'aIice',
    'b0b' and 'alice.' beside 'alice' and 'bob'; and one account minted 2,000 tokens in 20 s. Now names are ASCII
    and unique ignoring case and look-alike spellings (``skeleton``), and an account holds at most
    ``MAX_TOKENS`` active tokens (a revoked one frees its place)."""
    from mapfree.service.accounts import tokens as auth

    db = ["--db", f"sqlite:///{tmp_path / 'names.db'}"]
    mapfree("admin", *db, "create-user", "alice")
    mapfree("admin", *db, "create-user", "bob")
    for name, why in (
        ("\u0430lice", "ASCII"),
        ("Alice", "only in case"),
        (".x", "ASCII"),
        ("aIice", "looks like the existing 'alice'"),
        ("b0b", "looks like the existing 'bob'"),
        ("alice.", "looks like the existing 'alice'"),
        ("a-l1ce", "looks like the existing 'alice'"),
    ):
        out = subprocess.run(
            [sys.executable, "-m", "mapfree.cli.admin", *db, "create-user", name],
            capture_output=True,
            text=True,
            timeout=120,
        )
        assert out.returncode == 1 and why in out.stderr and "Traceback" not in out.stderr, (name, out.stderr)
    app = make_app()
    with app.client as c:
        h = app.auth("ann")
        made = [c.post("/api/tokens", data={"expires_in_days": "1"}, headers=h) for _ in range(auth.MAX_TOKENS - 1)]
        assert {r.status_code for r in made} == {201}  # ann's first token and these: the limit
        r = c.post("/api/tokens", data={"expires_in_days": "1"}, headers=h)
        assert r.status_code == 409 and "revoke some" in r.json()["detail"], r.text
        assert c.delete(f"/api/tokens/{made[0].json()['id']}", headers=h).status_code == 200
        assert c.post("/api/tokens", data={"expires_in_days": "1"}, headers=h).status_code == 201


def _sign_in(c, token: str) -> str:
    """Sign in on the form (as a new browser) -> the session cookie's value."""
    c.cookies.clear()
    login = c.get("/login")
    csrf = login.text.split('name="csrf_token" value="')[1].split('"')[0]
    r = c.post("/login", data={"token": token, "csrf_token": csrf}, follow_redirects=False)
    assert r.status_code == 303, r.text
    return r.cookies["mapfree_session"]


def test_browser_sessions_per_account_are_capped_and_old_ones_end(make_app):
    """400 sign-ins used to keep 416 sessions: now an account keeps ``MAX_SESSIONS``, the oldest end first."""
    from sqlalchemy import func, select

    from mapfree.service.accounts.tokens import MAX_SESSIONS
    from mapfree.service.database.models import User, WebSession, make_engine, session_factory

    app = make_app()
    c = app.client
    sids = [_sign_in(c, app.tokens["ann"]) for _ in range(MAX_SESSIONS + 5)]
    c.cookies.clear()
    engine = make_engine(app.settings.db_url)
    with session_factory(engine)() as db:
        ann = db.scalar(select(User.id).where(User.name == "ann"))
        assert db.scalar(select(func.count()).select_from(WebSession).where(WebSession.user_id == ann)) == MAX_SESSIONS
    engine.dispose()
    c.cookies.set("mapfree_session", sids[0])
    assert c.get("/api/me").status_code == 401  # the oldest ended
    c.cookies.set("mapfree_session", sids[-1])
    assert c.get("/api/me").status_code == 200


def test_sessions_from_before_token_lineage_end_with_the_upgrade(make_app):
    """A session stored before sessions recorded their token (schema 0004, ``token_id`` empty) could not be
    reached by token revocation and could mint a year-long token; now it is no session at all."""
    from sqlalchemy import select

    from mapfree.service.accounts.tokens import hash_secret
    from mapfree.service.database.models import User, WebSession, make_engine, now, session_factory

    app = make_app()
    engine = make_engine(app.settings.db_url)
    with session_factory(engine).begin() as db:
        ann = db.scalar(select(User.id).where(User.name == "ann"))
        db.add(WebSession(sid_hash=hash_secret("old-session"), user_id=ann, csrf="old-csrf", expires_at=now() + 3600))
    engine.dispose()
    c = app.client
    c.cookies.set("mapfree_session", "old-session")
    assert c.get("/api/me").status_code == 401
    r = c.post("/api/tokens", data={"expires_in_days": "365", "csrf_token": "old-csrf"})
    assert r.status_code == 401, r.text
