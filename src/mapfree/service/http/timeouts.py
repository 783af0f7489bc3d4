"""Read timeouts for ``mapfree serve``: half-sent requests must not hold a connection for ever (slowloris).

uvicorn closes a connection idle between requests (``timeout_keep_alive``), but not one that sends part of a
request: its keep-alive timer stops at the first byte, and nothing limits how long the rest of the request head
or the body may take. Here the request line and headers must arrive within ``header_timeout`` seconds of the
connection (or of the previous response), and each piece of a body within ``body_timeout`` seconds of the
last (408 otherwise)."""

from __future__ import annotations

import asyncio
import os

from starlette.responses import PlainTextResponse
from starlette.types import ASGIApp, Message, Receive, Scope, Send
from uvicorn.protocols.http.h11_impl import H11Protocol

DEFAULT_HEADER_TIMEOUT = 10.0
DEFAULT_BODY_TIMEOUT = 30.0
DEFAULT_PER_ADDRESS = 64
HEADER_TIMEOUT_ENV = "MAPFREE_HEADER_TIMEOUT"
PER_ADDRESS_ENV = "MAPFREE_CONNECTIONS_PER_ADDRESS"
EXEMPT_ENV = "MAPFREE_CONNECTION_CAP_EXEMPT"
HEAD_BYTES_ENV = "MAPFREE_MAX_HEAD_BYTES"
DEFAULT_HEAD_BYTES = 16 * 1024


def _header_timeout() -> float:
    return float(os.environ.get(HEADER_TIMEOUT_ENV, DEFAULT_HEADER_TIMEOUT))


def _per_address() -> int:
    return int(os.environ.get(PER_ADDRESS_ENV, DEFAULT_PER_ADDRESS))


def _exempt() -> set[str]:
    return {a.strip() for a in os.environ.get(EXEMPT_ENV, "").split(",") if a.strip()}


class HeadTimeoutProtocol(H11Protocol):
    """uvicorn's h11 protocol, closing a connection whose request head takes longer than ``header_timeout``, and
    one from an address that holds ``MAPFREE_CONNECTIONS_PER_ADDRESS`` open already (per API process; 0: no
    cap; the trusted proxies are exempt): ~1,100 half-open requests from one address had taken the whole
    ``--limit-concurrency`` and every other client's ``/health`` got 503."""

    _head_timer: asyncio.TimerHandle | None = None
    _peer: str | None = None  # counted in ``_open`` while this connection lasts
    _open: dict[str, int] = {}  # open connections per client address, this process (one event loop)

    def _arm(self) -> None:
        self._disarm()
        if _header_timeout() > 0:
            self._head_timer = self.loop.call_later(_header_timeout(), self._head_timed_out)

    def _disarm(self) -> None:
        if self._head_timer is not None:
            self._head_timer.cancel()
            self._head_timer = None

    def _head_timed_out(self) -> None:
        self._head_timer = None
        if not self.transport.is_closing():
            self.logger.info("request head not received within %g s; connection closed", _header_timeout())
            self.transport.close()

    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        super().connection_made(transport)
        peer = (transport.get_extra_info("peername") or ("?",))[0]
        cap = _per_address()
        if cap > 0 and peer not in _exempt() and "*" not in _exempt():
            if self._open.get(peer, 0) >= cap:
                self.logger.info("%s holds %d connections already; connection closed", peer, cap)
                transport.close()
                return
            self._open[peer] = self._open.get(peer, 0) + 1
            self._peer = peer
        self._arm()

    def handle_events(self) -> None:
        # ``--limit-concurrency`` counts requests being answered, not connections: uvicorn counted every open
        # connection, so half-open ones (a header byte a second, 64 per address from 18 loopback addresses)
        # filled it and /health got 503. Below the limit its check is skipped; at it, it answers 503 as before.
        limit = self.config.limit_concurrency
        if limit is not None:
            answering = sum(
                1
                for c in self.connections
                if isinstance(c, H11Protocol) and c.cycle is not None and not c.cycle.response_complete
            )
            self.limit_concurrency = None if answering < limit else limit
        before = self.cycle
        super().handle_events()
        if self.cycle is not before:  # a request's head arrived
            self._disarm()

    def on_response_complete(self) -> None:
        self._arm()  # the next request's head (a pipelined one is handled below, and disarms it)
        super().on_response_complete()

    def connection_lost(self, exc: Exception | None) -> None:
        self._disarm()
        if self._peer is not None:
            self._open[self._peer] -= 1
            if not self._open[self._peer]:
                del self._open[self._peer]
            self._peer = None
        super().connection_lost(exc)


def head_timeout_protocol(
    header_timeout: float,
    per_address: int = DEFAULT_PER_ADDRESS,
    exempt: str = "",
    max_head_bytes: int = DEFAULT_HEAD_BYTES,
) -> str:
    """What to give uvicorn as ``http=`` for this head timeout (0: none) and cap of connections per client
    address (0: none; ``exempt``: comma-separated addresses without a cap, the trusted proxies); and the largest
    request head ``HeadSizeLimit`` lets through. The values travel in the environment, so that the API
    processes of ``--api-processes N`` read them too."""
    os.environ[HEAD_BYTES_ENV] = str(max(0, int(max_head_bytes)))
    os.environ[HEADER_TIMEOUT_ENV] = repr(max(0.0, float(header_timeout)))
    os.environ[PER_ADDRESS_ENV] = str(max(0, int(per_address)))
    os.environ[EXEMPT_ENV] = exempt
    return f"{__name__}:HeadTimeoutProtocol"


class BodyTimeout:
    """ASGI middleware: a request body whose next piece takes longer than ``seconds``, or that is not all in
    ``total_seconds`` after its first read, is answered 408 and its connection closed (0: no limit). A trickle
    of a byte every few seconds no longer holds a connection and its spooled file for as long as it likes.
    Only reads of the body are timed, not a wait for a disconnect after it; the application sees a disconnect,
    and whatever it answers then is dropped."""

    def __init__(self, app: ASGIApp, seconds: float, total_seconds: float = 0.0):
        self.app, self.seconds, self.total_seconds = app, seconds, total_seconds

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or (self.seconds <= 0 and self.total_seconds <= 0):
            return await self.app(scope, receive, send)
        body_done = timed_out = started = False
        deadline: float | None = None
        loop = asyncio.get_running_loop()

        async def timed_receive() -> Message:
            nonlocal body_done, timed_out, deadline
            if body_done or timed_out:
                return await receive() if not timed_out else {"type": "http.disconnect"}
            if deadline is None and self.total_seconds > 0:
                deadline = loop.time() + self.total_seconds
            waits = [
                w
                for w in (
                    self.seconds if self.seconds > 0 else None,
                    None if deadline is None else max(0.0, deadline - loop.time()),
                )
                if w is not None
            ]
            try:
                message = await asyncio.wait_for(receive(), min(waits))
            except asyncio.TimeoutError:
                timed_out = True
                if not started:
                    why = (
                        f"not all in within {self.total_seconds:g} s"
                        if deadline is not None and loop.time() >= deadline
                        else f"nothing came for {self.seconds:g} s"
                    )
                    body = f'{{"detail": "request body not received: {why}", "status": 408}}'.encode()
                    await send(
                        {
                            "type": "http.response.start",
                            "status": 408,
                            "headers": [
                                (b"content-type", b"application/json"),
                                (b"connection", b"close"),
                                (b"content-length", str(len(body)).encode()),
                            ],
                        }
                    )
                    await send({"type": "http.response.body", "body": body})
                return {"type": "http.disconnect"}
            body_done = message.get("type") != "http.request" or not message.get("more_body", False)
            return message

        async def guarded_send(message: Message) -> None:
            nonlocal started
            if timed_out:
                return  # the 408 went out already
            started = started or message.get("type") == "http.response.start"
            await send(message)

        return await self.app(scope, timed_receive, guarded_send)


def head_bytes(scope: Scope) -> int:
    """Bytes of a request's line and headers as sent (``METHOD path?query HTTP/1.1``, ``name: value`` lines)."""
    line = len(scope["method"]) + len(scope.get("raw_path") or scope["path"].encode()) + 12
    query = len(scope.get("query_string") or b"")
    return line + query + sum(len(k) + len(v) + 4 for k, v in scope.get("headers", ()))


class HeadSizeLimit:
    """ASGI middleware: a request whose line and headers exceed ``MAPFREE_MAX_HEAD_BYTES`` (``mapfree serve
    --h11-max-incomplete-event-size``, 16 KiB by default) is answered 431 and its connection closed. h11's own
    limit holds only for a head that arrives in pieces: 100 KB of headers sent at once used to pass."""

    def __init__(self, app: ASGIApp):
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        limit = int(os.environ.get(HEAD_BYTES_ENV, DEFAULT_HEAD_BYTES))
        if scope["type"] == "http" and limit > 0 and head_bytes(scope) > limit:
            response = PlainTextResponse(
                f"request line and headers larger than {limit} bytes", 431, headers={"Connection": "close"}
            )
            return await response(scope, receive, send)
        return await self.app(scope, receive, send)
