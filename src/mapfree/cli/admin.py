"""``mapfree admin``: accounts and API tokens of the evaluation server (run on the server's database)."""

from __future__ import annotations

import argparse
import os
import sys

from . import HelpFormatter, Parser, fail


def _limit(text: str) -> int | None:
    """A daily test limit: a count (0: none), ``unlimited``, or ``default`` (the server's, None)."""
    if text.strip().lower() == "default":
        return None
    from ..service.config import parse_daily_limit

    try:
        return parse_daily_limit(text)
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected a number of evaluations (0: none), 'unlimited' or 'default'; got {str(text)[:40]!r}"
        ) from None


def _row_id(text: str) -> int:
    """A token's or session's id as listed: a number from 0 to 2^31 - 1 (the database's integer)."""
    from ..service.accounts.caller import MAX_ROW_ID

    try:
        n = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not an id: {text[:40]!r}") from None
    if not 0 <= n <= MAX_ROW_ID:
        raise argparse.ArgumentTypeError(f"no such id: {text[:40]} (ids run from 0 to {MAX_ROW_ID})")
    return n


def _shown(limit: int | None) -> str:
    from ..service.config import shown_limit

    return "default" if limit is None else str(shown_limit(limit))


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "admin",
        help="manage service accounts, tokens, sessions, the schema and backups",
        description="Manage accounts of `mapfree serve`. Tokens are printed once and stored hashed.",
        epilog="examples:\n"
        "  mapfree admin --db sqlite:///mapfree.db create-user alice --expires-in 90d\n"
        "  mapfree admin --db sqlite:///mapfree.db new-token alice --expires-in 30d --label ci\n"
        "  mapfree admin --db sqlite:///mapfree.db list-tokens alice\n"
        "  mapfree admin --db sqlite:///mapfree.db revoke-token 12\n"
        "  mapfree admin --db sqlite:///mapfree.db revoke-tokens alice\n"
        "  mapfree admin --db sqlite:///mapfree.db set-limit alice 0   # no test evaluations\n"
        "  mapfree admin --db sqlite:///mapfree.db set-limit alice unlimited\n"
        "  mapfree admin --db sqlite:///mapfree.db list-users\n"
        "  mapfree admin --db sqlite:///mapfree.db delete-user alice --yes\n"
        "  mapfree admin --db sqlite:///mapfree.db migrate\n"
        "  mapfree admin --db sqlite:///mapfree.db backup /backups/mapfree-2026-01-31.db\n",
        formatter_class=HelpFormatter,
    )
    p.add_argument(
        "--db",
        default=os.environ.get("MAPFREE_DB", "sqlite:///mapfree.db"),
        help="database URL (default: $MAPFREE_DB or sqlite:///mapfree.db)",
    )
    s = p.add_subparsers(dest="action", metavar="ACTION", required=True)
    expires = {
        "metavar": "DURATION",
        "help": "the token expires after this long (90d, 12h, 30m or seconds; default: never)",
    }
    c = s.add_parser("create-user", help="create an account and print its API token")
    c.add_argument("name")
    c.add_argument("--admin", action="store_true", help="may see every submission and delete any anchor")
    c.add_argument(
        "--test-daily-limit",
        type=_limit,
        default=None,
        metavar="N|unlimited|default",
        help="override the server's daily test limit: a count (0: no test evaluations at all), "
        "'unlimited', or 'default' (the server's, the default)",
    )
    c.add_argument("--expires-in", **expires)
    t = s.add_parser("new-token", help="issue another token for an account")
    t.add_argument("name")
    t.add_argument("--expires-in", **expires)
    t.add_argument("--label", default="", help="what the token is for (shown by list-tokens)")
    r = s.add_parser("revoke-tokens", help="revoke every token of an account (and end its browser sessions)")
    r.add_argument("name")
    s.add_parser("list-tokens", help="an account's tokens: id, prefix, label, created, expires, state").add_argument(
        "name"
    )
    s.add_parser(
        "revoke-token", help="revoke one token (by the id list-tokens shows), and the tokens and sessions made with it"
    ).add_argument("id", type=_row_id)
    s.add_parser("list-sessions", help="an account's open browser sessions").add_argument("name")
    s.add_parser("revoke-session", help="end one browser session (by its id)").add_argument("id", type=_row_id)
    d = s.add_parser("delete-user", help="delete an account with its tokens, sessions, anchors and submissions")
    d.add_argument("name")
    d.add_argument("--yes", action="store_true", help="really delete (without it: say what would go)")
    lim = s.add_parser("set-limit", help="set an account's daily test-evaluation limit")
    lim.add_argument("name")
    lim.add_argument(
        "limit",
        type=_limit,
        metavar="N|unlimited|default",
        help="test evaluations per 24 h: a count (0: none at all), 'unlimited', or 'default' (the "
        "server's --test-daily-limit)",
    )
    s.add_parser("list-users", help="list accounts")
    s.add_parser("init-db", help="create the tables or upgrade them (serve does this too)")
    s.add_parser("migrate", help="upgrade the schema to this version's (serve does this at start) and say so")
    b = s.add_parser("backup", help="consistent copy of the live database (SQLite); pg_dump advice (PostgreSQL)")
    b.add_argument("dest", help="new file to write (never overwritten)")
    p.set_defaults(func=run)


def _when(t: float | None) -> str:
    from ..service.accounts.tokens import utc

    return utc(t) if t else "never"


def run(a: argparse.Namespace) -> int:
    from sqlalchemy import select
    from sqlalchemy.orm import Session

    from ..service.accounts import tokens as auth
    from ..service.database.models import User, session_factory

    if a.action == "backup":  # before any upgrade: a backup is what one takes before upgrading
        from ..service.database.backup import backup

        try:
            print(backup(a.db, a.dest))
        except (OSError, ValueError, RuntimeError) as e:
            return fail("admin", e)
        return 0
    from ..service.database.migrations import SchemaVersion
    from ..service.database.models import DatabaseUnavailable, open_database

    try:
        engine, (before, after) = open_database(a.db)
    except (SchemaVersion, DatabaseUnavailable) as e:
        return fail("admin", e)
    if a.action == "migrate":
        print(f"schema version {after}" + (" (already)" if before == after else f" (was {before or 'unversioned'})"))
        return 0
    sessions = session_factory(engine)

    def user(db: Session, name: str) -> User:
        u = db.scalar(select(User).where(User.name == name))
        if u is None:
            raise LookupError(f"no user {name!r}")
        return u

    def lifetime() -> float | None:
        try:
            return auth.parse_duration(a.expires_in) if a.expires_in else None
        except ValueError as e:
            raise LookupError(f"--expires-in: {e}") from None

    try:
        return _act(a, sessions, user, lifetime, engine)
    except LookupError as e:  # no such user, a bad duration: one line, nothing changed (the transaction rolls back)
        return fail("admin", e.args[0])


def _act(a: argparse.Namespace, sessions, user, lifetime, engine) -> int:
    from sqlalchemy import select

    from ..service.accounts import tokens as auth
    from ..service.database.models import ApiToken, User, WebSession

    with sessions.begin() as db:
        if a.action == "create-user":
            expires_in = lifetime()  # the first token's
            try:
                u, token = auth.create_user(db, a.name, admin=a.admin, expires_in=expires_in)
            except ValueError as e:
                return fail("admin", e)
            u.test_daily_limit = a.test_daily_limit
            print(token)
            print(f"created user {a.name!r}; the token above is shown only once", file=sys.stderr)
        elif a.action == "new-token":
            try:
                print(auth.issue_token(db, user(db, a.name), lifetime(), a.label))
            except auth.TokenLimit as e:
                return fail("admin", e)
        elif a.action == "revoke-tokens":
            print(f"revoked {auth.revoke_tokens(db, user(db, a.name))} token(s)", file=sys.stderr)
        elif a.action == "list-tokens":
            from ..service.accounts.router import list_tokens, token_json

            print("id\tprefix\tlabel\tcreated\texpires\tstate")
            for t in map(token_json, list_tokens(db, user(db, a.name).id)):
                state = "revoked" if t["revoked"] else "expired" if t["expired"] else "active"
                print(
                    f"{t['id']}\t{t['prefix']}…\t{t['label'] or '-'}\t{_when(t['created_at'])}\t"
                    f"{_when(t['expires_at'])}\t{state}"
                )
        elif a.action == "revoke-token":
            row = db.get(ApiToken, a.id)
            if row is None:
                return fail("admin", f"no token {a.id}")
            ended = auth.revoke_token(db, row)
            also = [f"{len(v)} {k} made with it ({', '.join(map(str, v))})" for k, v in ended.items() if v]
            print(
                f"revoked token {a.id} ({row.prefix}…)" + (f" and ended {' and '.join(also)}" if also else ""),
                file=sys.stderr,
            )
        elif a.action == "list-sessions":
            from ..service.accounts.router import list_sessions

            print("id\topened\texpires")
            for w in list_sessions(db, user(db, a.name).id):
                print(f"{w.id}\t{_when(w.created_at)}\t{_when(w.expires_at)}")
        elif a.action == "revoke-session":
            row = db.get(WebSession, a.id)
            if row is None:
                return fail("admin", f"no session {a.id}")
            db.delete(row)
            print(f"ended session {a.id}", file=sys.stderr)
        elif a.action == "delete-user":
            return _delete_user(db, user(db, a.name), a.yes)
        elif a.action == "set-limit":
            user(db, a.name).test_daily_limit = a.limit
            print(f"{a.name}: daily test limit {_shown(a.limit)}", file=sys.stderr)
        elif a.action == "list-users":
            for u in db.scalars(select(User).order_by(User.id)):
                n = len(
                    db.scalars(select(ApiToken.id).where(ApiToken.user_id == u.id, ApiToken.revoked.is_(False))).all()
                )
                print(f"{u.name}\tadmin={u.is_admin}\ttokens={n}\ttest_limit={_shown(u.test_daily_limit)}")
    engine.dispose()
    return 0


def _delete_user(db, u, yes: bool) -> int:
    from sqlalchemy import func, select

    from ..service.accounts.router import delete_user
    from ..service.database.models import User

    if u.is_admin and db.scalar(select(func.count()).select_from(User).where(User.is_admin.is_(True))) == 1:
        return fail("admin", f"{u.name!r} is the only admin; make another admin first")
    name = u.name
    gone = delete_user(db, u, dry_run=not yes)
    what = ", ".join(f"{n} {k}" for k, n in gone.items())
    if not yes:
        print(
            f"would delete user {name!r} with {what} (their leaderboard entries too); add --yes to delete",
            file=sys.stderr,
        )
        return 1
    print(f"deleted user {name!r} with {what}", file=sys.stderr)
    return 0


def main(argv: list[str] | None = None) -> int:
    """``python -m mapfree.cli.admin`` = ``mapfree admin`` without loading the other subcommands."""
    parser = Parser(prog="mapfree")
    register(parser.add_subparsers(dest="command"))
    args = parser.parse_args(["admin", *(sys.argv[1:] if argv is None else argv)])
    return int(args.func(args) or 0)


if __name__ == "__main__":
    raise SystemExit(main())
