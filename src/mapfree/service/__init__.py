"""The service: a FastAPI app (evaluation server + relocalization API) over SQLite or PostgreSQL, with
background evaluation workers. ``create_app(Settings(...))``; run it with ``mapfree serve``."""

from .config import Limits, Settings

__all__ = ["Settings", "Limits", "create_app"]


def create_app(settings: Settings):
    from .http.app import create_app as _create

    return _create(settings)
