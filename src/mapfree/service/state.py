"""What the app holds for its requests (``create_app`` keeps it on ``app.state``), read in this one place and
handed to routes as FastAPI dependencies: the settings, the database's session factories and the limit on failed
token checks (helpers that are given only the request, such as the page frame, read them through the functions
here). The resources' own long-lived parts are theirs to hand out: the heavy pool (``http.heavy.Heavy``), the prepared methods
(``anchors.localizers.LocalizersDep``), the metrics and the health monitor (``operations.router``)."""

from __future__ import annotations

from typing import Annotated, Protocol

from fastapi import Depends, Request
from sqlalchemy.orm import Session, sessionmaker

from .config import Settings


def settings_of(request: Request) -> Settings:
    """The deployment's settings (``create_app``'s argument)."""
    return request.app.state.settings


def sessions_of(request: Request, read_only: bool = False) -> sessionmaker[Session]:
    """The app's database session factory: read-only (GET and HEAD requests, credential checks) or not."""
    return request.app.state.read_sessions if read_only else request.app.state.sessions


async def _settings(request: Request) -> Settings:  # async: resolving it takes no thread of the shared pool
    return settings_of(request)


async def _sessions(request: Request) -> sessionmaker[Session]:
    return sessions_of(request)


#: A route's ``settings: SettingsDep``: the deployment's settings.
SettingsDep = Annotated[Settings, Depends(_settings)]
#: A route's ``sessions: SessionsDep``: the session factory, for work that outlives the request's session
#: (a streamed response).
SessionsDep = Annotated[sessionmaker[Session], Depends(_sessions)]


class Throttle(Protocol):
    """What a route asks of the failed-token-check limit (``http.guard.AuthThrottle``)."""

    def refuse(self, request: Request) -> None:
        """429 when the caller's address is past its failures, else nothing."""


def throttle_of(request: Request) -> Throttle:
    """The app's limit on failed token checks."""
    return request.app.state.auth_throttle


async def _throttle(request: Request) -> Throttle:
    return throttle_of(request)


#: A route's ``throttle: ThrottleDep``: the limit on failed token checks, for a sign-in form's.
ThrottleDep = Annotated[Throttle, Depends(_throttle)]
