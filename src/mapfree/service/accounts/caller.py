"""Request-scoped helpers: the database session, the signed-in user, and CSRF checks.

Writes need a user: either ``Authorization: Bearer <token>`` (API clients; no cookies, so no CSRF risk) or a
browser session cookie plus that session's CSRF token (form field ``csrf_token`` or header ``X-CSRF-Token``).
"""

from __future__ import annotations

from collections.abc import AsyncIterator
from dataclasses import dataclass
from typing import Annotated

from fastapi import HTTPException, Path, Request
from sqlalchemy.orm import Session

from ..database.models import User, WebSession
from ..state import sessions_of, settings_of, throttle_of
from . import tokens as auth

#: The largest row id the database holds (a 32-bit integer on PostgreSQL): a larger one in a path is a 422,
#: not a query that overflows (a 500 from 2^63 on SQLite, from 2^31 on PostgreSQL).
MAX_ROW_ID = 2**31 - 1
#: A row id in a path: a token's, a session's, an anchor photo's index.
RowId = Annotated[int, Path(ge=0, le=MAX_ROW_ID, description="an id as listed (0 to 2^31 - 1)")]

SESSION_COOKIE = "mapfree_session"
LOGIN_CSRF_COOKIE = "mapfree_login_csrf"


@dataclass
class Caller:
    """Who sent a request: an account (``user``; None: nobody signed in) and how it proved so."""

    user: User | None
    session: WebSession | None = None  # set when authenticated by cookie
    via_token: bool = False

    @property
    def csrf(self) -> str:
        """The CSRF token the caller's forms must carry (empty for token callers and anonymous ones)."""
        return self.session.csrf if self.session else ""


@dataclass
class SignedIn(Caller):
    """A caller with an account: what ``require_user`` and ``require_writer`` return."""

    user: User


#: Methods whose requests only read: their sessions take no write transaction (``session_factory``).
READ_METHODS = ("GET", "HEAD")


async def db_session(request: Request) -> AsyncIterator[Session]:
    """The request's database session (a FastAPI dependency: closed when the response is sent); read-only for
    GET and HEAD, so that on SQLite a write transaction is begun only where a write follows. Async, so that its
    closing (the rollback that ends a transaction still open) needs no thread of the shared pool."""
    with sessions_of(request, read_only=request.method in READ_METHODS)() as db:
        yield db


#: The 401 of a write without credentials.
SIGN_IN = "authentication required: send 'Authorization: Bearer <token>' or sign in"


def token_user(request: Request, db: Session, header: str) -> User:
    """The account of an ``Authorization`` header's bearer token; a 401 naming why not (unknown, revoked,
    expired), or a 429 past the failures allowed from the caller's address."""
    scheme, _, token = header.partition(" ")
    user, why = (
        auth.check_token(db, token.strip()) if scheme.lower() == "bearer" else (None, "invalid or revoked API token")
    )
    if user is None:
        throttle_of(request).refuse(request)
        raise HTTPException(401, why, headers={"WWW-Authenticate": "Bearer"})
    return user


def check_credentials(request: Request) -> int:
    """The account id of a request's credentials, from its headers alone (``guard.CredentialGate``): a bearer
    token, else the browser session cookie; 401 (or 429) when there are none or they are bad. Reads only."""
    with sessions_of(request, read_only=True)() as db:
        header = request.headers.get("authorization")
        if header is not None:
            return token_user(request, db, header).id
        sess = auth.session_for(db, request.cookies.get(SESSION_COOKIE))
        if sess is None:
            raise HTTPException(401, SIGN_IN, headers={"WWW-Authenticate": "Bearer"})
        return sess.user_id


def identify(request: Request, db: Session) -> Caller:
    """Who is calling (possibly nobody). A malformed or unknown bearer token is a 401, not anonymous."""
    header = request.headers.get("authorization")
    if header is not None:
        account = getattr(request.state, "account", None)  # this header, checked by CredentialGate already
        user = db.get(User, account) if account is not None else None
        user = user if user is not None else token_user(request, db, header)
        request.state.user_id = user.id
        db.commit()  # end the read transaction (on SQLite it holds the write lock)
        return Caller(user, None, True)
    sess = auth.session_for(db, request.cookies.get(SESSION_COOKIE))
    user = db.get(User, sess.user_id) if sess is not None else None
    db.commit()
    if user is not None:
        request.state.user_id = user.id
        return Caller(user, sess)
    return Caller(None)


def signed_in(request: Request, db: Session) -> User:
    """The account of a web page's caller; a 401 pointing to the sign-in page otherwise."""
    user = identify(request, db).user
    if user is None:
        raise HTTPException(401, "sign in first (/login)")
    return user


def require_user(request: Request, db: Session) -> SignedIn:
    """A signed-in caller (token or session), for reading what needs an account; a 401 otherwise."""
    caller = identify(request, db)
    if caller.user is None:
        raise HTTPException(401, "authentication required", headers={"WWW-Authenticate": "Bearer"})
    return SignedIn(caller.user, caller.session, caller.via_token)


def require_writer(request: Request, db: Session, form_csrf: str | None = None) -> SignedIn:
    """A signed-in caller allowed to write: token callers, or cookie callers with the right CSRF token."""
    caller = identify(request, db)
    if caller.user is None:
        raise HTTPException(401, SIGN_IN, headers={"WWW-Authenticate": "Bearer"})
    if not caller.via_token:
        given = form_csrf or request.headers.get("x-csrf-token")
        if not auth.same_secret(given, caller.csrf):
            raise HTTPException(403, "CSRF check failed: reload the page and submit the form again")
    return SignedIn(caller.user, caller.session, caller.via_token)


def require_operator(request: Request) -> None:
    """Monitoring endpoints: the operator token (``Settings.operator_token``) or an admin's token or session."""
    expected = settings_of(request).operator_token
    scheme, _, given = request.headers.get("authorization", "").partition(" ")
    if expected and scheme.lower() == "bearer" and auth.same_secret(given.strip(), expected):
        return
    with sessions_of(request)() as db:
        caller = identify(request, db)
    if caller.user is None:
        raise HTTPException(
            401, "authentication required: the operator token or an admin's", headers={"WWW-Authenticate": "Bearer"}
        )
    if not caller.user.is_admin:
        raise HTTPException(403, "only admins and the operator token may read this")
