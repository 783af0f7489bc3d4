"""The FastAPI application: ``create_app(settings)``: the database (created, upgraded, repaired), what the app
holds for its requests, the middlewares, the error handlers (``handlers``) and each resource's routers."""

from __future__ import annotations

import json
import logging
import os
from pathlib import Path

from fastapi import FastAPI
from fastapi.staticfiles import StaticFiles
from fastapi_offline import FastAPIOffline
from sqlalchemy.engine import Engine
from starlette.routing import BaseRoute

from .. import __version__
from .anchors.localizers import Localizers, register_methods_dir
from .config import Settings, parse_daily_limit
from .database.models import init_db, make_engine, session_factory
from .handlers import install_error_handlers
from .http.access import AccessLog
from .http.gc_freeze import freeze_long_lived
from .http.guard import AuthThrottle, CredentialGate
from .http.head_as_get import HeadAsGet
from .http.heavy import HeavyPool, default_threads
from .http.timeouts import BodyTimeout, HeadSizeLimit
from .leaderboard.storage import drop_interrupted_uploads
from .operations.health import HealthMonitor
from .operations.metrics import Metrics
from .process import die_with_parent, parent_from_env
from .schemas import ERRORS, for_clients

log = logging.getLogger("mapfree.http")


def open_repaired(db_url: str) -> Engine:
    """The database's engine, its schema created or upgraded to this code's, and the uploads cut off when a
    server was killed removed (their quota and test evaluations refunded)."""
    engine = make_engine(db_url)
    init_db(engine)
    with session_factory(engine).begin() as db:
        if n := drop_interrupted_uploads(db):
            log.warning(
                "interrupted uploads removed; their quota and test evaluations refunded", extra={"submissions": n}
            )
    return engine


def hold(app: FastAPI, settings: Settings, engine: Engine) -> None:
    """What the app holds for its requests (read by the dependencies of ``state``, ``http.heavy``,
    ``anchors.localizers`` and ``operations.router``): settings, database, monitors, pools, prepared methods."""
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
    app.state.auth_throttle = AuthThrottle(settings.auth_failures_per_minute)


def include_routers(app: FastAPI) -> list[BaseRoute]:
    """Every resource's JSON routes, then its web pages, and the static files -> every route (the app's own and
    every router's), for a 405's ``Allow``."""
    from .accounts import pages as account_pages
    from .accounts import router as accounts
    from .anchors import pages as anchor_pages
    from .anchors import router as anchors
    from .leaderboard import pages as leaderboard_pages
    from .leaderboard import router as leaderboard
    from .operations import router as operations

    every_route = list(app.router.routes)
    for r in (operations, accounts, leaderboard, anchors, account_pages, leaderboard_pages, anchor_pages):
        app.include_router(r.router)
        every_route += r.router.routes
    app.mount("/static", StaticFiles(directory=str(Path(__file__).parent / "static")), name="static")
    return every_route


def create_app(settings: Settings) -> FastAPI:
    """The app of ``mapfree.service.create_app`` (documented there): database, state, middlewares, routes."""
    engine = open_repaired(settings.db_url)
    # /docs and /redoc with their assets served from /docs-assets (fastapi-offline): no CDN, so they work offline
    app = FastAPIOffline(
        title="mapfree service",
        version=__version__,
        static_url="/docs-assets",
        max_body_size=settings.limits.max_request_bytes,
        responses=ERRORS,
        description="Map-free benchmark evaluation server and metric relocalization API.",
    )
    hold(app, settings, engine)
    if settings.methods_dir is not None:
        register_methods_dir(settings.methods_dir)
    app.add_middleware(CredentialGate)  # inside the access log: its 401s are logged and counted
    app.add_middleware(AccessLog, throttle=app.state.auth_throttle, observe=app.state.metrics.observe)
    app.add_middleware(BodyTimeout, seconds=settings.body_timeout, total_seconds=settings.body_total_timeout)
    install_error_handlers(app, settings.limits.max_request_bytes, include_routers(app))
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
