"""Schema migrations (Alembic), shipped inside the package so that an installed ``mapfree`` upgrades its
database: ``mapfree serve`` (every API process and worker) upgrades at start, ``mapfree admin migrate`` on
demand. The version lives in the database's ``alembic_version`` table.

Three kinds of database meet ``upgrade``: an empty one (every table made from the models, stamped with the
newest version: the migrations' result, in one step), one from before migrations (no version table: revision
0001 adds the tables it may lack, then the later ones run), and a versioned one (the missing revisions run).
The whole upgrade is one transaction under a lock (SQLite: its write lock; PostgreSQL: an advisory lock), so that
processes starting together upgrade once.
"""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path
from typing import TYPE_CHECKING

from sqlalchemy import inspect, text
from sqlalchemy.engine import Connection, Engine

if TYPE_CHECKING:
    from alembic.config import Config

__all__ = ["upgrade", "current", "head", "add_missing", "SchemaVersion"]

_LOCK_KEY = 0x6D617066  # PostgreSQL advisory lock id of migrations ("mapf")


@lru_cache(maxsize=1)
def _config() -> Config:
    from alembic.config import Config

    cfg = Config()
    cfg.set_main_option("script_location", str(Path(__file__).parent))
    return cfg


@lru_cache(maxsize=1)
def head() -> str:
    """The newest revision this code knows."""
    from alembic.script import ScriptDirectory

    newest = ScriptDirectory.from_config(_config()).get_current_head()
    if newest is None:  # the versions folder is missing from the installation
        raise RuntimeError(f"no schema migrations in {Path(__file__).parent / 'versions'}: reinstall mapfree")
    return newest


def _current(conn: Connection) -> str | None:
    from alembic.runtime.migration import MigrationContext

    return MigrationContext.configure(conn).get_current_revision()


def current(engine: Engine) -> str | None:
    """The database's revision (None: not versioned, i.e. empty or from before migrations)."""
    with engine.connect() as conn:
        rev = _current(conn)
        conn.rollback()
    return rev


def add_missing(table: str, *columns) -> None:
    """Inside a migration: add those of ``columns`` that ``table`` lacks (a database whose version table was lost
    may have some already)."""
    from alembic import op

    have = {c["name"] for c in inspect(op.get_bind()).get_columns(table)}
    todo = [c for c in columns if c.name not in have]
    if todo:
        with op.batch_alter_table(table) as t:
            for c in todo:
                t.add_column(c)


class SchemaVersion(RuntimeError):
    """The database is newer than this code (it was upgraded by a later release)."""


def upgrade(engine: Engine) -> tuple[str | None, str]:
    """Bring the database to ``head()``; returns (revision before, after). Idempotent and safe to run from
    several processes at once."""
    from alembic import command
    from alembic.script import ScriptDirectory

    from ..models import Base

    with engine.begin() as conn:  # SQLite: BEGIN IMMEDIATE, the write lock
        if conn.dialect.name == "postgresql":
            conn.execute(text("SELECT pg_advisory_xact_lock(:k)"), {"k": _LOCK_KEY})
        before = _current(conn)
        if before == head():
            return before, before
        if before is not None and before not in {
            s.revision for s in ScriptDirectory.from_config(_config()).walk_revisions()
        }:
            raise SchemaVersion(
                f"the database is at schema version {before}, which this mapfree does not know "
                f"(its newest is {head()}): it was upgraded by a newer release; run that one"
            )
        cfg = _config()
        cfg.attributes["connection"] = conn
        if before is None and not inspect(conn).get_table_names():
            Base.metadata.create_all(conn)  # an empty database: the models are the newest schema
            command.stamp(cfg, "head")
        else:
            command.upgrade(cfg, "head")
        return before, head()
