"""Heavy requests (localize, anchor creation and photos, the try page) on threads of their own.

FastAPI runs every plain ``def`` endpoint on one shared pool (40 threads): 45 concurrent localize calls took
all of them and stalled sign-in, the leaderboards and every other page. Here the heavy endpoints run on a small
bounded pool instead, with a bounded number of requests admitted (running or waiting): past that the answer is
an immediate 429 with ``Retry-After``, so that neither threads nor memory grow with the number of callers."""

from __future__ import annotations

import asyncio
import contextvars
import functools
import math
import os
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from typing import Any, Callable

from fastapi import HTTPException, Request


def default_threads() -> int:
    """Heavy computations at once per API process when not configured: one per CPU, at most 4."""
    return max(1, min(4, os.cpu_count() or 1))


class HeavyPool:
    """``threads`` worker threads and room for ``queue`` more requests waiting; ``run`` answers 429 when full."""

    def __init__(self, threads: int, queue: int):
        self.threads = threads if threads > 0 else default_threads()
        self.capacity = self.threads + max(0, queue)
        self.executor = ThreadPoolExecutor(self.threads, thread_name_prefix="mapfree-heavy")
        self._lock = threading.Lock()
        self.admitted = 0
        self._mean_s = 2.0  # running mean of a heavy request's duration, for Retry-After

    def retry_after(self) -> int:
        """Seconds after which a slot is likely free: the queue ahead drained at the recent pace."""
        return max(1, min(120, math.ceil(self._mean_s * self.capacity / self.threads)))

    def _admit(self) -> None:
        with self._lock:
            if self.admitted >= self.capacity:
                wait = self.retry_after()
                raise HTTPException(429, f"the server is busy with {self.admitted} relocalization requests "
                                         f"(its limit); try again in {wait} s", headers={"Retry-After": str(wait)})
            self.admitted += 1

    def _done(self, seconds: float) -> None:
        with self._lock:
            self.admitted -= 1
            self._mean_s = 0.8 * self._mean_s + 0.2 * seconds

    async def run(self, fn: Callable[..., Any], *args: Any, **kwargs: Any) -> Any:
        """``fn(*args, **kwargs)`` on a heavy thread (429 when ``capacity`` requests are in already)."""
        self._admit()
        t0 = time.perf_counter()
        try:
            ctx = contextvars.copy_context()
            call = functools.partial(ctx.run, fn, *args, **kwargs)
            return await asyncio.get_running_loop().run_in_executor(self.executor, call)
        finally:
            self._done(time.perf_counter() - t0)

    def shutdown(self) -> None:
        self.executor.shutdown(wait=False, cancel_futures=True)


def heavy(fn: Callable[..., Any]) -> Callable[..., Any]:
    """Decorator of a plain ``def`` endpoint with a ``request`` parameter: FastAPI sees the same parameters, but
    the body runs on the app's ``HeavyPool`` (``app.state.heavy``) instead of the shared thread pool."""

    @functools.wraps(fn)
    async def endpoint(*args: Any, **kwargs: Any) -> Any:
        request: Request = kwargs["request"]
        return await request.app.state.heavy.run(fn, *args, **kwargs)

    return endpoint
