"""Accounts, API tokens (only their SHA-256 is stored) and browser sessions with CSRF tokens.

Tokens are 256-bit random strings, so a plain SHA-256 is enough (no password stretching needed): a stolen
database does not reveal usable tokens, and lookups stay one indexed equality.
"""

from __future__ import annotations

import hashlib
import hmac
import math
import re
import secrets
import time

from sqlalchemy import delete, func, or_, select
from sqlalchemy.orm import Session

from ..database.models import ApiToken, User, WebSession, now

TOKEN_PREFIX = "mf_"
#: Account names: ASCII letters, digits, '-', '_', '.'; no look-alike of another name can be made from them
#: (Cyrillic 'а' beside Latin 'a' were two accounts the boards showed alike), and names differing only in
#: case are refused as the same name.
USER_NAME_RE = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,63}")
#: Active (not revoked, not expired) tokens one account may hold.
MAX_TOKENS = 100
#: Browser sessions one account keeps at once; a new sign-in past them ends the oldest.
MAX_SESSIONS = 20


class TokenLimit(ValueError):
    """The account holds ``MAX_TOKENS`` active tokens already."""


def hash_secret(secret: str) -> str:
    return hashlib.sha256(secret.encode("utf-8", "surrogatepass")).hexdigest()


def new_token() -> str:
    return TOKEN_PREFIX + secrets.token_urlsafe(32)


#: Look-alike ASCII spellings, folded to one (after lower-casing): ``aIice`` and ``alice``, ``b0b`` and ``bob``.
_CONFUSABLE = (("rn", "m"), ("vv", "w"), ("cl", "d"), ("0", "o"), ("1", "l"), ("i", "l"), ("|", "l"))


def skeleton(name: str) -> str:
    """A name's look-alike fold: lower case, without separators (``.``, ``-``, ``_``), and with the ASCII
    letters and digits that pass for one another in a sans-serif font made one (``_CONFUSABLE``). Two names with
    the same skeleton cannot both be accounts: ``alice.``, ``aIice`` and ``a-lice`` all fold to ``allce``."""
    folded = re.sub(r"[._-]", "", name.lower())
    for seen, one in _CONFUSABLE:
        folded = folded.replace(seen, one)
    return folded


def create_user(db: Session, name: str, admin: bool = False, expires_in: float | None = None) -> tuple[User, str]:
    """A new account and its first token (the only time the plain token is seen; ``expires_in`` as for
    ``issue_token``)."""
    name = name.strip()
    if not USER_NAME_RE.fullmatch(name):
        raise ValueError(
            "user name must be 1-64 ASCII letters, digits, '-', '_' or '.', starting with a letter or "
            "digit (so that no name can pass for another with look-alike letters)"
        )
    same = db.scalar(select(User.name).where(func.lower(User.name) == name.lower()))
    if same is not None:
        raise ValueError(
            f"user {name!r} already exists"
            if same == name
            else f"user name {name!r} differs from the existing {same!r} only in case"
        )
    key = skeleton(name)
    alike = next((n for n in db.scalars(select(User.name)) if skeleton(n) == key), None)
    if alike is not None:
        raise ValueError(
            f"user name {name!r} looks like the existing {alike!r} (names equal once case, separators and "
            "look-alike letters (0/o, 1/l/I, rn/m, vv/w) are set aside are one name); choose another"
        )
    user = User(name=name, is_admin=admin)
    db.add(user)
    db.flush()
    return user, issue_token(db, user, expires_in)


def _ends(lifetime: float | None, parent: ApiToken | None) -> float | None:
    """When a token or session that lives ``lifetime`` seconds (None: for ever) ends, never after ``parent``."""
    ends = now() + lifetime if lifetime is not None else None
    if parent is not None and parent.expires_at is not None:
        ends = parent.expires_at if ends is None else min(ends, parent.expires_at)
    return ends


def issue_token(
    db: Session, user: User, expires_in: float | None = None, label: str = "", parent: ApiToken | None = None
) -> str:
    """A new token of ``user`` (valid ``expires_in`` seconds; None: until revoked); the plain token is returned
    once and only its hash stored. ``parent``: the token it is created with; it never outlives that one, and
    revoking that one revokes it."""
    if expires_in is not None and not (math.isfinite(expires_in) and expires_in > 0):
        raise ValueError(f"a token's lifetime must be positive, got {expires_in} s")
    active = db.execute(
        select(func.count())
        .select_from(ApiToken)
        .where(
            ApiToken.user_id == user.id,
            ApiToken.revoked.is_(False),
            or_(ApiToken.expires_at.is_(None), ApiToken.expires_at > now()),
        )
    ).scalar_one()
    if active >= MAX_TOKENS:
        raise TokenLimit(
            f"account {user.name!r} holds {active} active tokens, the most it may; revoke some first "
            "(DELETE /api/tokens/{id}, the access page, or mapfree admin revoke-token)"
        )
    token = new_token()
    db.add(
        ApiToken(
            user_id=user.id,
            token_hash=hash_secret(token),
            prefix=token[:10],
            label=label[:64],
            expires_at=_ends(expires_in, parent),
            parent_id=parent.id if parent is not None else None,
        )
    )
    return token


def find_token(db: Session, token: str) -> tuple[ApiToken | None, str]:
    """(the token's row, "") or (None, why it is refused: unknown, revoked or expired, with when)."""
    if not token or len(token) > 200:
        return None, "invalid or revoked API token"
    row = db.scalar(select(ApiToken).where(ApiToken.token_hash == hash_secret(token), ApiToken.revoked.is_(False)))
    if row is None:
        return None, "invalid or revoked API token"
    if row.expires_at is not None and row.expires_at <= now():
        return None, (
            f"API token {row.prefix}… expired on {utc(row.expires_at)}; ask for a new one (mapfree "
            "admin new-token) or create one while signed in (POST /api/tokens)"
        )
    return row, ""


def check_token(db: Session, token: str) -> tuple[User | None, str]:
    """(the token's user, "") or (None, why it is refused: unknown, revoked or expired, with when)."""
    row, why = find_token(db, token)
    return (db.get(User, row.user_id) if row is not None else None), why


def revoke_token(db: Session, row: ApiToken) -> dict[str, list[int]]:
    """Revoke ``row`` and everything made with it: the tokens created with it (and with those, …) and the
    browser sessions signed in with any of them -> the ids of the other tokens and of the sessions ended."""
    revoked, frontier = [row.id], [row.id]
    while frontier:
        children = db.scalars(select(ApiToken).where(ApiToken.parent_id.in_(frontier))).all()
        frontier = [c.id for c in children if c.id not in revoked]
        revoked += frontier
    for t in db.scalars(select(ApiToken).where(ApiToken.id.in_(revoked), ApiToken.revoked.is_(False))):
        t.revoked = True
    sessions = list(db.scalars(select(WebSession.id).where(WebSession.token_id.in_(revoked))))
    db.execute(delete(WebSession).where(WebSession.id.in_(sessions)))
    return {"tokens": revoked[1:], "sessions": sessions}


def utc(t: float) -> str:
    return time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime(t))


_UNITS = {"s": 1, "m": 60, "h": 3600, "d": 86400, "w": 7 * 86400}


def parse_duration(text: str) -> float:
    """``"90d"``, ``"12h"``, ``"30m"``, ``"45s"``, ``"2w"`` or plain seconds -> seconds (positive)."""
    t = text.strip().lower()
    try:
        seconds = float(t[:-1]) * _UNITS[t[-1]] if t and t[-1] in _UNITS else float(t)
    except ValueError:
        raise ValueError(f"not a duration: {text!r} (e.g. 90d, 12h, 30m or seconds)") from None
    if not (math.isfinite(seconds) and seconds > 0):
        raise ValueError(f"a duration must be positive: {text!r}")
    return seconds


def revoke_tokens(db: Session, user: User) -> int:
    """Revoke every token of ``user`` and end every browser session of the account (each was opened with a token)."""
    rows = db.scalars(select(ApiToken).where(ApiToken.user_id == user.id, ApiToken.revoked.is_(False))).all()
    for r in rows:
        r.revoked = True
    db.execute(delete(WebSession).where(WebSession.user_id == user.id))
    return len(rows)


def open_session(db: Session, token: ApiToken, hours: float) -> tuple[str, str]:
    """A new browser session signed in with ``token`` -> (session id for the cookie, its CSRF token). It ends
    after ``hours``, when the token expires, or when the token is revoked, whichever comes first. The account
    keeps at most ``MAX_SESSIONS``: past them the oldest end (400 sign-ins used to keep 416 sessions)."""
    sid, csrf = secrets.token_urlsafe(32), secrets.token_urlsafe(24)
    db.add(
        WebSession(
            sid_hash=hash_secret(sid),
            user_id=token.user_id,
            csrf=csrf,
            expires_at=_ends(hours * 3600, token),
            token_id=token.id,
        )
    )
    db.flush()
    kept = select(WebSession.id).where(WebSession.user_id == token.user_id).order_by(WebSession.id.desc())
    db.execute(
        delete(WebSession).where(
            WebSession.user_id == token.user_id, WebSession.id.not_in(kept.limit(MAX_SESSIONS).scalar_subquery())
        )
    )
    return sid, csrf


def session_for(db: Session, sid: str | None) -> WebSession | None:
    """The live session of a cookie's id, or None: unknown, expired, or made before sessions recorded their
    token (schema 0004), which token revocation could not reach, so they end with the upgrade."""
    if not sid or len(sid) > 200:
        return None
    row = db.scalar(select(WebSession).where(WebSession.sid_hash == hash_secret(sid)))
    return row if row is not None and row.expires_at > now() and row.token_id is not None else None


def close_session(db: Session, sid: str | None) -> None:
    row = session_for(db, sid)
    if row is not None:
        db.delete(row)


def same_secret(a: str | None, b: str | None) -> bool:
    return bool(a) and bool(b) and hmac.compare_digest(str(a), str(b))
