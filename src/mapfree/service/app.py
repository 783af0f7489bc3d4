"""The FastAPI application: ``create_app(settings)``. Every request error is a 4xx JSON (API) or HTML page
(browser) naming the problem; unexpected errors are logged and answered with a generic 500."""

from __future__ import annotations

import json
import logging
import os
import time
from pathlib import Path

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.staticfiles import StaticFiles
from fastapi_offline import FastAPIOffline
from starlette.concurrency import run_in_threadpool
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.types import Scope

from .. import __version__
from .anchors.localizers import Localizers, register_methods_dir
from .config import Settings, parse_daily_limit
from .database.models import RETRY_AFTER_S, init_db, make_engine, session_factory, unavailable
from .http.errors import error_response, wants_html
from .http.gc_freeze import freeze_long_lived
from .http.guard import AuthThrottle, CredentialGate, client_address, request_id
from .http.head_as_get import HeadAsGet
from .http.heavy import HeavyPool, default_threads
from .http.timeouts import BodyTimeout, HeadSizeLimit
from .inputs import UploadError
from .leaderboard.own import Withdrawn
from .leaderboard.storage import drop_interrupted_uploads
from .operations.health import HealthMonitor
from .operations.metrics import Metrics
from .process import die_with_parent, parent_from_env
from .schemas import ERRORS, for_clients

log = logging.getLogger("mapfree.http")
CSP = "default-src 'self'; img-src 'self' data:; style-src 'self'; script-src 'self'; frame-ancestors 'none'"


def _validation_message(exc: RequestValidationError) -> str:
    parts = []
    for e in exc.errors():
        loc = ".".join(str(x) for x in e.get("loc", ()) if x not in ("body", "query", "path"))
        parts.append(f"{loc or 'request'}: {e.get('msg', 'invalid')}")
    return "; ".join(parts) or "invalid request"


def allowed_methods(routes: list, scope: Scope) -> list[str]:
    """The methods of every route of ``routes`` whose path matches ``scope``'s (Starlette's 405 names only the
    first route's: ``GET`` where ``DELETE`` is allowed too)."""
    from starlette.routing import Match, Route

    methods: set[str] = set()
    for route in routes:
        if isinstance(route, Route) and route.methods and route.matches(scope)[0] != Match.NONE:
            methods |= route.methods
    if "GET" in methods:  # HEAD is answered as GET (``HeadAsGet``)
        methods.add("HEAD")
    return sorted(methods)


def create_app(settings: Settings) -> FastAPI:
    """The app of ``mapfree.service.create_app`` (documented there): database, state, middlewares, routes."""
    engine = make_engine(settings.db_url)
    init_db(engine)
    with session_factory(engine).begin() as db:  # uploads cut off when a server was killed: refund them now
        if n := drop_interrupted_uploads(db):
            log.warning(
                "interrupted uploads removed; their quota and test evaluations refunded", extra={"submissions": n}
            )
    # /docs and /redoc with their assets served from /docs-assets (fastapi-offline): no CDN, so they work offline
    app = FastAPIOffline(
        title="mapfree service",
        version=__version__,
        static_url="/docs-assets",
        max_body_size=settings.limits.max_request_bytes,
        responses=ERRORS,
        description="Map-free benchmark evaluation server and metric relocalization API.",
    )
    app.state.settings, app.state.engine, app.state.sessions = settings, engine, session_factory(engine)
    app.state.read_sessions = session_factory(engine, read_only=True)  # GET and HEAD requests, credential checks
    app.state.health = HealthMonitor(engine)
    app.state.metrics = Metrics(engine)
    app.state.heavy = HeavyPool(settings.heavy_threads, settings.heavy_queue, method_threads=settings.method_threads)
    app.state.localizers = Localizers(
        per_method=default_threads(),
        cache_bytes=int(settings.anchor_cache_mb * (1 << 20)),
        max_side=settings.limits.work_max_side,
        pool_bytes=int(settings.method_pool_mb * (1 << 20)),
    )
    if settings.methods_dir is not None:
        register_methods_dir(settings.methods_dir)

    @app.exception_handler(UploadError)
    async def _upload_error(request: Request, exc: UploadError):
        return error_response(request, exc.status, exc.message)

    @app.exception_handler(Withdrawn)
    async def _withdrawn(request: Request, exc: Withdrawn):
        if wants_html(request):
            from .pages import withdrawn_page

            return await run_in_threadpool(withdrawn_page, request, exc)
        return error_response(request, exc.status_code, str(exc.detail))

    @app.exception_handler(StarletteHTTPException)
    async def _http_error(request: Request, exc: StarletteHTTPException):
        msg = exc.detail if isinstance(exc.detail, str) else str(exc.detail)
        headers = getattr(exc, "headers", None)
        if exc.status_code == 413 and "too large" in msg.lower():
            msg = f"request body larger than {settings.limits.max_request_bytes} bytes"
        if exc.status_code == 405:  # every method of the path, not only the first route's
            allowed = allowed_methods(every_route, request.scope)
            headers = {**(headers or {}), "Allow": ", ".join(allowed)}
            msg = f"method {request.method} not allowed here; allowed: {', '.join(allowed)}"
        return error_response(request, exc.status_code, msg, headers)

    @app.exception_handler(RequestValidationError)
    async def _validation(request: Request, exc: RequestValidationError):
        return error_response(request, 422, _validation_message(exc))

    def _database_down(request: Request, exc: Exception):
        log.warning("database unavailable", extra={"path": request.url.path, "error": str(exc).splitlines()[0][:300]})
        return error_response(
            request,
            503,
            f"the database is unavailable or busy; try again in {RETRY_AFTER_S} s",
            {"Retry-After": str(RETRY_AFTER_S)},
        )

    @app.exception_handler(Exception)
    async def _crash(request: Request, exc: Exception):  # only reached when the middleware below did not answer
        if unavailable(exc):
            return _database_down(request, exc)
        log.error("unhandled error", exc_info=exc, extra={"path": request.url.path})
        return error_response(request, 500, "internal server error")

    throttle = app.state.auth_throttle = AuthThrottle(settings.auth_failures_per_minute)
    app.add_middleware(CredentialGate)  # inside the access log below: its 401s are logged and counted

    @app.middleware("http")
    async def _access_log(request: Request, call_next):
        """Every request gets an id (``X-Request-ID``) and one JSON access-log line, unexpected 500s included;
        failed token checks are counted per client address (``guard.AuthThrottle``)."""
        t0 = time.perf_counter()
        rid = request.state.request_id = request_id(request)
        try:
            response = await call_next(request)
        except Exception as exc:
            if unavailable(exc):
                response = _database_down(request, exc)
            else:
                log.error(
                    "unhandled error",
                    exc_info=exc,
                    extra={"request_id": rid, "method": request.method, "path": request.url.path},
                )
                response = error_response(request, 500, f"internal server error (request id {rid})")
        client = client_address(request)
        if response.status_code == 401 and throttle.credentialed(request):
            throttle.failed(client)
        route = request.scope.get("route")
        seconds = time.perf_counter() - t0
        method = "HEAD" if getattr(request.state, "head", False) else request.method
        app.state.metrics.observe(method, getattr(route, "path", "unmatched"), response.status_code, seconds)
        response.headers["X-Request-ID"] = rid
        response.headers.setdefault("X-Content-Type-Options", "nosniff")
        response.headers.setdefault("Referrer-Policy", "same-origin")
        if not request.url.path.startswith(("/docs", "/redoc")):
            response.headers.setdefault("Content-Security-Policy", CSP)
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

    app.add_middleware(BodyTimeout, seconds=settings.body_timeout, total_seconds=settings.body_total_timeout)

    from . import pages
    from .accounts import router as accounts
    from .anchors import router as anchors
    from .leaderboard import router as leaderboard
    from .operations import router as operations

    every_route = list(app.router.routes)  # the app's own and every router's, for a 405's Allow
    for r in (operations, accounts, leaderboard, anchors, pages):
        app.include_router(r.router)
        every_route += r.router.routes
    app.mount("/static", StaticFiles(directory=str(Path(__file__).parent / "static")), name="static")
    app.add_middleware(HeadAsGet)
    app.add_middleware(HeadSizeLimit)
    schema = app.openapi
    app.openapi = lambda: for_clients(schema())  # type: ignore[method-assign]
    return app


def _env_path(name: str) -> Path | None:
    """The folder an environment variable names (unset or empty: None)."""
    value = os.environ.get(name)
    return Path(value) if value else None


def app_from_env() -> FastAPI:
    """Factory for ``uvicorn --factory mapfree.service.app:app_from_env`` (settings from MAPFREE_* variables)."""
    from .http.logs import setup_logging

    setup_logging(os.environ.get("MAPFREE_LOG_LEVEL", "info"))
    raw = os.environ.get("MAPFREE_SETTINGS")
    parent = parent_from_env()
    if parent is not None:  # an API process of `mapfree serve --api-processes N`: it ends with that process
        die_with_parent(parent)
    if raw:  # written by `mapfree serve --api-processes N`
        from .config import Limits

        d = json.loads(raw)
        d["limits"] = Limits(**d.get("limits", {}))
        d["splits"] = tuple(d.get("splits", ("val", "test")))
        s = Settings(**d)
    else:
        s = Settings(
            db_url=os.environ.get("MAPFREE_DB", "sqlite:///mapfree.db"),
            data_root=_env_path("MAPFREE_DATA"),
            gt_root=_env_path("MAPFREE_GT"),
            default_method=os.environ.get("MAPFREE_METHOD", ""),
            test_daily_limit=parse_daily_limit(os.environ.get("MAPFREE_TEST_DAILY_LIMIT", "5")),
            secure_cookies=os.environ.get("MAPFREE_SECURE_COOKIES", "") == "1",
            operator_token=os.environ.get("MAPFREE_OPERATOR_TOKEN", ""),
        )
    app = create_app(s)
    freeze_long_lived()
    return app
