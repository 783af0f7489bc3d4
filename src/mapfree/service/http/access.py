"""The access log: every request gets an id (``X-Request-ID``), the security headers, one JSON log line and its
latency in the metrics, unexpected 500s included; failed token checks are counted per client address."""

from __future__ import annotations

import logging
import time
from collections.abc import Callable

from fastapi import Request
from fastapi.responses import Response
from starlette.middleware.base import BaseHTTPMiddleware, RequestResponseEndpoint
from starlette.types import ASGIApp

from ..database.models import unavailable
from .errors import database_down, error_response
from .guard import AuthThrottle, client_address, request_id

log = logging.getLogger("mapfree.http")
CSP = "default-src 'self'; img-src 'self' data:; style-src 'self'; script-src 'self'; frame-ancestors 'none'"

#: Records one answered request: (method, route path, status, seconds) (``operations.metrics.Metrics.observe``).
Observe = Callable[[str, str, int, float], None]


class AccessLog(BaseHTTPMiddleware):
    """HTTP middleware: the request id, the access-log line and the metrics of every request; an exception no
    handler answered becomes a 503 (database unavailable) or a 500 naming the request id. Failed token checks
    (401s of requests that carried credentials) are counted per client address (``guard.AuthThrottle``)."""

    def __init__(self, app: ASGIApp, throttle: AuthThrottle, observe: Observe):
        super().__init__(app)
        self.throttle, self.observe = throttle, observe

    async def dispatch(self, request: Request, call_next: RequestResponseEndpoint) -> Response:
        t0 = time.perf_counter()
        rid = request.state.request_id = request_id(request)
        try:
            response = await call_next(request)
        except Exception as exc:
            response = self._crashed(request, exc, rid)
        client = client_address(request)
        if response.status_code == 401 and self.throttle.credentialed(request):
            self.throttle.failed(client)
        route = request.scope.get("route")
        seconds = time.perf_counter() - t0
        method = "HEAD" if getattr(request.state, "head", False) else request.method
        self.observe(method, getattr(route, "path", "unmatched"), response.status_code, seconds)
        _secure_headers(request, response, rid)
        log.info(
            "request",
            extra={
                "method": method,
                "route": getattr(route, "path", "?"),
                "status": response.status_code,
                "ms": round(seconds * 1000, 2),
                "request_id": rid,
                "client": client,
                "user_id": getattr(request.state, "user_id", None),
            },
        )
        return response

    @staticmethod
    def _crashed(request: Request, exc: Exception, rid: str) -> Response:
        if unavailable(exc):
            return database_down(request, exc)
        log.error(
            "unhandled error",
            exc_info=exc,
            extra={"request_id": rid, "method": request.method, "path": request.url.path},
        )
        return error_response(request, 500, f"internal server error (request id {rid})")


def _secure_headers(request: Request, response: Response, rid: str) -> None:
    response.headers["X-Request-ID"] = rid
    response.headers.setdefault("X-Content-Type-Options", "nosniff")
    response.headers.setdefault("Referrer-Policy", "same-origin")
    if not request.url.path.startswith(("/docs", "/redoc")):
        response.headers.setdefault("Content-Security-Policy", CSP)
