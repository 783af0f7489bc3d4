"""``mapfree serve``: the evaluation server and relocalization API, with N evaluation worker processes."""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import os
import signal
import subprocess
import sys
import threading
import time

log = logging.getLogger("mapfree.serve")


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "serve", help="run the evaluation server + relocalization API (FastAPI) with evaluation workers",
        description="Serve the benchmark's evaluation server and the relocalization API. SQLite by default; "
                    "pass --db postgresql://user:pass@host/db to share one database between several API "
                    "processes and workers on several hosts. Create accounts with `mapfree admin create-user`.")
    p.add_argument("--db", default=os.environ.get("MAPFREE_DB", "sqlite:///mapfree.db"),
                   help="database URL: sqlite:///path.db (default) or postgresql://user:pass@host:5432/db")
    p.add_argument("--data", default=os.environ.get("MAPFREE_DATA"),
                   help="dataset root with the public val/ and test/ splits (scene lists, val ground truth)")
    p.add_argument("--gt", default=os.environ.get("MAPFREE_GT"),
                   help="private ground-truth root for test (GT/test/sNNNNN/poses.txt); never served")
    p.add_argument("--workers", type=int, default=1, help="evaluation worker processes on this host (default 1)")
    p.add_argument("--host", default="127.0.0.1", help="bind address (default 127.0.0.1)")
    p.add_argument("--port", type=int, default=8000, help="port (default 8000)")
    p.add_argument("--api-processes", type=int, default=1, help="uvicorn worker processes for the API")
    p.add_argument("--no-api", action="store_true", help="run only the evaluation workers (scale-out hosts)")
    p.add_argument("--lease-seconds", type=float, default=60.0,
                   help="a job whose worker stops renewing for this long is retried (default 60)")
    p.add_argument("--test-daily-limit", type=int, default=5, help="test evaluations per account per 24 h")
    p.add_argument("--max-upload-mb", type=float, default=50.0, help="largest submission ZIP (default 50 MB)")
    p.add_argument("--method", default="", help="default relocalization method of new anchors")
    p.add_argument("--secure-cookies", action="store_true", help="mark cookies Secure (behind HTTPS)")
    p.add_argument("--log-level", default="info")
    p.set_defaults(func=run)


def settings_from_args(a: argparse.Namespace):
    from ..service.config import Limits, Settings

    limits = Limits(max_submission_bytes=int(a.max_upload_mb * (1 << 20)))
    limits.max_request_bytes = max(limits.max_request_bytes, limits.max_submission_bytes + (1 << 20))
    return Settings(db_url=a.db, data_root=a.data, gt_root=a.gt, test_daily_limit=a.test_daily_limit,
                    lease_seconds=a.lease_seconds, default_method=a.method, secure_cookies=a.secure_cookies,
                    limits=limits)


def worker_command(a: argparse.Namespace) -> list[str]:
    cmd = [sys.executable, "-m", "mapfree.service.worker", "--db", a.db, "--lease-seconds", str(a.lease_seconds),
           "--log-level", a.log_level, "--exit-with-parent"]
    if a.data:
        cmd += ["--data", str(a.data)]
    if a.gt:
        cmd += ["--gt", str(a.gt)]
    return cmd


class Supervisor:
    """Keeps ``n`` worker processes alive (a crashed or killed one is replaced) until ``stop()``."""

    def __init__(self, cmd: list[str], n: int):
        self.cmd, self.n, self.procs, self.stopping = cmd, n, [], threading.Event()
        self.thread = threading.Thread(target=self._watch, daemon=True)

    def start(self) -> None:
        self.procs = [subprocess.Popen(self.cmd) for _ in range(self.n)]
        log.info("workers started", extra={"pids": [p.pid for p in self.procs]})
        self.thread.start()

    def _watch(self) -> None:
        while not self.stopping.wait(1.0):
            for i, p in enumerate(self.procs):
                if p.poll() is not None and not self.stopping.is_set():
                    log.warning("worker exited; restarting", extra={"pid": p.pid, "code": p.returncode})
                    self.procs[i] = subprocess.Popen(self.cmd)

    def stop(self, timeout: float = 15.0) -> None:
        self.stopping.set()
        for p in self.procs:
            if p.poll() is None:
                p.send_signal(signal.SIGTERM)
        deadline = time.time() + timeout
        for p in self.procs:
            try:
                p.wait(max(0.1, deadline - time.time()))
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()


def run(a: argparse.Namespace) -> int:
    from ..service.db import init_db, make_engine
    from ..service.logs import setup_logging

    setup_logging(a.log_level)
    settings = settings_from_args(a)
    engine = make_engine(settings.db_url)
    init_db(engine)  # once, before several processes race to create tables
    engine.dispose()
    sup = Supervisor(worker_command(a), a.workers) if a.workers > 0 else None
    if sup:
        sup.start()
    try:
        if a.no_api:
            stop = threading.Event()
            signal.signal(signal.SIGTERM, lambda *_: stop.set())
            try:
                stop.wait()
            except KeyboardInterrupt:
                pass
            return 0
        import uvicorn

        log.info("serving", extra={"host": a.host, "port": a.port, "db": settings.db_url.split("://")[0]})
        if a.api_processes > 1:
            os.environ["MAPFREE_SETTINGS"] = json.dumps(dataclasses.asdict(settings), default=str)
            uvicorn.run("mapfree.service.app:app_from_env", factory=True, host=a.host, port=a.port,
                        workers=a.api_processes, log_config=None, access_log=False)
        else:
            from ..service import create_app

            uvicorn.run(create_app(settings), host=a.host, port=a.port, log_config=None, access_log=False)
        return 0
    finally:
        if sup:
            sup.stop()


def main(argv: list[str] | None = None) -> int:
    """``python -m mapfree.cli.serve`` = ``mapfree serve`` without loading the other subcommands."""
    parser = argparse.ArgumentParser(prog="mapfree")
    register(parser.add_subparsers(dest="command"))
    args = parser.parse_args(["serve", *(sys.argv[1:] if argv is None else argv)])
    return int(args.func(args) or 0)


if __name__ == "__main__":
    raise SystemExit(main())
