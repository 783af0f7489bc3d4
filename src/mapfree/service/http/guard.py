"""Per-request guards of the HTTP layer: request ids for logs and error bodies, the client address, and a
limit on failed token checks."""

from __future__ import annotations

import re
import threading
import time
import uuid
from collections import OrderedDict, deque

from fastapi import HTTPException, Request
from starlette.concurrency import run_in_threadpool
from starlette.datastructures import Headers
from starlette.types import ASGIApp, Receive, Scope, Send

from ..accounts.caller import check_credentials
from .errors import error_response

_RID_RE = re.compile(r"[A-Za-z0-9._-]{1,64}")


def request_id(request: Request) -> str:
    """The caller's ``X-Request-ID`` when it is a short plain token (a proxy's), else a fresh one."""
    given = request.headers.get("x-request-id", "")
    return given if _RID_RE.fullmatch(given) else uuid.uuid4().hex[:16]


def client_address(request: Request) -> str:
    """The caller's address: the TCP peer's, or a trusted proxy's ``X-Forwarded-For`` (uvicorn applies it only
    for the proxies ``serve --forwarded-allow-ips`` names)."""
    return request.client.host if request.client else "?"


class AuthThrottle:
    """Failed token checks per client address in a sliding minute. Over the limit, a wrong token (API or
    sign-in form) from that address is answered 429 instead of 401 until the oldest failure is a minute old
    (per API process). A valid token always goes through: the failures of others behind the same address (a
    NAT, a proxy) never lock its owner out. Tokens are 256-bit random strings, so no guessing rate could find
    one; what the 429 adds is a signal to back off, and quieter logs."""

    def __init__(self, per_minute: int, max_clients: int = 100_000):
        self.per_minute, self.max_clients = per_minute, max_clients
        self._failures: OrderedDict[str, deque] = OrderedDict()
        self._lock = threading.Lock()

    @staticmethod
    def credentialed(request: Request) -> bool:
        """A bearer token or the sign-in form: what a guesser sends (a stale cookie is not a guess)."""
        return "authorization" in request.headers or (request.method == "POST" and request.url.path == "/login")

    def retry_after(self, client: str) -> int:
        """Seconds until ``client`` may try again (0: now)."""
        if self.per_minute <= 0:
            return 0
        with self._lock:
            q = self._failures.get(client)
            if not q:
                return 0
            while q and q[0] < time.monotonic() - 60:
                q.popleft()
            return int(q[0] + 60 - time.monotonic()) + 1 if len(q) >= self.per_minute else 0

    def refuse(self, request: Request) -> None:
        """For a wrong token: a 429 (with ``Retry-After``) when its address is over the limit; else nothing
        (the caller answers 401, which the access-log middleware counts)."""
        wait = self.retry_after(client_address(request))
        if wait:
            raise HTTPException(
                429,
                f"too many failed token checks from this address; try again in {wait} s",
                headers={"Retry-After": str(wait)},
            )

    def failed(self, client: str) -> None:
        if self.per_minute <= 0:
            return
        with self._lock:
            q = self._failures.setdefault(client, deque(maxlen=self.per_minute))
            q.append(time.monotonic())
            self._failures.move_to_end(client)
            while len(self._failures) > self.max_clients:  # a flood of addresses: forget the quietest
                self._failures.popitem(last=False)


#: Requests that carry a body but no credentials by design: the sign-in form.
_ANONYMOUS_WRITES = {("POST", "/login")}
_BODY_METHODS = ("POST", "PUT", "PATCH", "DELETE")
#: The one content type an anonymous write may have (the sign-in form's), and its largest body: a token and a
#: CSRF token are under 200 bytes.
ANONYMOUS_TYPE, ANONYMOUS_MAX_BYTES = "application/x-www-form-urlencoded", 4096


def anonymous_body_problem(scope: Scope) -> tuple[int, str] | None:
    """Why an anonymous write's body is refused from its headers, before a byte is read, or None: it must be the
    sign-in form's (urlencoded, read in memory), with a ``Content-Length`` of at most ``ANONYMOUS_MAX_BYTES``. A
    ``multipart/form-data`` body with a file part used to be spooled to disk before the handler ran: ten
    connections holding the last byte of 60 MB bodies kept 600 MB of temporary files open."""
    headers = Headers(scope=scope)
    kind = headers.get("content-type", "").split(";")[0].strip().lower()
    if kind != ANONYMOUS_TYPE:
        return 415, f"the sign-in form is sent as {ANONYMOUS_TYPE}; got {kind or 'no content type'}"
    length = headers.get("content-length", "")
    if not length.isdigit():
        return 411, "the sign-in form needs a Content-Length"
    if int(length) > ANONYMOUS_MAX_BYTES:
        return 413, f"the sign-in form is at most {ANONYMOUS_MAX_BYTES} bytes; got {length}"
    return None


class CredentialGate:
    """ASGI middleware: a request that may carry a body (every write but the sign-in form) is refused 401 from
    its headers, before a byte of its body is read, when its credentials are missing or bad. An anonymous
    upload used to be read whole (spooled to disk) and only then refused. The sign-in form, the one anonymous
    write, is refused from its headers too unless it is a small urlencoded body (``anonymous_body_problem``).
    The account found is kept in
    ``request.state.account`` (the heavy pool's fair share is per account)."""

    def __init__(self, app: ASGIApp):
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or scope["method"] not in _BODY_METHODS:
            return await self.app(scope, receive, send)
        request = Request(scope)
        if (scope["method"], scope["path"]) in _ANONYMOUS_WRITES:
            problem = anonymous_body_problem(scope)
            if problem is None:
                return await self.app(scope, receive, send)
            response = await run_in_threadpool(error_response, request, *problem, {"Connection": "close"})
            return await response(scope, receive, send)
        try:
            scope.setdefault("state", {})["account"] = await run_in_threadpool(check_credentials, request)
        except HTTPException as e:
            headers = {**(e.headers or {}), "Connection": "close"}  # the unread body ends the connection
            response = await run_in_threadpool(error_response, request, e.status_code, str(e.detail), headers)
            return await response(scope, receive, send)
        return await self.app(scope, receive, send)
