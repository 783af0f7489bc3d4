"""A request's error as its client reads it: the HTML error page for a browser, JSON for everyone else. The
app's exception handlers and the credential gate (which answers before the app sees a request) both answer
through ``error_response``."""

from __future__ import annotations

import logging

from fastapi import Request
from fastapi.responses import JSONResponse, Response

from ..accounts.render import error_page
from ..database.models import RETRY_AFTER_S

log = logging.getLogger("mapfree.http")

#: Paths that always answer JSON, whatever the client accepts.
_API_PREFIXES = ("/api/", "/anchors", "/health", "/metrics", "/openapi.json")


def wants_html(request: Request) -> bool:
    """Whether the request comes from a browser page (it accepts HTML, and its path is not an API's)."""
    p = request.url.path
    return not p.startswith(_API_PREFIXES) and "text/html" in request.headers.get("accept", "")


def error_response(request: Request, status: int, message: str, headers: dict | None = None) -> Response:
    """A request's error: the HTML error page for a browser, else JSON ``{detail, status, request_id}``."""
    if wants_html(request):
        return error_page(request, status, message, headers)
    rid = getattr(request.state, "request_id", None)
    return JSONResponse({"detail": message, "status": status, "request_id": rid}, status_code=status, headers=headers)


def database_down(request: Request, exc: Exception) -> Response:
    """The 503 (with ``Retry-After``) of a request that found the database unavailable or busy; logged."""
    log.warning("database unavailable", extra={"path": request.url.path, "error": str(exc).splitlines()[0][:300]})
    return error_response(
        request,
        503,
        f"the database is unavailable or busy; try again in {RETRY_AFTER_S} s",
        {"Retry-After": str(RETRY_AFTER_S)},
    )
