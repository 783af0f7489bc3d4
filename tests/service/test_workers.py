"""The service's processes: workers never import from the working directory and vanish from /health when killed, a
worker that keeps dying is restarted with backoff, any burst of SIGTERMs stops one, and a serving process freezes
its long-lived objects."""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import time
import zipfile

import httpx
import pytest
from sqlalchemy import func, select

from mapfree.service import Settings

from .conftest import OPERATOR_TOKEN, create_users, free_port, health_detail, stop_server
from .conftest import pose_text as _pose_text
from .conftest import zip_of as _zip

FAKE_CONCURRENT = """
import importlib.util, os, sys, sysconfig
with open({marker!r}, "a") as f:
    f.write(f"{{os.getpid()}}\\n")
_dir = os.path.join(sysconfig.get_paths()["stdlib"], "concurrent")
_spec = importlib.util.spec_from_file_location("concurrent", os.path.join(_dir, "__init__.py"),
                                               submodule_search_locations=[_dir])
_mod = importlib.util.module_from_spec(_spec)
sys.modules["concurrent"] = _mod
_spec.loader.exec_module(_mod)
"""


def test_workers_ignore_the_working_directory_and_health_drops_dead_workers(split_data, tmp_path):
    """A ``concurrent.py`` where ``mapfree serve`` starts never runs in a worker; a SIGKILLed worker vanishes
    from /health at once, which says ``degraded`` while no worker is alive."""
    hostile = tmp_path / "cwd"
    hostile.mkdir()
    marker = tmp_path / "imported-from-cwd.txt"
    (hostile / "concurrent.py").write_text(FAKE_CONCURRENT.format(marker=str(marker)))
    port, db = free_port(), f"sqlite:///{tmp_path / 'iso.db'}"
    log = open(tmp_path / "serve.log", "w")  # noqa: SIM115 - the server writes it for as long as it runs
    # -P: the API process itself must not pick the file up either (what the console script `mapfree` does)
    proc = subprocess.Popen(
        [
            sys.executable,
            "-P",
            "-m",
            "mapfree.cli.serve",
            "--db",
            db,
            "--data",
            str(split_data.root),
            "--workers",
            "1",
            "--port",
            str(port),
        ],
        cwd=hostile,
        stdout=log,
        stderr=subprocess.STDOUT,
        start_new_session=True,
        env={**os.environ, "OMP_NUM_THREADS": "1", "MAPFREE_OPERATOR_TOKEN": OPERATOR_TOKEN},
    )
    url = f"http://127.0.0.1:{port}"
    try:
        deadline, h = time.time() + 60, {}
        while time.time() < deadline and not h.get("workers"):
            assert proc.poll() is None, (tmp_path / "serve.log").read_text()[-2000:]
            with contextlib.suppress(httpx.HTTPError):
                h = health_detail(url)
            time.sleep(0.2)
        assert h.get("workers") and h["status"] == "ok", (h, (tmp_path / "serve.log").read_text()[-2000:])
        time.sleep(1.0)  # a worker that imported the file would have written the marker by now
        assert not marker.exists(), f"imported from the working directory by pid {marker.read_text()}"
        os.kill(h["workers"][0]["pid"], signal.SIGKILL)
        time.sleep(0.3)
        after = health_detail(url, timeout=5)
        assert after["workers"] == [] and after["status"] == "degraded", after
    finally:
        stop_server(proc)
        log.close()


def test_a_worker_that_keeps_dying_is_restarted_with_backoff():
    from mapfree.cli.serve import Supervisor

    sup = Supervisor([sys.executable, "-c", "raise SystemExit(3)"], 1, backoff=0.25, max_backoff=10.0)
    sup.start()
    time.sleep(2.5)
    sup.stop()
    # restarts after 0.25, 0.5, 1, 2 s: at most 4 in 2.5 s (a fixed 1 s poll or none would give more)
    assert 2 <= sup.spawned <= 4, sup.spawned
    assert sup.failures[0] >= 2


def _worker_rows(db_url: str) -> int:
    from mapfree.service.database.models import WorkerRow, make_engine, session_factory

    engine = make_engine(db_url)
    with session_factory(engine)() as db:
        n = db.scalar(select(func.count()).select_from(WorkerRow))
    engine.dispose()
    return int(n or 0)


@pytest.mark.parametrize("when", ["idle", "mid-job"])
def test_a_burst_of_sigterms_stops_a_worker(split_data, tmp_path, when):
    """The worker's SIGTERM handler called ``Event.set()``; a second SIGTERM landing while the first handler
    held the event's lock (``serve`` stopping it and the parent-death signal, close together) blocked the
    nested handler for ever: the worker outlived ``serve``. Now a handler only wakes a thread. SIGTERMs are
    sent every millisecond from the moment the worker is idle (or scoring a job) until it has exited, so
    that they also land during its final database delete."""
    from mapfree.service.database.models import User, init_db, make_engine, session_factory
    from mapfree.service.leaderboard.submissions import accept

    db_url = f"sqlite:///{tmp_path / 'w.db'}"
    create_users(db_url, {"ann": None})
    if when == "mid-job":
        engine = make_engine(db_url)
        init_db(engine)
        with session_factory(engine)() as db:
            user = db.scalar(select(User).where(User.name == "ann"))
            data = _zip(
                {
                    f"pose_{s.name}.txt": _pose_text(s, 20_000, i)
                    for i, s in enumerate(sorted((split_data.root / "val").iterdir()))
                },
                zipfile.ZIP_DEFLATED,
            )
            accept(db, Settings(db_url=db_url, data_root=split_data.root), user, "val", "slow", False, data)
        engine.dispose()
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "mapfree.service.leaderboard.worker",
            "--db",
            db_url,
            "--data",
            str(split_data.root),
            "--poll-seconds",
            "0.05",
        ],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        env={**os.environ, "OMP_NUM_THREADS": "1"},
    )
    try:
        deadline = time.time() + 60
        while time.time() < deadline and _worker_rows(db_url) == 0:
            assert proc.poll() is None
            time.sleep(0.05)
        if when == "mid-job":
            while time.time() < deadline and "running" not in _statuses(db_url):
                time.sleep(0.01)
            assert "running" in _statuses(db_url)
        t0, sent = time.time(), 0
        while proc.poll() is None and time.time() - t0 < 20:
            for _ in range(200):  # back to back: one lands while the handler of another runs
                try:
                    os.kill(proc.pid, signal.SIGTERM)
                except ProcessLookupError:
                    break
            sent += 200
            time.sleep(0.001)
        assert proc.poll() is not None, f"the worker still runs {time.time() - t0:.0f} s after {sent} SIGTERMs"
        assert _worker_rows(db_url) == 0 or proc.returncode != 0  # a clean stop removed its row
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def _statuses(db_url: str) -> set[str]:
    from mapfree.service.database.models import Submission, make_engine, session_factory

    engine = make_engine(db_url)
    with session_factory(engine)() as db:
        out = set(db.scalars(select(Submission.status)))
    engine.dispose()
    return out


def test_a_signal_during_the_stop_handler_cannot_deadlock():
    """The nested-handler deadlock, made certain: the main thread holds the stop event's lock (as a first
    handler inside ``Event.set()`` does) when two SIGTERMs arrive. A handler that called ``stop.set()`` blocked
    on that lock for ever; ``stop_on_signals``' handlers return at once and a thread sets the event."""
    script = (
        "import os, signal, threading, sys\n"
        "from mapfree.service.process import stop_on_signals\n"
        "stop = threading.Event()\n"
        "stop_on_signals(stop)\n"
        "with stop._cond:\n"
        "    os.kill(os.getpid(), signal.SIGTERM)\n"
        "    os.kill(os.getpid(), signal.SIGTERM)\n"
        "    sum(range(1000))\n"
        "sys.exit(0 if stop.wait(10) else 1)\n"
    )
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=30)
    assert out.returncode == 0, out.stderr


def test_a_serving_process_freezes_its_long_lived_objects(tmp_path):
    """In a serving process the app's objects (and a relocalizer built later) leave the garbage collector's
    walks, so a full collection no longer pauses requests; a process that did not ask collects as usual."""
    code = f"""
import gc
from mapfree.service import Settings, create_app
from mapfree.service.http.gc_freeze import after_load, freeze_long_lived
app = create_app(Settings(db_url="sqlite:///{tmp_path / "gc.db"}"))
after_load()
assert gc.get_freeze_count() == 0, "froze without being asked"
freeze_long_lived()
frozen = gc.get_freeze_count()
assert frozen > 50000, frozen
keep = [[i] for i in range(20000)]
after_load()
assert gc.get_freeze_count() >= frozen + 20000, (frozen, gc.get_freeze_count())
"""
    r = subprocess.run(
        [sys.executable, "-c", code],
        capture_output=True,
        text=True,
        timeout=120,
        env={**os.environ, "OMP_NUM_THREADS": "1"},
    )
    assert r.returncode == 0, r.stderr[-2000:]
