"""Schema versions (Alembic): a database made before migrations existed upgrades and keeps working; the
migrations and the models describe the same schema; processes starting together upgrade once."""

from __future__ import annotations

import sqlite3
import subprocess
import sys
import threading
from pathlib import Path

import pytest
from fastapi.testclient import TestClient
from sqlalchemy import inspect

from mapfree.service import Settings, create_app
from mapfree.service.database.migrations import SchemaVersion, current, head, upgrade
from mapfree.service.database.models import Base, make_engine

from .conftest import BACKENDS, db_url_for

OLD_SQL = Path(__file__).parent / "data" / "db-before-migrations.sql"


def old_database(path: Path) -> str:
    """The committed database from before migrations, restored into ``path``."""
    con = sqlite3.connect(path)
    con.executescript(OLD_SQL.read_text())
    con.close()
    return f"sqlite:///{path}"


def schema(url: str) -> dict:
    """Every table's columns (type, nullability, default), keys, indexes and unique constraints."""
    engine = make_engine(url)
    insp = inspect(engine)
    out = {}
    for t in insp.get_table_names():
        if t == "alembic_version":
            continue
        out[t] = {
            "columns": {c["name"]: (str(c["type"]), c["nullable"], str(c.get("default"))) for c in insp.get_columns(t)},
            "pk": insp.get_pk_constraint(t)["constrained_columns"],
            "fks": sorted(
                (
                    tuple(f["constrained_columns"]),
                    f["referred_table"],
                    tuple(f["referred_columns"]),
                    f.get("options", {}).get("ondelete"),
                )
                for f in insp.get_foreign_keys(t)
            ),
            "indexes": sorted((i["name"], tuple(i["column_names"]), bool(i["unique"])) for i in insp.get_indexes(t)),
            "unique": sorted(tuple(u["column_names"]) for u in insp.get_unique_constraints(t)),
        }
    engine.dispose()
    return out


def test_the_first_revision_is_the_schema_from_before_migrations(tmp_path):
    from alembic import command

    from mapfree.service.database.migrations import _config

    old = schema(old_database(tmp_path / "old.db"))
    engine = make_engine(f"sqlite:///{tmp_path / 'first.db'}")
    with engine.begin() as conn:
        cfg = _config()
        cfg.attributes["connection"] = conn
        command.upgrade(cfg, "0001")
    engine.dispose()
    assert schema(f"sqlite:///{tmp_path / 'first.db'}") == old


def test_an_old_database_upgrades_to_the_models_schema_and_keeps_working(tmp_path):
    url = old_database(tmp_path / "old.db")
    engine = make_engine(url)
    assert current(engine) is None
    assert upgrade(engine) == (None, head())
    assert current(engine) == head() and upgrade(engine) == (head(), head())  # once only
    engine.dispose()
    fresh = make_engine(f"sqlite:///{tmp_path / 'fresh.db'}")
    Base.metadata.create_all(fresh)
    fresh.dispose()
    assert schema(url) == schema(f"sqlite:///{tmp_path / 'fresh.db'}")

    c = TestClient(create_app(Settings(db_url=url)), raise_server_exceptions=False)
    user, admin = ({"Authorization": "Bearer mf_old-user-token"}, {"Authorization": "Bearer mf_old-admin-token"})
    assert c.get("/api/me", headers=user).json()["name"] == "olduser"
    anchor = c.get("/anchors/" + "b" * 32, headers=user).json()
    assert anchor["name"] == "old anchor" and anchor["has_depth"], anchor
    assert c.get("/anchors/" + "b" * 32 + "/photos/0", headers=user).content.startswith(b"\x89PNG")
    sub = c.get("/api/submissions/" + "a" * 32, headers=user).json()
    assert sub["status"] == "done" and sub["metrics"]["Average Median Translation Error"] == 1.5
    assert c.get("/health/detail", headers=admin).status_code == 200
    c.close()


def test_a_database_newer_than_the_code_is_refused(tmp_path):
    url = f"sqlite:///{tmp_path / 'new.db'}"
    engine = make_engine(url)
    upgrade(engine)
    with engine.begin() as conn:
        conn.exec_driver_sql("UPDATE alembic_version SET version_num = '9999'")
    with pytest.raises(SchemaVersion, match="schema version 9999.*newer release"):
        upgrade(engine)
    engine.dispose()
    r = subprocess.run(
        [sys.executable, "-m", "mapfree.cli.serve", "--db", url, "--workers", "0", "--port", "1"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert r.returncode == 2 and "schema version 9999" in r.stderr and "Traceback" not in r.stderr, r.stderr


def _upgrade_together(url: str, n: int) -> tuple[list, list]:
    """``upgrade`` of the database at ``url`` from ``n`` threads at once, each with its own engine (as processes
    starting together) -> what each returned, and the errors raised."""
    results, errors = [], []

    def start():
        engine = make_engine(url)
        try:
            results.append(upgrade(engine))
        except Exception as e:  # pragma: no cover - the callers' assertions show it
            errors.append(e)
        engine.dispose()

    threads = [threading.Thread(target=start) for _ in range(n)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(60)
    return results, errors


def test_processes_starting_together_upgrade_once(tmp_path):
    url = old_database(tmp_path / "old.db")
    results, errors = _upgrade_together(url, 4)
    assert not errors, errors
    assert sorted(results, key=str) == sorted([(None, head())] + [(head(), head())] * 3, key=str)


def test_processes_opening_an_old_database_together_never_fail(tmp_path):
    """The first connection to an old database switches it to WAL, which needs the file to itself; where that
    meets another connection's commit, SQLite answers "database is locked" at once, without its busy wait, and
    about one start in 40 of four processes together failed so. 100 such starts (a few seconds): none fails."""
    for i in range(100):
        url = old_database(tmp_path / f"old{i}.db")
        results, errors = _upgrade_together(url, 4)
        assert not errors, (i, errors)
        assert len(results) == 4


@pytest.mark.parametrize("backend", BACKENDS)
def test_upgrading_from_the_first_revision_gives_the_models_schema_on_each_backend(backend, tmp_path):
    """The first revision's tables with a user in them, upgraded by processes starting together (once, under the
    backend's lock), end as the models' schema, the rows kept."""
    from alembic import command
    from sqlalchemy import text

    from mapfree.service.database.migrations import _config

    old, new = db_url_for(backend, tmp_path), db_url_for(backend, tmp_path)
    engine = make_engine(old)
    with engine.begin() as conn:
        cfg = _config()
        cfg.attributes["connection"] = conn
        command.upgrade(cfg, "0001")
        conn.execute(text("INSERT INTO users (name, is_admin, created_at) VALUES ('old', false, 1.0)"))
        conn.execute(text("DROP TABLE alembic_version"))  # as a database from before migrations has none
    engine.dispose()
    results, _ = _upgrade_together(old, 3)
    assert sorted(results, key=str) == sorted([(None, head())] + [(head(), head())] * 2, key=str)
    fresh = make_engine(new)
    upgrade(fresh)  # empty: made from the models, stamped
    fresh.dispose()
    assert schema(old) == schema(new)
    engine = make_engine(old)
    with engine.connect() as conn:
        assert conn.execute(text("SELECT name FROM users")).scalar_one() == "old"
    engine.dispose()
