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

from . import HelpFormatter

log = logging.getLogger("mapfree.serve")


def _daily_limit(text: str) -> int:
    from ..service.config import parse_daily_limit

    try:
        return parse_daily_limit(text)
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e)) from None


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "serve",
        help="run the evaluation server + relocalization API (FastAPI) with evaluation workers",
        description="Serve the benchmark's evaluation server and the relocalization API. SQLite by default; "
        "pass --db postgresql://user:pass@host/db to share one database between several API "
        "processes and workers on several hosts. Create accounts with `mapfree admin create-user`.",
        epilog="examples:\n"
        "  mapfree admin --db sqlite:///mapfree.db create-user alice   # prints alice's API token once\n"
        "  mapfree serve --db sqlite:///mapfree.db --data data/mapfree --gt private_gt --workers 2 --port 8000\n"
        "  mapfree serve --db postgresql+psycopg://u:p@dbhost/mapfree --api-processes 4 --workers 0\n"
        "  mapfree serve --db postgresql+psycopg://u:p@dbhost/mapfree --no-api --workers 8 --data … --gt …\n",
        formatter_class=HelpFormatter,
    )
    p.add_argument(
        "--db",
        default=os.environ.get("MAPFREE_DB", "sqlite:///mapfree.db"),
        help="database URL: sqlite:///path.db (default) or postgresql://user:pass@host:5432/db",
    )
    p.add_argument(
        "--data",
        default=os.environ.get("MAPFREE_DATA"),
        help="dataset root with the public val/ and test/ splits (scene lists, val ground truth; "
        "default: $MAPFREE_DATA)",
    )
    p.add_argument(
        "--gt",
        default=os.environ.get("MAPFREE_GT"),
        help="private ground-truth root for test (GT/test/sNNNNN/poses.txt); never served (default: $MAPFREE_GT)",
    )
    p.add_argument("--workers", type=int, default=1, help="evaluation worker processes on this host (default 1)")
    p.add_argument("--host", default="127.0.0.1", help="bind address (default 127.0.0.1)")
    p.add_argument("--port", type=port_number, default=8000, help="port, 0-65535 (default 8000)")
    p.add_argument("--api-processes", type=int, default=1, help="uvicorn worker processes for the API (default 1)")
    p.add_argument("--no-api", action="store_true", help="run only the evaluation workers (scale-out hosts)")
    p.add_argument(
        "--lease-seconds",
        type=float,
        default=60.0,
        help="a job whose worker stops renewing for this long is retried (default 60)",
    )
    p.add_argument(
        "--test-daily-limit",
        type=_daily_limit,
        default=5,
        metavar="N|unlimited",
        help="test evaluations per account per 24 h (default 5; 0: none at all; 'unlimited': no limit)",
    )
    p.add_argument("--max-upload-mb", type=float, default=50.0, help="largest submission ZIP (default 50 MB)")
    p.add_argument(
        "--max-entry-mb", type=float, default=64.0, help="largest pose file inside a ZIP, uncompressed (default 64 MiB)"
    )
    p.add_argument(
        "--max-unpacked-mb",
        type=float,
        default=256.0,
        help="all pose files of a ZIP together, uncompressed (default 256 MiB)",
    )
    p.add_argument(
        "--val-hourly-limit",
        type=int,
        default=30,
        help="val submissions per account per hour (default 30; 0: unlimited)",
    )
    p.add_argument(
        "--storage-quota-mb",
        type=float,
        default=1024.0,
        help="stored submission ZIPs and anchor photos (images + depth maps) per account (default 1024 MiB; 0: unlimited)",
    )
    p.add_argument(
        "--zip-retention-days",
        type=float,
        default=90.0,
        help="delete stored ZIPs of finished submissions after this many days (default 90; 0: keep)",
    )
    p.add_argument(
        "--auth-failures-per-minute",
        type=int,
        default=20,
        help="failed token checks per client address and minute before a 429 (default 20; 0: off)",
    )
    p.add_argument(
        "--methods-dir",
        default=os.environ.get("MAPFREE_SERVICE_METHODS"),
        help="folder of method YAMLs that clients may name (by file name, never by path; "
        "default: $MAPFREE_SERVICE_METHODS)",
    )
    p.add_argument(
        "--method", default="", help="relocalization method of new anchors that name none (default: best-offline)"
    )
    p.add_argument("--secure-cookies", action="store_true", help="mark cookies Secure (behind HTTPS)")
    g = p.add_argument_group("memory and concurrency of the relocalization API (per API process)")
    g.add_argument(
        "--work-max-side",
        type=int,
        default=1024,
        help="photos are downscaled to this long side before a method runs (default 1024; 0: never)",
    )
    g.add_argument(
        "--heavy-threads",
        type=int,
        default=0,
        help="localize / anchor computations at once (default 0: one per CPU, at most 4)",
    )
    g.add_argument(
        "--heavy-queue",
        type=int,
        default=8,
        help="such requests waiting for a thread; more get 429 with Retry-After (default 8)",
    )
    g.add_argument(
        "--method-threads",
        type=int,
        default=0,
        help="threads of one localize / anchor computation (OpenCV, torch, BLAS), whatever OMP_NUM_THREADS "
        "says (default 0: the CPUs divided among the heavy threads, at least 1)",
    )
    g.add_argument(
        "--anchor-cache-mb",
        type=float,
        default=256.0,
        help="prepared anchors (features, depth at the working size) kept in memory (default 256 MiB)",
    )
    g.add_argument(
        "--method-pool-mb",
        type=float,
        default=1024.0,
        help="built relocalizers (their models) kept in memory, least recently used dropped first (default 1024 MiB)",
    )
    g = p.add_argument_group("connections (uvicorn)")
    g.add_argument(
        "--forwarded-allow-ips",
        default="",
        help="comma-separated addresses of trusted reverse proxies whose X-Forwarded-For/-Proto are "
        "believed ('*': any); default: none, the client address is the TCP peer's",
    )
    g.add_argument(
        "--timeout-keep-alive",
        type=float,
        default=5.0,
        help="close a connection idle this long between requests (default 5 s)",
    )
    g.add_argument(
        "--header-timeout",
        type=float,
        default=10.0,
        help="close a connection whose request line and headers take longer (default 10 s; 0: off)",
    )
    g.add_argument(
        "--body-timeout",
        type=float,
        default=30.0,
        help="answer 408 when the next piece of a request body takes longer (default 30 s; 0: off)",
    )
    g.add_argument(
        "--body-total-timeout",
        type=float,
        default=600.0,
        help="answer 408 when a whole request body takes longer (default 600 s: 64 MiB at 1 Mbit/s; 0: off)",
    )
    g.add_argument(
        "--max-connections-per-address",
        type=int,
        default=64,
        help="open connections one client address may hold per API process; more are closed at once "
        "(default 64; 0: no cap; the --forwarded-allow-ips proxies have none)",
    )
    g.add_argument(
        "--limit-concurrency",
        type=int,
        default=1000,
        help="connections per API process before new requests get 503 (default 1000; 0: no limit)",
    )
    g.add_argument(
        "--h11-max-incomplete-event-size",
        type=int,
        default=16 * 1024,
        help="largest request line + headers in bytes (default 16 KiB)",
    )
    p.add_argument("--log-level", default="info", help="debug, info, warning or error (default: info)")
    p.set_defaults(func=run)


def settings_from_args(a: argparse.Namespace):
    from ..service.config import Limits, Settings

    mb = 1 << 20
    limits = Limits(
        max_submission_bytes=int(a.max_upload_mb * mb),
        max_zip_entry_bytes=int(a.max_entry_mb * mb),
        max_zip_uncompressed_bytes=int(a.max_unpacked_mb * mb),
        work_max_side=a.work_max_side,
    )
    limits.max_request_bytes = max(limits.max_request_bytes, limits.max_submission_bytes + mb)
    return Settings(
        db_url=a.db,
        data_root=a.data,
        gt_root=a.gt,
        test_daily_limit=a.test_daily_limit,
        lease_seconds=a.lease_seconds,
        default_method=a.method,
        secure_cookies=a.secure_cookies,
        methods_dir=a.methods_dir,
        val_hourly_limit=a.val_hourly_limit,
        storage_quota_bytes=int(a.storage_quota_mb * mb),
        zip_retention_days=a.zip_retention_days,
        auth_failures_per_minute=a.auth_failures_per_minute,
        heavy_threads=a.heavy_threads,
        heavy_queue=a.heavy_queue,
        method_threads=a.method_threads,
        anchor_cache_mb=a.anchor_cache_mb,
        method_pool_mb=a.method_pool_mb,
        body_timeout=a.body_timeout,
        body_total_timeout=a.body_total_timeout,
        limits=limits,
        operator_token=os.environ.get("MAPFREE_OPERATOR_TOKEN", ""),
    )


def uvicorn_options(a: argparse.Namespace) -> dict:
    """uvicorn's connection settings from the flags: timeouts, concurrency, header size, trusted proxies (none
    unless named: uvicorn would otherwise believe X-Forwarded-For from 127.0.0.1, a per-request new address)."""
    from ..service.http.timeouts import head_timeout_protocol

    return {
        "http": head_timeout_protocol(
            a.header_timeout, a.max_connections_per_address, a.forwarded_allow_ips, a.h11_max_incomplete_event_size
        ),
        "timeout_keep_alive": a.timeout_keep_alive,
        "limit_concurrency": a.limit_concurrency or None,
        "timeout_graceful_shutdown": 10,
        "h11_max_incomplete_event_size": a.h11_max_incomplete_event_size,
        "proxy_headers": bool(a.forwarded_allow_ips),
        "forwarded_allow_ips": a.forwarded_allow_ips or None,
    }


#: Start workers without the working directory on their module path (``-P``; ``-I`` before Python 3.11): a
#: ``concurrent.py`` or any other stdlib-named file where ``mapfree serve`` was started must never run in them.
ISOLATED = "-P" if sys.version_info >= (3, 11) else "-I"


def worker_command(a: argparse.Namespace) -> list[str]:
    limits = dataclasses.asdict(settings_from_args(a).limits)
    cmd = [
        sys.executable,
        ISOLATED,
        "-m",
        "mapfree.service.leaderboard.worker",  # the database URL: worker_env
        "--lease-seconds",
        str(a.lease_seconds),
        "--zip-retention-days",
        str(a.zip_retention_days),
        "--limits",
        json.dumps(limits),
        "--log-level",
        a.log_level,
        "--exit-with-parent",
    ]
    if a.data:
        cmd += ["--data", str(a.data)]
    if a.gt:
        cmd += ["--gt", str(a.gt)]
    return cmd


def worker_env(a: argparse.Namespace) -> dict[str, str]:
    """The workers' environment: the database URL goes there, never on their command line, where ``ps`` would
    show its password to every user of the host (a process's environment is readable by its owner only); and
    this process's pid, which the workers watch (their ``getppid()`` is already another's if it died first)."""
    from ..service.process import PARENT_PID_ENV

    return {**os.environ, "MAPFREE_DB": a.db, PARENT_PID_ENV: str(os.getpid())}


class Supervisor:
    """Keeps ``n`` worker processes alive until ``stop()``. A worker that exits is replaced; one that keeps dying
    soon after its start is replaced after a growing pause (``backoff`` doubling up to ``max_backoff`` s), so a
    broken installation does not spin, and a worker that ran ``stable_s`` seconds starts the count afresh."""

    def __init__(
        self,
        cmd: list[str],
        n: int,
        backoff: float = 1.0,
        max_backoff: float = 60.0,
        stable_s: float = 30.0,
        env: dict[str, str] | None = None,
    ):
        self.cmd, self.n, self.stopping = cmd, n, threading.Event()
        self.procs: list[subprocess.Popen] = []
        self.env = env
        self.backoff, self.max_backoff, self.stable_s = backoff, max_backoff, stable_s
        self.started: list[float] = []
        self.failures: list[int] = []  # consecutive quick deaths per slot
        self.restart_at: list[float] = []
        self.spawned = 0
        self._lock = threading.Lock()  # a restart and stop() one after the other, never interleaved
        self.thread = threading.Thread(target=self._watch, daemon=True)

    def _spawn(self) -> subprocess.Popen:
        """A worker that gets SIGTERM when this process (or the spawning thread) ends, from its first
        instruction on (``process.parent_death_signal``)."""
        from ..service.process import parent_death_signal

        self.spawned += 1
        return subprocess.Popen(self.cmd, env=self.env, preexec_fn=parent_death_signal())

    def start(self) -> None:
        with self._lock:
            self.procs = [self._spawn() for _ in range(self.n)]
        self.started, self.failures, self.restart_at = [time.time()] * self.n, [0] * self.n, [0.0] * self.n
        log.info("workers started", extra={"pids": [p.pid for p in self.procs]})
        self.thread.start()

    def _watch(self) -> None:
        while not self.stopping.wait(0.2):
            for i, p in enumerate(self.procs):
                if p.poll() is None or self.stopping.is_set():
                    continue
                t = time.time()
                if not self.restart_at[i]:  # just noticed: decide when to restart
                    quick = t - self.started[i] < self.stable_s
                    self.failures[i] = self.failures[i] + 1 if quick else 0
                    delay = min(self.max_backoff, self.backoff * 2 ** (self.failures[i] - 1)) if quick else 0.0
                    self.restart_at[i] = t + delay
                    log.warning(
                        "worker exited; restarting", extra={"pid": p.pid, "code": p.returncode, "in_s": round(delay, 1)}
                    )
                if t >= self.restart_at[i]:
                    with self._lock:  # a stop() that came meanwhile finds no worker it did not signal
                        if self.stopping.is_set():
                            return
                        self.procs[i], self.started[i], self.restart_at[i] = self._spawn(), t, 0.0

    def stop(self, timeout: float = 15.0) -> None:
        with self._lock:
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


def port_number(text: str) -> int:
    """``--port``'s type: a TCP port, 0-65535 (argparse answers anything else in one line, exit 2).

    Raises:
        argparse.ArgumentTypeError: Not an integer, or out of range.
    """
    try:
        port = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a port number (0-65535), got {text!r}") from None
    if not 0 <= port <= 65535:
        raise argparse.ArgumentTypeError(f"a port is 0-65535, got {port}")
    return port


def port_problem(host: str, port: int) -> str | None:
    """Why ``host:port`` cannot be served (in use, or not an address of this host), or None."""
    import errno
    import socket

    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)
    except OSError as e:
        return f"--host {host}: {e.strerror or e}"
    family, _, _, _, addr = infos[0]
    with socket.socket(family, socket.SOCK_STREAM) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as uvicorn binds it
        try:
            s.bind(addr)
        except OSError as e:
            if e.errno == errno.EADDRINUSE:
                return (
                    f"port {port} on {host} is in use (another mapfree serve? its server.pid says which); stop "
                    "it or choose another --port"
                )
            return f"cannot listen on {host}:{port}: {e.strerror or e}"
    return None


def check_folders(a: argparse.Namespace) -> str | None:
    """Why ``--data`` or ``--gt`` cannot be used (not a folder), or None."""
    from pathlib import Path

    for flag, value in (("--data", a.data), ("--gt", a.gt)):
        if value and not Path(value).is_dir():
            return f"{flag} {value}: no such folder"
    return None


def run(a: argparse.Namespace) -> int:
    from ..service.database.models import DatabaseUnavailable, open_database
    from ..service.http.logs import setup_logging
    from ..service.leaderboard.scoring import check_ground_truth

    if (problem := check_folders(a)) is not None:
        print(f"mapfree serve: error: {problem}", file=sys.stderr)
        return 2
    if not a.no_api and (problem := port_problem(a.host, a.port)) is not None:
        print(f"mapfree serve: error: {problem}", file=sys.stderr)
        return 1
    settings = settings_from_args(a)
    try:
        check_ground_truth(settings)
    except ValueError as e:
        print(f"mapfree serve: error: {e}", file=sys.stderr)
        return 2
    from ..service.database.migrations import SchemaVersion

    try:  # create the tables or upgrade the schema, once, before the API processes and workers start
        engine, (before, after) = open_database(settings.db_url)
        engine.dispose()
    except SchemaVersion as e:
        print(f"mapfree serve: error: {e}", file=sys.stderr)
        return 2
    except DatabaseUnavailable as e:
        print(f"mapfree serve: error: {e}", file=sys.stderr)
        return 1
    setup_logging(a.log_level)  # JSON lines from here on (the checks above say what is wrong in one line)
    if before != after:
        log.info("database schema upgraded", extra={"from": before or "unversioned", "to": after})
    sup = Supervisor(worker_command(a), a.workers, env=worker_env(a)) if a.workers > 0 else None
    if sup:
        sup.start()
    try:
        if a.no_api:
            from ..service.process import stop_on_signals

            stop = threading.Event()
            stop_on_signals(stop)
            stop.wait()
            return 0
        import uvicorn

        log.info("serving", extra={"host": a.host, "port": a.port, "db": settings.db_url.split("://")[0]})
        conn = uvicorn_options(a)
        if a.api_processes > 1:
            from ..service.process import PARENT_PID_ENV

            os.environ["MAPFREE_SETTINGS"] = json.dumps(dataclasses.asdict(settings), default=str)
            os.environ[PARENT_PID_ENV] = str(os.getpid())  # they end with this process, even on kill -9
            uvicorn.run(
                "mapfree.service.app:app_from_env",
                factory=True,
                host=a.host,
                port=a.port,
                workers=a.api_processes,
                log_config=None,
                access_log=False,
                **conn,
            )
        else:
            from ..service import create_app
            from ..service.http.gc_freeze import freeze_long_lived

            app = create_app(settings)
            freeze_long_lived()
            uvicorn.run(app, host=a.host, port=a.port, log_config=None, access_log=False, **conn)
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
