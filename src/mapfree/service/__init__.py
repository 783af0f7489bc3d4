"""The service: a FastAPI app (evaluation server + relocalization API) over SQLite or PostgreSQL, with
background evaluation workers. ``create_app(Settings(...))``; run it with ``mapfree serve``."""

from __future__ import annotations

from typing import TYPE_CHECKING

from .config import Limits, Settings

if TYPE_CHECKING:
    from fastapi import FastAPI

__all__ = ["Settings", "Limits", "create_app"]


def create_app(settings: Settings) -> FastAPI:
    """The service's ASGI app: the JSON API (submissions, leaderboards, relocalization anchors, accounts), the
    web pages, and the monitoring endpoints, over the database ``settings.db_url`` names.

    The database is created, or upgraded to this code's schema version, first (safe from several processes at
    once), and uploads cut off when an earlier server was killed are removed. Submissions are only queued
    here: evaluation workers score them (``mapfree serve --workers N``, or
    ``mapfree.service.leaderboard.worker.run`` in a process of your own). Importing ``mapfree.service`` stays
    light: the web stack is imported on the first call.

    Args:
        settings: The deployment: database URL, dataset and ground-truth folders, limits, quotas.

    Returns:
        A FastAPI application; serve it with any ASGI server (``mapfree serve`` runs uvicorn with the
        connection limits and timeouts a public server needs).

    Raises:
        mapfree.service.database.migrations.SchemaVersion: The database was upgraded by a newer mapfree.
        sqlalchemy.exc.SQLAlchemyError: The database cannot be reached.

    Example:
        ```python
        from pathlib import Path

        import uvicorn

        from mapfree.service import Settings, create_app

        app = create_app(Settings(db_url="sqlite:///mapfree.db", data_root=Path("data")))
        uvicorn.run(app, host="127.0.0.1", port=8000)
        ```
    """
    from .app import create_app as _create

    return _create(settings)
