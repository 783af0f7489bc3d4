"""Server-rendered HTML: the Jinja2 templates (``service/templates``) with their filters, a page with the
navigation of whoever is calling (so it lives with the accounts), and the error page. Every resource's web pages
(its ``pages`` module) and the error responses (``http.errors``) render through here."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

from fastapi import Request
from fastapi.responses import HTMLResponse
from fastapi.templating import Jinja2Templates
from sqlalchemy.orm import Session

from ..state import sessions_of, settings_of
from .caller import identify

templates = Jinja2Templates(directory=str(Path(__file__).parents[1] / "templates"))


def _fmt_time(t: float | None, fmt: str = "%Y-%m-%d %H:%M:%S UTC") -> str:
    return time.strftime(fmt, time.gmtime(t)) if t else ""


def _fmt_num(v: object) -> str:
    if v is None:
        return "–"
    return f"{v:.3f}" if isinstance(v, float) else str(v)


def _fmt_diff(v: float | None) -> str:
    return "–" if v is None else f"{v:+.3f}"


templates.env.filters["time"] = _fmt_time
templates.env.filters["num"] = _fmt_num
templates.env.filters["diff"] = _fmt_diff


def page(request: Request, name: str, db: Session, status: int = 200, **ctx: Any) -> HTMLResponse:
    """Template ``name`` rendered with ``ctx`` and the caller's navigation (account, CSRF token, splits)."""
    caller = identify(request, db)
    return templates.TemplateResponse(
        request,
        name,
        {"user": caller.user, "csrf": caller.csrf, "splits": settings_of(request).splits, **ctx},
        status_code=status,
    )


def error_page(request: Request, status: int, message: str, headers: dict | None = None) -> HTMLResponse:
    """The HTML error page, with the navigation of whoever is signed in (never "sign in" to a signed-in user)."""
    user, csrf = None, ""
    try:
        with sessions_of(request)() as db:
            caller = identify(request, db)
            user, csrf = caller.user, caller.csrf
    except Exception:  # a bad token, or the database is down: an anonymous header is still a useful page
        pass
    return templates.TemplateResponse(
        request,
        "error.html",
        {"status": status, "message": message, "user": user, "csrf": csrf, "splits": settings_of(request).splits},
        status_code=status,
        headers=headers,
    )
