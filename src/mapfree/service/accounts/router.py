"""A user's own API tokens and browser sessions: list them, create a token with an expiry, revoke one at a time
(``mapfree admin`` does the same for any account). Only hashes are stored: a listing shows each token's prefix
and label, never the token."""

from __future__ import annotations

from fastapi import APIRouter, Depends, Form, HTTPException, Request
from fastapi.responses import RedirectResponse
from sqlalchemy import select
from sqlalchemy.orm import Session

from ..database.models import Anchor, ApiToken, Submission, WebSession, now
from ..inputs import check_name
from ..schemas import MeOut, NewTokenOut, RevokedTokenOut, SessionEndedOut, SessionOut, TokenOut
from ..state import SettingsDep
from . import tokens as auth
from .caller import SESSION_COOKIE, Caller, RowId, db_session, require_user, require_writer
from .quota import stored_bytes, test_quota

router = APIRouter()
#: The longest lifetime a user may give a token they create themselves (an admin's CLI may give any).
MAX_SELF_SERVICE_DAYS = 365.0


def token_json(t: ApiToken, current_hash: str = "") -> dict:
    expired = t.expires_at is not None and t.expires_at <= now()
    return {
        "id": t.id,
        "prefix": t.prefix,
        "label": t.label,
        "created_at": t.created_at,
        "expires_at": t.expires_at,
        "revoked": t.revoked,
        "expired": expired,
        "current": t.token_hash == current_hash,
    }


def session_json(s: WebSession, current_hash: str = "") -> dict:
    return {"id": s.id, "created_at": s.created_at, "expires_at": s.expires_at, "current": s.sid_hash == current_hash}


def list_tokens(db: Session, user_id: int) -> list[ApiToken]:
    return list(db.scalars(select(ApiToken).where(ApiToken.user_id == user_id).order_by(ApiToken.id)))


def list_sessions(db: Session, user_id: int) -> list[WebSession]:
    return list(
        db.scalars(
            select(WebSession)
            .where(WebSession.user_id == user_id, WebSession.expires_at > now())
            .order_by(WebSession.id)
        )
    )


def current_token_hash(request: Request) -> str:
    """The hash of the request's bearer token ("" without one): how a listing marks the token in use."""
    scheme, _, token = request.headers.get("authorization", "").partition(" ")
    return auth.hash_secret(token.strip()) if scheme.lower() == "bearer" and token.strip() else ""


def current_token(request: Request, db: Session, caller: Caller) -> ApiToken | None:
    """The token a request is made with: its bearer token, or the one its browser session was signed in with."""
    if caller.via_token:
        return db.scalar(select(ApiToken).where(ApiToken.token_hash == current_token_hash(request)))
    return db.get(ApiToken, caller.session.token_id) if caller.session and caller.session.token_id else None


def _own_row(request: Request, db: Session, model, row_id: int, what: str, csrf: str | None = None):
    """Row ``row_id`` of ``model`` if it belongs to the signed-in writer; a 404 otherwise (another's included)."""
    caller = require_writer(request, db, csrf or request.headers.get("x-csrf-token"))
    row = db.get(model, row_id)
    if row is None or row.user_id != caller.user.id:
        raise HTTPException(404, f"no such {what} of yours")
    return row


@router.get("/api/tokens", tags=["accounts"], response_model=list[TokenOut])
def my_tokens(request: Request, db: Session = Depends(db_session)):
    """Your API tokens (prefix, label, creation, expiry, revoked); ``current``: the one this request used."""
    caller = require_user(request, db)
    return [token_json(t, current_token_hash(request)) for t in list_tokens(db, caller.user.id)]


@router.post("/api/tokens", status_code=201, tags=["accounts"], response_model=NewTokenOut)
def create_token(
    request: Request,
    expires_in_days: float = Form(..., description="lifetime in days (max 365)"),
    label: str = Form("", description="what the token is for"),
    csrf_token: str | None = Form(None),
    db: Session = Depends(db_session),
):
    """A new API token of yours that expires (shown once, in ``token``). It never outlives the token this request
    is made with (or that its browser session was signed in with), and revoking that one revokes it."""
    caller = require_writer(request, db, csrf_token)
    if not 0 < expires_in_days <= MAX_SELF_SERVICE_DAYS:
        raise HTTPException(422, f"expires_in_days must lie in (0, {MAX_SELF_SERVICE_DAYS:g}]")

    try:
        token = auth.issue_token(
            db,
            caller.user,
            expires_in_days * 86400,
            check_name(label, 64, "label"),
            parent=current_token(request, db, caller),
        )
    except auth.TokenLimit as e:
        raise HTTPException(409, str(e)) from None
    db.commit()
    row = db.execute(select(ApiToken).where(ApiToken.token_hash == auth.hash_secret(token))).scalar_one()
    return {"token": token, **token_json(row)}


@router.delete("/api/tokens/{tid}", tags=["accounts"], response_model=RevokedTokenOut)
def revoke_token(tid: RowId, request: Request, db: Session = Depends(db_session)):
    """Revoke one of your tokens (the one this request uses too: it stops working at once), with everything
    made with it: ``ended`` lists the ids of the tokens created with it and of the browser sessions signed in
    with any of those."""
    row = _own_row(request, db, ApiToken, tid, "token")
    ended = auth.revoke_token(db, row)
    db.commit()
    return {**token_json(row), "ended": ended}


@router.get("/api/sessions", tags=["accounts"], response_model=list[SessionOut])
def my_sessions(request: Request, db: Session = Depends(db_session)):
    """Your open browser sessions; ``current``: the one this request came with."""
    caller = require_user(request, db)
    sid = request.cookies.get(SESSION_COOKIE)
    current = auth.hash_secret(sid) if sid else ""
    return [session_json(s, current) for s in list_sessions(db, caller.user.id)]


@router.delete("/api/sessions/{session_id}", tags=["accounts"], response_model=SessionEndedOut)
def end_session(session_id: RowId, request: Request, db: Session = Depends(db_session)):
    """Sign one of your browser sessions out (e.g. a lost phone's)."""
    db.delete(_own_row(request, db, WebSession, session_id, "session"))
    db.commit()
    return {"id": session_id, "ended": True}


# ------------------------------------------------------------- the forms of the access page (``pages.access_page``)


@router.post("/me/tokens/{tid}/revoke", include_in_schema=False)
def revoke_token_form(tid: RowId, request: Request, csrf_token: str = Form(""), db: Session = Depends(db_session)):
    auth.revoke_token(db, _own_row(request, db, ApiToken, tid, "token", csrf_token))
    db.commit()
    return RedirectResponse("/me/access", status_code=303)


@router.post("/me/sessions/{session_id}/end", include_in_schema=False)
def end_session_form(
    session_id: RowId, request: Request, csrf_token: str = Form(""), db: Session = Depends(db_session)
):
    db.delete(_own_row(request, db, WebSession, session_id, "session", csrf_token))
    db.commit()
    return RedirectResponse("/me/access", status_code=303)


def delete_user(db: Session, user, dry_run: bool = False) -> dict[str, int]:
    """Delete an account with everything it owns: tokens, sessions, anchors with their photos, submissions with
    their ZIPs, results and plots (their leaderboard entries go with them). The database's cascades do the
    deleting; returns what was there, by kind (``dry_run``: only that)."""
    from sqlalchemy import func

    counts = {
        "tokens": db.scalar(select(func.count()).select_from(ApiToken).where(ApiToken.user_id == user.id)),
        "sessions": db.scalar(select(func.count()).select_from(WebSession).where(WebSession.user_id == user.id)),
        "anchors": db.scalar(select(func.count()).select_from(Anchor).where(Anchor.user_id == user.id)),
        "submissions": db.scalar(select(func.count()).select_from(Submission).where(Submission.user_id == user.id)),
    }
    if not dry_run:
        db.delete(user)
        db.flush()
    return {k: int(v or 0) for k, v in counts.items()}


@router.get("/api/me", tags=["accounts"], response_model=MeOut)
def me(request: Request, settings: SettingsDep, db: Session = Depends(db_session)):
    caller = require_user(request, db)
    u = caller.user
    quota = test_quota(db, settings, u)
    return {
        "name": u.name,
        "admin": u.is_admin,
        "test_evaluations_left_today": quota.left,
        "test_daily_limit": quota.shown_limit,
        "storage_used_bytes": stored_bytes(db, u.id),
        "storage_quota_bytes": settings.storage_quota_bytes,
    }
