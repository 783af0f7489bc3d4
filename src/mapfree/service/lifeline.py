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


def parent_from_env() -> int | None:
    """The serving process's pid, as ``mapfree serve`` passes it to its API processes."""
    value = os.environ.get(PARENT_PID_ENV, "")
    return int(value) if value.isdigit() else None
