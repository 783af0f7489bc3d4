"""The app's exception handlers: every request error is a 4xx JSON (API) or HTML page (browser) naming the
problem; a database that is down is a 503 with ``Retry-After``; anything else is logged and answered with a
generic 500."""

from __future__ import annotations

import logging

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import Response
from starlette.concurrency import run_in_threadpool
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.routing import BaseRoute, Match, Route
from starlette.types import Scope

from .database.models import unavailable
from .http.errors import database_down, error_response, wants_html
from .inputs import UploadError
from .leaderboard.own import Withdrawn

log = logging.getLogger("mapfree.http")


def validation_message(exc: RequestValidationError) -> str:
    """FastAPI's validation errors as one line: ``field: problem; field: problem``."""
    parts = []
    for e in exc.errors():
        loc = ".".join(str(x) for x in e.get("loc", ()) if x not in ("body", "query", "path"))
        parts.append(f"{loc or 'request'}: {e.get('msg', 'invalid')}")
    return "; ".join(parts) or "invalid request"


def allowed_methods(routes: list[BaseRoute], scope: Scope) -> list[str]:
    """The methods of every route of ``routes`` whose path matches ``scope``'s (Starlette's 405 names only the
    first route's: ``GET`` where ``DELETE`` is allowed too)."""
    methods: set[str] = set()
    for route in routes:
        if isinstance(route, Route) and route.methods and route.matches(scope)[0] != Match.NONE:
            methods |= route.methods
    if "GET" in methods:  # HEAD is answered as GET (``HeadAsGet``)
        methods.add("HEAD")
    return sorted(methods)


async def _upload_error(request: Request, exc: Exception) -> Response:
    assert isinstance(exc, UploadError)
    return error_response(request, exc.status, exc.message)


async def _withdrawn(request: Request, exc: Exception) -> Response:
    assert isinstance(exc, Withdrawn)
    if wants_html(request):
        from .leaderboard.pages import withdrawn_page

        return await run_in_threadpool(withdrawn_page, request, exc)
    return error_response(request, exc.status_code, str(exc.detail))


async def _validation(request: Request, exc: Exception) -> Response:
    assert isinstance(exc, RequestValidationError)
    return error_response(request, 422, validation_message(exc))


async def _crash(request: Request, exc: Exception) -> Response:  # only reached when the access log did not answer
    if unavailable(exc):
        return database_down(request, exc)
    log.error("unhandled error", exc_info=exc, extra={"path": request.url.path})
    return error_response(request, 500, "internal server error")


def install_error_handlers(app: FastAPI, max_request_bytes: int, routes: list[BaseRoute]) -> None:
    """Answer every error of ``app``'s requests as its client reads them (``http.errors.error_response``).

    Args:
        app: The app.
        max_request_bytes: The body limit, named in the 413 of a body over it.
        routes: Every route of the app, its routers' included, named in the ``Allow`` of a 405.
    """

    async def http_error(request: Request, exc: Exception) -> Response:
        assert isinstance(exc, StarletteHTTPException)
        msg = exc.detail if isinstance(exc.detail, str) else str(exc.detail)
        headers = getattr(exc, "headers", None)
        if exc.status_code == 413 and "too large" in msg.lower():
            msg = f"request body larger than {max_request_bytes} bytes"
        if exc.status_code == 405:  # every method of the path, not only the first route's
            allowed = allowed_methods(routes, request.scope)
            headers = {**(headers or {}), "Allow": ", ".join(allowed)}
            msg = f"method {request.method} not allowed here; allowed: {', '.join(allowed)}"
        return error_response(request, exc.status_code, msg, headers)

    app.add_exception_handler(UploadError, _upload_error)
    app.add_exception_handler(Withdrawn, _withdrawn)
    app.add_exception_handler(StarletteHTTPException, http_error)
    app.add_exception_handler(RequestValidationError, _validation)
    app.add_exception_handler(Exception, _crash)
