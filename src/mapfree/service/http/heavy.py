"""Heavy requests (localize, anchor creation and photos, the try page) on threads of their own.

FastAPI runs every plain ``def`` endpoint on one shared pool (40 threads): 45 concurrent localize calls took
all of them and stalled sign-in, the leaderboards and every other page. Here the heavy endpoints run on a small
bounded pool instead, with a bounded number of requests admitted (running or waiting): past that the answer is
an immediate 429 with ``Retry-After``, so that neither threads nor memory grow with the number of callers. One
account gets a fair share of them: four anchors localized round-robin by one account used to make every
other user's request wait behind its own."""

from __future__ import annotations

import asyncio
import contextvars
import functools
import math
import os
import sys
import threading
import time
from collections import OrderedDict, deque
from collections.abc import Callable, Hashable
from concurrent.futures import ThreadPoolExecutor
from typing import Annotated, Any

from fastapi import Depends, HTTPException, Request

from .guard import client_address


def default_threads() -> int:
    """Heavy computations at once per API process when not configured: one per CPU, at most 4."""
    return max(1, min(4, os.cpu_count() or 1))


def default_method_threads(heavy_threads: int) -> int:
    """One heavy computation's threads when not configured: the CPUs shared among the heavy threads (at least
    one each), so that heavy threads x method threads stay within the CPUs. More oversubscribes the cores: with
    torch's two OpenMP threads per request on a busy 2-CPU machine, the default method took 2.0 s instead of
    0.2 s (OpenMP threads wait for each other at every parallel region)."""
    return max(1, (os.cpu_count() or 1) // max(1, heavy_threads))


def set_method_threads(threads: int) -> None:
    """The calling thread's method thread pools: ``threads`` (> 0) for OpenCV, torch's intra-op pool, the BLAS
    libraries and OpenMP.

    Set explicitly rather than inherited: an ``OMP_NUM_THREADS=1`` in the server's environment used to leave
    NumPy's BLAS and torch single-threaded in the API and OpenCV on every core, whatever the library call it is
    compared with had. OpenMP's count is per thread, hence a call on each heavy thread. torch is not imported
    for this (a server of OpenCV methods never loads it): the environment variables set here are what it and
    its OpenMP read when a method loads them later."""
    import cv2
    from threadpoolctl import threadpool_limits

    for var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
        os.environ[var] = str(threads)
    cv2.setNumThreads(threads)
    threadpool_limits(threads)  # BLAS (process-wide) and OpenMP (this thread), as loaded so far
    torch = sys.modules.get("torch")
    if torch is not None:
        torch.set_num_threads(threads)


class HeavyPool:
    """``threads`` worker threads and room for ``queue`` more requests waiting (``capacity`` in all), shared fairly
    among accounts, with room reserved for an account not yet in:

    * an account not in is admitted while there is room at all;
    * an account with requests in gets one more only while it holds fewer than ``capacity // (k + 1)`` of them,
      ``k`` the accounts in (itself included), and fewer than ``per_account`` when that is set. So ``k``
      accounts flooding hold at most ``k * (capacity // (k + 1))`` once the requests they had in before the
      last of them came have ended, and at least ``capacity / (k + 1)`` slots stay free for a newcomer
      (one account alone: half the room; two: a third each);
    * a free thread goes to the accounts waiting in turn, so one account's requests queue behind its own, not
      in front of everyone else's.

    Each thread sets its method thread pools to ``method_threads`` when it starts (``set_method_threads``; 0:
    ``default_method_threads``)."""

    def __init__(self, threads: int, queue: int, per_account: int = 0, method_threads: int = 0):
        self.threads = threads if threads > 0 else default_threads()
        self.capacity = self.threads + max(0, queue)
        self.per_account = per_account if per_account > 0 else self.capacity
        self.method_threads = method_threads if method_threads > 0 else default_method_threads(self.threads)
        self.executor = ThreadPoolExecutor(
            self.threads,
            thread_name_prefix="mapfree-heavy",
            initializer=set_method_threads,
            initargs=(self.method_threads,),
        )
        self._lock = threading.Lock()
        self.admitted = 0
        self._in: dict[Hashable, int] = {}  # requests admitted per account
        self._turns: dict[Hashable, int] = {}  # threads given to each account with requests in
        self._waiting: OrderedDict[Hashable, deque[asyncio.Future]] = OrderedDict()  # first: waits longest
        self.running = 0
        self._mean_s = 2.0  # running mean of a heavy request's duration, for Retry-After

    def retry_after(self) -> int:
        """Seconds after which a slot is likely free: the queue ahead drained at the recent pace."""
        return max(1, min(120, math.ceil(self._mean_s * self.capacity / self.threads)))

    def _busy(self, message: str) -> HTTPException:
        wait = self.retry_after()
        return HTTPException(429, f"{message}; try again in {wait} s", headers={"Retry-After": str(wait)})

    def _admit(self, account: Hashable) -> None:
        with self._lock:
            if self.admitted >= self.capacity:
                raise self._busy(f"the server is busy with {self.admitted} relocalization requests (its limit)")
            held = self._in.get(account, 0)
            share = self.share()
            if held and held >= share:
                raise self._busy(
                    f"this account has {held} relocalization requests in already (its share of the server: "
                    f"{share} while {len(self._in)} accounts have requests in)"
                )
            self.admitted += 1
            if account not in self._in:  # one turn ahead of the accounts in (none starves a newcomer, nor it them)
                self._turns[account] = max(0, min(self._turns.values(), default=0) - 1)
            self._in[account] = self._in.get(account, 0) + 1

    def share(self) -> int:
        """Requests one account with requests in may hold (call with the lock held): ``capacity // (k + 1)`` for
        ``k`` accounts in, room kept for one more, capped by ``per_account``."""
        return min(self.per_account, self.capacity // (len(self._in) + 1))

    def _done(self, account: Hashable, seconds: float) -> None:
        with self._lock:
            self.admitted -= 1
            self._in[account] -= 1
            if not self._in[account]:
                del self._in[account], self._turns[account]
            self._mean_s = 0.8 * self._mean_s + 0.2 * seconds

    async def _turn(self, account: Hashable) -> None:
        """Wait for a thread (on the event loop, like ``_release``): at once when one is free and nobody waits."""
        if self.running < self.threads and not self._waiting:
            self.running += 1
            self._turns[account] += 1
            return
        turn = asyncio.get_running_loop().create_future()
        self._waiting.setdefault(account, deque()).append(turn)
        try:
            await turn
        except asyncio.CancelledError:
            if turn.done() and not turn.cancelled():  # the thread was given as the request went: pass it on
                self._release()
            else:
                q = self._waiting.get(account)
                if q is not None and turn in q:
                    q.remove(turn)
                    if not q:
                        del self._waiting[account]
            raise

    def _release(self) -> None:
        """A thread is free: give it to the waiting account that had the fewest turns (the one waiting longest
        among equals), which then waits at the back."""
        self.running -= 1
        while self.running < self.threads and self._waiting:
            account = min(self._waiting, key=self._turns.__getitem__)
            q = self._waiting.pop(account)
            turn = q.popleft()
            if q:
                self._waiting[account] = q
            if turn.cancelled():
                continue
            self.running += 1
            self._turns[account] += 1
            turn.set_result(None)

    async def run(self, fn: Callable[..., Any], *args: Any, account: Hashable = None, **kwargs: Any) -> Any:
        """``fn(*args, **kwargs)`` on a heavy thread for ``account`` (429 when ``capacity`` requests, or the
        account's share, are in already)."""
        self._admit(account)
        t0 = time.perf_counter()
        try:
            await self._turn(account)
            try:
                ctx = contextvars.copy_context()
                call = functools.partial(ctx.run, fn, *args, **kwargs)
                return await asyncio.get_running_loop().run_in_executor(self.executor, call)
            finally:
                self._release()
        finally:
            self._done(account, time.perf_counter() - t0)

    def shutdown(self) -> None:
        self.executor.shutdown(wait=False, cancel_futures=True)


def pool_of(request: Request) -> HeavyPool:
    """The app's heavy pool (``create_app`` holds it)."""
    return request.app.state.heavy


async def _heavy_pool(request: Request) -> HeavyPool:  # async: resolving it takes no thread of the shared pool
    return pool_of(request)


#: A route's ``pool: Heavy``: the app's ``HeavyPool``, for a route that sends only part of its work there.
Heavy = Annotated[HeavyPool, Depends(_heavy_pool)]


def heavy(fn: Callable[..., Any]) -> Callable[..., Any]:
    """Decorator of a plain ``def`` endpoint with a ``request`` parameter: FastAPI sees the same parameters, but
    the body runs on the app's ``HeavyPool`` (``pool_of``) instead of the shared thread pool."""

    @functools.wraps(fn)
    async def endpoint(*args: Any, **kwargs: Any) -> Any:
        request: Request = kwargs["request"]
        account = getattr(request.state, "account", None) or client_address(request)  # CredentialGate's
        return await pool_of(request).run(fn, *args, account=account, **kwargs)

    return endpoint
