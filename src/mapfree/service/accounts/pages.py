"""The accounts' web pages: the home page, signing in and out (the sign-in form is a double-submit CSRF form:
no session exists yet; the session cookie is HttpOnly and SameSite=Lax), and the page of your tokens and
browser sessions."""

from __future__ import annotations

import secrets

from fastapi import APIRouter, Depends, Form, HTTPException, Request
from fastapi.responses import HTMLResponse, RedirectResponse
from sqlalchemy.orm import Session

from ..config import Settings
from ..state import SettingsDep, ThrottleDep
from . import tokens as auth
from .caller import LOGIN_CSRF_COOKIE, SESSION_COOKIE, db_session, require_user, require_writer
from .render import page
from .router import current_token_hash, list_sessions, list_tokens, session_json, token_json

router = APIRouter(include_in_schema=False)


@router.get("/", response_class=HTMLResponse)
def home(request: Request, db: Session = Depends(db_session)):
    return page(request, "index.html", db)


@router.get("/login", response_class=HTMLResponse)
def login_form(request: Request, settings: SettingsDep, db: Session = Depends(db_session)):
    return _login_page(request, db, settings)


def _login_page(request: Request, db: Session, settings: Settings, status: int = 200, error: str = "") -> HTMLResponse:
    token = secrets.token_urlsafe(24)  # double-submit: no session exists yet
    resp = page(request, "login.html", db, status, login_csrf=token, error=error)
    resp.set_cookie(
        LOGIN_CSRF_COOKIE,
        token,
        httponly=True,
        samesite="strict",
        secure=settings.secure_cookies,
        max_age=3600,
    )
    return resp


@router.post("/login")
def login(
    request: Request,
    settings: SettingsDep,
    throttle: ThrottleDep,
    token: str = Form(...),
    csrf_token: str = Form(""),
    db: Session = Depends(db_session),
):
    if not auth.same_secret(csrf_token, request.cookies.get(LOGIN_CSRF_COOKIE)):
        raise HTTPException(403, "CSRF check failed: reload the sign-in page and try again")
    row, _ = auth.find_token(db, token.strip())
    if row is None:  # the sign-in form again, with the error above it
        try:
            throttle.refuse(request)
        except HTTPException as e:
            resp = _login_page(request, db, settings, e.status_code, str(e.detail))
            resp.headers.update(e.headers or {})
            return resp
        return _login_page(request, db, settings, 401, "invalid or revoked API token")
    sid, _ = auth.open_session(db, row, settings.session_hours)  # ends with the token, at the latest
    db.commit()
    signed_in = RedirectResponse("/me", status_code=303)
    signed_in.set_cookie(
        SESSION_COOKIE,
        sid,
        httponly=True,
        samesite="lax",
        secure=settings.secure_cookies,
        max_age=int(settings.session_hours * 3600),
    )
    signed_in.delete_cookie(LOGIN_CSRF_COOKIE)
    return signed_in


@router.post("/logout")
def logout(request: Request, csrf_token: str = Form(""), db: Session = Depends(db_session)):
    require_writer(request, db, csrf_token)
    auth.close_session(db, request.cookies.get(SESSION_COOKIE))
    db.commit()
    resp = RedirectResponse("/", status_code=303)
    resp.delete_cookie(SESSION_COOKIE)
    return resp


@router.get("/me/access", response_class=HTMLResponse)
def access_page(request: Request, db: Session = Depends(db_session)):
    """Your tokens and browser sessions, each with a button that revokes it."""
    caller = require_user(request, db)
    sid = request.cookies.get(SESSION_COOKIE)
    current = auth.hash_secret(sid) if sid else ""
    return page(
        request,
        "access.html",
        db,
        tokens=[token_json(t, current_token_hash(request)) for t in list_tokens(db, caller.user.id)],
        sessions=[session_json(s, current) for s in list_sessions(db, caller.user.id)],
    )
