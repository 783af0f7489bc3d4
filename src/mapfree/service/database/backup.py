"""``mapfree admin backup``: a consistent copy of a live database.

SQLite: the online backup API copies the database page by page while the server keeps running; writers that
come meanwhile make it restart from their pages, so the copy is one moment's state (WAL content included), unlike
copying the file, which can catch a half-written page or miss the ``-wal`` file. PostgreSQL: ``pg_dump`` is the
tool (a consistent snapshot in one transaction); we print the command rather than run a client of unknown
version against the server.
"""

from __future__ import annotations

import os
import sqlite3
from pathlib import Path

from sqlalchemy.engine import make_url

from .models import normalize_url

#: Pages copied per step; between steps the server's writers get the database.
PAGES_PER_STEP = 1024


def backup_sqlite(db_path: str | os.PathLike, dest: str | os.PathLike) -> int:
    """Copy the SQLite database at ``db_path`` into the new file ``dest`` (0600) -> its size in bytes."""
    dest = Path(dest)
    if dest.exists():
        raise FileExistsError(f"{dest} exists; give a new file name (a backup never overwrites)")
    if not Path(db_path).is_file():
        raise FileNotFoundError(f"no SQLite database at {db_path}")
    src = sqlite3.connect(db_path, timeout=30)
    try:
        os.close(os.open(dest, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o600))  # holds tokens' hashes: owner only
        out = sqlite3.connect(dest)
        try:
            src.backup(out, pages=PAGES_PER_STEP)
            ok = out.execute("PRAGMA integrity_check").fetchone()[0]
            if ok != "ok":
                raise RuntimeError(f"the copy failed its integrity check: {ok}")
        finally:
            out.close()
    finally:
        src.close()
    return dest.stat().st_size


def pg_dump_advice(url: str, dest: str) -> str:
    """How to back up a PostgreSQL database with ``pg_dump`` (password from the environment, not the line)."""
    u = make_url(normalize_url(url))
    host = f" -h {u.host}" if u.host else ""
    port = f" -p {u.port}" if u.port else ""
    user = f" -U {u.username}" if u.username else ""
    return (
        f"PostgreSQL: back it up with pg_dump (a consistent snapshot while the server runs):\n"
        f"  PGPASSWORD=... pg_dump{host}{port}{user} -Fc -f {dest} {u.database}\n"
        f"restore into an empty database with:\n"
        f"  pg_restore{host}{port}{user} -d NEWDB {dest}\n"
        f"(use the pg_dump of the server's major version or newer; pass the password via PGPASSWORD or "
        f"~/.pgpass, never on the command line)"
    )


def backup(url: str, dest: str) -> str:
    """Back up the database at ``url`` into ``dest``: done for SQLite (returns a summary), advice for others."""
    u = make_url(normalize_url(url))
    if u.get_backend_name() == "sqlite":
        if not u.database or u.database == ":memory:":
            raise ValueError("an in-memory SQLite database has nothing to back up")
        size = backup_sqlite(u.database, dest)
        return f"backed up {u.database} to {dest} ({size} bytes, consistent, integrity checked)"
    return pg_dump_advice(url, dest)
