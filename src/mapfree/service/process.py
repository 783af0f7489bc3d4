"""Child processes of ``mapfree serve`` (API processes, evaluation workers) end with it: killed with ``kill -9``,
it used to leave its API processes serving the port without workers, and a restart failed with "Address
already in use"."""

from __future__ import annotations

import ctypes
import logging
import os
import signal
import sys
import threading
from collections.abc import Callable

log = logging.getLogger("mapfree.service")
PR_SET_PDEATHSIG = 1  # linux/prctl.h
PARENT_PID_ENV = "MAPFREE_PARENT_PID"


def die_with_parent(parent_pid: int | None, sig: int = signal.SIGTERM, poll_s: float = 1.0) -> None:
    """Have this process receive ``sig`` when its parent dies: Linux ``prctl(PR_SET_PDEATHSIG)``, and, where
    that is missing or the parent died before it was set, a thread that compares ``getppid()`` with
    ``parent_pid`` every ``poll_s`` s (a parent that is gone already: ``sig`` at once)."""
    if sys.platform.startswith("linux"):
        try:
            libc = ctypes.CDLL(None, use_errno=True)
            if libc.prctl(PR_SET_PDEATHSIG, int(sig), 0, 0, 0) != 0:
                log.warning("prctl(PR_SET_PDEATHSIG) failed", extra={"errno": ctypes.get_errno()})
        except (OSError, AttributeError):
            pass
    if parent_pid is None:
        return

    def watch() -> None:
        while os.getppid() == parent_pid:
            threading.Event().wait(poll_s)
        log.warning("parent process is gone; stopping", extra={"parent": parent_pid})
        os.kill(os.getpid(), sig)

    threading.Thread(target=watch, name="mapfree-lifeline", daemon=True).start()


def parent_death_signal(sig: int = signal.SIGTERM) -> Callable[[], None] | None:
    """A ``preexec_fn`` for ``subprocess.Popen``: the child asks for ``sig`` when its parent dies
    (``prctl(PR_SET_PDEATHSIG)``, which survives ``exec``) *before* it execs, so before it runs any code of its
    own; a parent gone already by then (the window between ``fork`` and the ``prctl``) makes it exit at once.
    Workers that set this themselves after their imports were left running for ever when ``serve`` stopped in
    its first seconds. ``None`` off Linux.

    The signal comes when the *thread* that spawned the child ends, so spawn from a thread that lives as long
    as the children should (the main thread, or a supervisor thread that stops them anyway)."""
    if not sys.platform.startswith("linux"):
        return None
    try:
        prctl = ctypes.CDLL(None, use_errno=True).prctl  # looked up here: nothing is loaded in the forked child
    except (OSError, AttributeError):
        return None
    parent = os.getpid()

    def preexec() -> None:
        prctl(PR_SET_PDEATHSIG, int(sig), 0, 0, 0)
        if os.getppid() != parent:
            os._exit(0)

    return preexec


def stop_on_signals(stop: threading.Event, signals: tuple[int, ...] = (signal.SIGTERM, signal.SIGINT)) -> None:
    """Set ``stop`` when one of ``signals`` arrives (call from the main thread). A Python signal handler runs
    between two bytecodes of the main thread, possibly inside a handler that is itself inside ``stop.set()``,
    holding the event's lock: a handler that called ``stop.set()`` then waited on that lock for ever (two
    SIGTERMs close together, ``serve``'s and the parent-death signal, left a worker alive after ``serve`` had
    stopped). So the handlers do nothing; the signal's number reaches a wake-up pipe
    (``signal.set_wakeup_fd``), and a thread that reads it sets ``stop``."""
    r, w = os.pipe()
    os.set_blocking(w, False)
    for sig in signals:
        signal.signal(sig, _ignore)
    signal.set_wakeup_fd(w, warn_on_full_buffer=False)

    def watch() -> None:
        while os.read(r, 64):
            stop.set()

    threading.Thread(target=watch, name="mapfree-signals", daemon=True).start()


def _ignore(signum, frame) -> None:  # the wake-up pipe carries the signal (stop_on_signals)
    return None


def parent_from_env() -> int | None:
    """The serving process's pid, as ``mapfree serve`` passes it to its API processes."""
    value = os.environ.get(PARENT_PID_ENV, "")
    return int(value) if value.isdigit() else None
