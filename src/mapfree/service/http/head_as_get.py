"""``HEAD`` wherever ``GET`` is answered (HTTP requires it; monitors and link checkers send it): the request is
routed as a ``GET`` and the body is dropped, its headers (``Content-Length`` included) kept."""

from __future__ import annotations

from collections.abc import Awaitable, Callable
from typing import Any

Scope = dict[str, Any]
Message = dict[str, Any]


class HeadAsGet:
    """ASGI middleware: a ``HEAD`` request runs its ``GET`` route; only the response's start reaches the client."""

    def __init__(self, app: Callable[..., Awaitable[None]]):
        self.app = app

    async def __call__(self, scope: Scope, receive, send) -> None:
        if scope["type"] != "http" or scope["method"] != "HEAD":
            await self.app(scope, receive, send)
            return

        async def send_head(message: Message) -> None:
            if message["type"] != "http.response.body":
                await send(message)
            elif not message.get("more_body", False):  # the body's last part: end the response, empty
                await send({"type": "http.response.body", "body": b"", "more_body": False})

        state = {**scope.get("state", {}), "head": True}  # request.state.head: logs say HEAD
        await self.app({**scope, "method": "GET", "state": state}, receive, send_head)
