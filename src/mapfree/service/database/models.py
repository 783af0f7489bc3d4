"""Database schema (SQLAlchemy 2) and engine setup for SQLite (default) and PostgreSQL.

Everything the service keeps lives here, blobs included, so API and worker processes on several hosts share
one PostgreSQL database and nothing else. Timestamps are UNIX seconds (floats) to compare the same everywhere.
"""

from __future__ import annotations

import os
import sqlite3
import threading
import time
import uuid
from typing import Any, cast

from sqlalchemy import (
    JSON,
    Boolean,
    Float,
    ForeignKey,
    Integer,
    LargeBinary,
    String,
    Text,
    UniqueConstraint,
    create_engine,
    event,
    false,
)
from sqlalchemy.engine import Connection, CursorResult, Engine, make_url
from sqlalchemy.engine import Result as Rows
from sqlalchemy.exc import OperationalError
from sqlalchemy.orm import DeclarativeBase, Mapped, mapped_column, sessionmaker


def now() -> float:
    return time.time()


def new_id() -> str:
    return uuid.uuid4().hex


def changed_rows(result: Rows[Any]) -> int:
    """How many rows an UPDATE or DELETE run through a ``Session`` changed. The session returns a ``CursorResult``
    for those statements, which its signature types as a plain ``Result``."""
    return cast("CursorResult[Any]", result).rowcount


class Base(DeclarativeBase):
    pass


class User(Base):
    __tablename__ = "users"
    id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=True)
    name: Mapped[str] = mapped_column(String(64), unique=True)
    is_admin: Mapped[bool] = mapped_column(Boolean, default=False)
    test_daily_limit: Mapped[int | None] = mapped_column(Integer, nullable=True)  # None: the server default
    created_at: Mapped[float] = mapped_column(Float, default=now)


class ApiToken(Base):
    """Only the SHA-256 of a token is stored; ``prefix`` (not secret) lets an admin tell tokens apart."""

    __tablename__ = "api_tokens"
    id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=True)
    user_id: Mapped[int] = mapped_column(ForeignKey("users.id", ondelete="CASCADE"), index=True)
    token_hash: Mapped[str] = mapped_column(String(64), unique=True)
    prefix: Mapped[str] = mapped_column(String(16))
    revoked: Mapped[bool] = mapped_column(Boolean, default=False)
    created_at: Mapped[float] = mapped_column(Float, default=now)
    expires_at: Mapped[float | None] = mapped_column(Float, nullable=True)  # None: never (schema 0002)
    label: Mapped[str] = mapped_column(String(64), default="", server_default="")  # what it is for (0002)
    #: The token it was created with (None: issued by an admin); revoking that one revokes this (0004).
    parent_id: Mapped[int | None] = mapped_column(Integer, nullable=True)


class WebSession(Base):
    __tablename__ = "web_sessions"
    id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=True)
    sid_hash: Mapped[str] = mapped_column(String(64), unique=True)
    user_id: Mapped[int] = mapped_column(ForeignKey("users.id", ondelete="CASCADE"), index=True)
    csrf: Mapped[str] = mapped_column(String(64))
    expires_at: Mapped[float] = mapped_column(Float)
    created_at: Mapped[float | None] = mapped_column(Float, nullable=True, default=now)  # schema 0002
    #: The token it was signed in with; the session ends when that token is revoked (0004).
    token_id: Mapped[int | None] = mapped_column(Integer, nullable=True)


class Submission(Base):
    """A job: stored (with its ZIP) and committed before the upload is acknowledged."""

    __tablename__ = "submissions"
    id: Mapped[str] = mapped_column(String(32), primary_key=True, default=new_id)
    user_id: Mapped[int] = mapped_column(ForeignKey("users.id", ondelete="CASCADE"), index=True)
    split: Mapped[str] = mapped_column(String(16), index=True)
    name: Mapped[str] = mapped_column(String(128))
    public: Mapped[bool] = mapped_column(Boolean, default=False)
    status: Mapped[str] = mapped_column(String(16), index=True, default="queued")  # queued|running|done|failed
    attempts: Mapped[int] = mapped_column(Integer, default=0)
    worker_id: Mapped[str | None] = mapped_column(String(64), nullable=True)
    lease_until: Mapped[float | None] = mapped_column(Float, nullable=True)
    error: Mapped[str | None] = mapped_column(Text, nullable=True)
    size_bytes: Mapped[int] = mapped_column(Integer, default=0)
    sha256: Mapped[str] = mapped_column(String(64))
    created_at: Mapped[float] = mapped_column(Float, default=now, index=True)
    started_at: Mapped[float | None] = mapped_column(Float, nullable=True)
    finished_at: Mapped[float | None] = mapped_column(Float, nullable=True)


class SubmissionFile(Base):
    """A stored ZIP: its first chunk here, the rest (if any) in ``zip_chunks``; deleting this row deletes them."""

    __tablename__ = "submission_files"
    submission_id: Mapped[str] = mapped_column(ForeignKey("submissions.id", ondelete="CASCADE"), primary_key=True)
    data: Mapped[bytes] = mapped_column(LargeBinary)


class ZipChunk(Base):
    """Chunk ``seq`` (1, 2, ...) of a stored ZIP, so that uploads and workers stream it with bounded memory."""

    __tablename__ = "zip_chunks"
    submission_id: Mapped[str] = mapped_column(
        ForeignKey("submission_files.submission_id", ondelete="CASCADE"), primary_key=True
    )
    seq: Mapped[int] = mapped_column(Integer, primary_key=True)
    data: Mapped[bytes] = mapped_column(LargeBinary)


class Result(Base):
    """One row per submission at most (primary key): a result is written once."""

    __tablename__ = "results"
    submission_id: Mapped[str] = mapped_column(ForeignKey("submissions.id", ondelete="CASCADE"), primary_key=True)
    metrics: Mapped[dict] = mapped_column(JSON)
    per_scene: Mapped[dict | None] = mapped_column(JSON, nullable=True)  # always None for test
    problems: Mapped[list] = mapped_column(JSON, default=list)
    plot_data: Mapped[bytes | None] = mapped_column(
        LargeBinary, nullable=True, deferred=True
    )  # packed report; never for test
    worker_id: Mapped[str] = mapped_column(String(64))
    attempt: Mapped[int] = mapped_column(Integer)
    eval_seconds: Mapped[float] = mapped_column(Float)
    created_at: Mapped[float] = mapped_column(Float, default=now)


class MethodInfo(Base):
    """What a submission's author says about the method (shown on the leaderboard); a table of its own so that
    existing databases gain it with ``create_all``."""

    __tablename__ = "method_info"
    submission_id: Mapped[str] = mapped_column(ForeignKey("submissions.id", ondelete="CASCADE"), primary_key=True)
    description: Mapped[str] = mapped_column(Text, default="")
    paper_url: Mapped[str] = mapped_column(String(500), default="")
    code_url: Mapped[str] = mapped_column(String(500), default="")
    runtime_ms: Mapped[float | None] = mapped_column(Float, nullable=True)  # per query, as the author measured it
    extra_data: Mapped[bool] = mapped_column(Boolean, default=False)  # trained/tuned on data beyond the train split


class Plot(Base):
    __tablename__ = "plots"
    __table_args__ = (UniqueConstraint("submission_id", "name"),)
    id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=True)
    submission_id: Mapped[str] = mapped_column(ForeignKey("submissions.id", ondelete="CASCADE"), index=True)
    name: Mapped[str] = mapped_column(String(64))
    png: Mapped[bytes] = mapped_column(LargeBinary)


class Anchor(Base):
    """A reference photo (with intrinsics and optional metric depth) that anyone signed in can localize against."""

    __tablename__ = "anchors"
    id: Mapped[str] = mapped_column(String(32), primary_key=True, default=new_id)
    user_id: Mapped[int] = mapped_column(ForeignKey("users.id", ondelete="CASCADE"), index=True)
    name: Mapped[str] = mapped_column(String(128), default="")
    method: Mapped[str] = mapped_column(String(64))
    intrinsics: Mapped[dict] = mapped_column(JSON)
    image: Mapped[bytes] = mapped_column(LargeBinary)
    depth: Mapped[bytes | None] = mapped_column(LargeBinary, nullable=True)
    created_at: Mapped[float] = mapped_column(Float, default=now)
    #: Only the owner (and admins) see it, its photos and localize against it (schema 0003).
    private: Mapped[bool] = mapped_column(Boolean, default=False, server_default=false())
    #: Uploaded calibrations, ``[{"name": file name, "file": calibration JSON}]``; None: the method's shipped ones
    #: (``anchors.calibration``; schema 0005).
    calibration: Mapped[list | None] = mapped_column(JSON, nullable=True)
    #: Answers say ``accepted`` when ``p_correct`` is at least this (None: no threshold; schema 0005).
    accept: Mapped[float | None] = mapped_column(Float, nullable=True)


class AnchorPhoto(Base):
    """A further photo of an anchor's place (the anchor row holds the first one, whose camera is the anchor's
    frame): its own intrinsics and optional depth, and ``pose`` = world-to-camera from the anchor's frame as
    ``[qw, qx, qy, qz, tx, ty, tz]`` (metres). A table of its own so that existing databases gain it with
    ``create_all``. ``seq`` is the photo's index for life: deleting one leaves a gap, an index is never given
    again (``RetiredPhotoIndex``), and the photos' indices and creation times identify an anchor's version
    (``anchors.domain.anchor_version``)."""

    __tablename__ = "anchor_photos"
    anchor_id: Mapped[str] = mapped_column(ForeignKey("anchors.id", ondelete="CASCADE"), primary_key=True)
    seq: Mapped[int] = mapped_column(Integer, primary_key=True)  # 1, 2, ... (photo 0 is the anchor row's)
    intrinsics: Mapped[dict] = mapped_column(JSON)
    pose: Mapped[list] = mapped_column(JSON)
    image: Mapped[bytes] = mapped_column(LargeBinary)
    depth: Mapped[bytes | None] = mapped_column(LargeBinary, nullable=True)
    created_at: Mapped[float] = mapped_column(Float, default=now)


class RetiredPhotoIndex(Base):
    """The highest index among an anchor's deleted photos, so that a photo added later never reuses it (a client
    that remembered "photo 2" must not get another photo). A table of its own so that existing databases gain
    it with ``create_all``; an anchor without a row has had none of its highest photos deleted since then."""

    __tablename__ = "anchor_retired_indices"
    anchor_id: Mapped[str] = mapped_column(ForeignKey("anchors.id", ondelete="CASCADE"), primary_key=True)
    highest: Mapped[int] = mapped_column(Integer)


class WorkerRow(Base):
    __tablename__ = "workers"
    id: Mapped[str] = mapped_column(String(64), primary_key=True)
    host: Mapped[str] = mapped_column(String(128))
    pid: Mapped[int] = mapped_column(Integer)
    started_at: Mapped[float] = mapped_column(Float, default=now)
    last_seen: Mapped[float] = mapped_column(Float, default=now)
    jobs_done: Mapped[int] = mapped_column(Integer, default=0)


def normalize_url(url: str) -> str:
    """Accept ``postgresql://`` and plain paths; PostgreSQL goes through psycopg 3."""
    if "://" not in url:
        return f"sqlite:///{url}"
    if url.startswith("postgres://"):
        url = "postgresql://" + url[len("postgres://") :]
    if url.startswith("postgresql://"):
        url = "postgresql+psycopg://" + url[len("postgresql://") :]
    return url


def is_sqlite(engine: Engine) -> bool:
    return engine.dialect.name == "sqlite"


def _private_file(path: str | None) -> None:
    """Create a new SQLite file readable by its owner only (0600; SQLite gives its -wal and -shm files the same
    mode): it holds token hashes, sessions and the private test results."""
    if not path or path == ":memory:" or path.startswith("file:") or os.path.exists(path):
        return
    os.close(os.open(path, os.O_CREAT | os.O_WRONLY, 0o600))


#: Execution option of a connection that only reads (``/health``): on SQLite its transactions do not take the
#: write lock, so a health check never waits behind an upload's inserts.
READ_ONLY = "mapfree_read_only"


def _wal(cur: Any, wait_s: float = 30.0) -> None:
    """Put a SQLite database in WAL mode (once: the mode is stored in the file). The switch takes the exclusive
    lock and SQLite answers "database is locked" at once, without its busy wait, while another connection holds
    the file (processes starting together on an old database): retried until ``wait_s`` has passed."""
    deadline = time.monotonic() + wait_s
    while True:
        try:
            if str(cur.execute("PRAGMA journal_mode").fetchone()[0]).lower() != "wal":
                cur.execute("PRAGMA journal_mode=WAL")
            return
        except sqlite3.OperationalError as e:
            if "locked" not in str(e) or time.monotonic() > deadline:
                raise
            time.sleep(0.05)


#: Seconds a SQLite write transaction waits for this process's earlier ones before the request gets a 503.
WRITE_WAIT_S = 30.0
#: Connections of a SQLite engine: one for every thread that may hold one at once (the shared pool's 40, the
#: heavy threads, health and metrics), so that a burst queues for the write lock, never for a connection.
SQLITE_POOL = 64
#: Threads of one process that may wait for the write turn at once; past that a write is refused at once (503
#: with Retry-After). A transaction still open when its endpoint returns ends on another thread of the shared
#: pool (40; 8 stay free): were every one of them waiting for the turn it holds, nothing would move until their
#: timeouts.
WRITE_WAITERS = 32
_WRITE_HELD = "mapfree_write_lock"


def _sqlite_writes_in_turn(engine: Engine) -> None:
    """Serialize this process's SQLite write transactions on a lock of its own, in Python, before ``BEGIN
    IMMEDIATE``: waiting in SQLite's busy handler (a sleep-and-retry poll, no queue) let ~60 concurrent light
    writes stall each other and every other connection for 30 s and fail with "database is locked". Other
    processes on the same file still meet at SQLite's lock. Read-only transactions (``READ_ONLY``) take neither.
    The lock is released when the transaction ends (commit, rollback, or the connection going back to the pool);
    at most ``WRITE_WAITERS`` threads wait for it, a write past them is refused at once (``unavailable``: 503)."""
    lock = threading.Lock()
    waiting = threading.BoundedSemaphore(WRITE_WAITERS)

    def release(info: dict) -> None:
        if info.pop(_WRITE_HELD, False):
            lock.release()

    @event.listens_for(engine, "begin")
    def _begin(conn: Connection) -> None:  # pragma: no cover - driver hook
        # a connection marked read-only reads a WAL snapshot without queueing for the write lock
        if conn.get_execution_options().get(READ_ONLY):
            conn.exec_driver_sql("BEGIN")
            return
        if not waiting.acquire(blocking=False):  # the threads of the pool stay free to end transactions
            raise OperationalError(
                "BEGIN IMMEDIATE", None, sqlite3.OperationalError(f"database busy: {WRITE_WAITERS} writes waiting")
            )
        try:
            turn = lock.acquire(timeout=WRITE_WAIT_S)
        finally:
            waiting.release()
        if not turn:
            raise OperationalError(
                "BEGIN IMMEDIATE", None, sqlite3.OperationalError(f"database busy: no write turn in {WRITE_WAIT_S} s")
            )
        conn.info[_WRITE_HELD] = True
        try:
            conn.exec_driver_sql("BEGIN IMMEDIATE")
        except BaseException:
            release(conn.info)
            raise

    @event.listens_for(engine, "commit")
    def _commit(conn: Connection) -> None:  # pragma: no cover - driver hook
        release(conn.info)

    @event.listens_for(engine, "rollback")
    def _rollback(conn: Connection) -> None:  # pragma: no cover - driver hook
        release(conn.info)

    @event.listens_for(engine, "checkin")
    def _checkin(dbapi_conn: Any, record: Any) -> None:  # pragma: no cover - pool hook
        release(record.info)


def make_engine(url: str) -> Engine:
    """An engine; on SQLite every transaction is ``BEGIN IMMEDIATE`` (one writer at a time: this process's in
    turn, others' waiting up to 30 s) but those of ``READ_ONLY`` connections, in WAL mode so that readers are not
    blocked; one pooled connection per thread that may use one."""
    url = normalize_url(url)
    if make_url(url).get_backend_name() == "sqlite":
        _private_file(make_url(url).database)
        engine = create_engine(
            url,
            connect_args={"timeout": 30, "check_same_thread": False},
            pool_size=8,
            max_overflow=SQLITE_POOL - 8,
        )

        @event.listens_for(engine, "connect")
        def _connect(dbapi_conn: Any, _record: Any) -> None:  # pragma: no cover - driver hook
            dbapi_conn.isolation_level = None  # let us issue BEGIN ourselves
            cur = dbapi_conn.cursor()
            cur.execute("PRAGMA busy_timeout=30000")
            _wal(cur)
            cur.execute("PRAGMA foreign_keys=ON")
            cur.close()

        _sqlite_writes_in_turn(engine)
        return engine
    return create_engine(url, pool_pre_ping=True, pool_size=10, max_overflow=10)


class DatabaseUnavailable(RuntimeError):
    """The database URL is malformed, names a driver that is not installed, or the database cannot be reached
    or opened; the message says which in one line, without the password."""


#: Seconds a client is told to wait (``Retry-After``) when the database is down or busy.
RETRY_AFTER_S = 5


def unavailable(exc: BaseException) -> bool:
    """Whether ``exc`` says the database is down or busy, not that a request is wrong: it could not be reached
    (PostgreSQL stopped, a connection cut), it is locked past the wait (SQLite), or every pooled connection
    stayed in use past the pool's timeout. Such a request is answered 503 with ``Retry-After``, not 500."""
    from sqlalchemy import exc as sa

    return isinstance(exc, (sa.OperationalError, sa.TimeoutError)) or (
        isinstance(exc, sa.DBAPIError) and exc.connection_invalidated
    )


def shown_url(url: str) -> str:
    """A database URL as it may be printed: without its password."""
    try:
        return make_url(normalize_url(url)).render_as_string(hide_password=True)
    except Exception:  # malformed: show only its scheme
        return url.split("://", 1)[0] + "://…"


def open_database(url: str) -> tuple[Engine, tuple[str | None, str]]:
    """An engine on ``url`` with the schema brought to this code's version -> (engine, (revision before,
    after)); ``DatabaseUnavailable`` in one line for a malformed URL, a missing driver or a database that
    cannot be reached (``mapfree serve`` and ``mapfree admin`` print it instead of a traceback)."""
    from sqlalchemy.exc import ArgumentError, NoSuchModuleError, SQLAlchemyError

    from .migrations import upgrade

    try:
        engine = make_engine(url)
    except (ArgumentError, NoSuchModuleError, ValueError) as e:
        raise DatabaseUnavailable(
            f"not a database URL this server can use: {shown_url(url)} "
            f"({str(e).splitlines()[0][:200]}); expected sqlite:///PATH or "
            "postgresql://USER:PASSWORD@HOST:PORT/NAME"
        ) from None
    except (ImportError, OSError) as e:
        raise DatabaseUnavailable(
            f"cannot open the database {shown_url(url)}: {str(e).splitlines()[0][:200]}"
        ) from None
    try:
        return engine, upgrade(engine)
    except SQLAlchemyError as e:
        engine.dispose()
        reason = str(getattr(e, "orig", None) or e).strip().splitlines()[0][:300]
        raise DatabaseUnavailable(f"cannot open the database {shown_url(url)}: {reason}") from None


def init_db(engine: Engine) -> None:
    """Create the tables or upgrade them to this code's schema version (``migrations.upgrade``; idempotent and
    safe to run from several processes at once)."""
    from .migrations import upgrade

    upgrade(engine)


def session_factory(engine: Engine, read_only: bool = False) -> sessionmaker:
    """Sessions of ``engine``; ``read_only``: for requests that only read (on SQLite their transactions take no
    write lock, so they are answered during a burst of writes; a write in one is refused by SQLite's snapshot
    rules, so use them only where no write follows)."""
    return sessionmaker(engine.execution_options(**{READ_ONLY: True}) if read_only else engine, expire_on_commit=False)
