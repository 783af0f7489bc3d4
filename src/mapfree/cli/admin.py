"""``mapfree admin``: accounts and API tokens of the evaluation server (run on the server's database)."""

from __future__ import annotations

import argparse
import os
import sys

from . import HelpFormatter


def _limit(text: str) -> int | None:
    """A daily test limit: a count (0: none), ``unlimited``, or ``default`` (the server's, None)."""
    if text.strip().lower() == "default":
        return None
    from ..service.config import parse_daily_limit

    try:
        return parse_daily_limit(text)
    except ValueError as e:
        raise argparse.ArgumentTypeError(f"{e}, or 'default'") from None


def _shown(limit: int | None) -> str:
    return "default" if limit is None else ("unlimited" if limit < 0 else str(limit))


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("admin", help="manage service accounts and API tokens",
                       description="Manage accounts of `mapfree serve`. Tokens are printed once and stored hashed.",
                       epilog="examples:\n"
                              "  mapfree admin --db sqlite:///mapfree.db create-user alice\n"
                              "  mapfree admin --db sqlite:///mapfree.db new-token alice\n"
                              "  mapfree admin --db sqlite:///mapfree.db revoke-tokens alice\n"
                              "  mapfree admin --db sqlite:///mapfree.db set-limit alice 0   # no test evaluations\n"
                              "  mapfree admin --db sqlite:///mapfree.db set-limit alice unlimited\n"
                              "  mapfree admin --db sqlite:///mapfree.db list-users\n",
                       formatter_class=HelpFormatter)
    p.add_argument("--db", default=os.environ.get("MAPFREE_DB", "sqlite:///mapfree.db"),
                   help="database URL (default: $MAPFREE_DB or sqlite:///mapfree.db)")
    s = p.add_subparsers(dest="action", metavar="ACTION", required=True)
    c = s.add_parser("create-user", help="create an account and print its API token")
    c.add_argument("name")
    c.add_argument("--admin", action="store_true", help="may see every submission and delete any anchor")
    c.add_argument("--test-daily-limit", type=_limit, default=None, metavar="N|unlimited|default",
                   help="override the server's daily test limit: a count (0: no test evaluations at all), "
                        "'unlimited', or 'default' (the server's, the default)")
    t = s.add_parser("new-token", help="issue another token for an account")
    t.add_argument("name")
    r = s.add_parser("revoke-tokens", help="revoke every token of an account")
    r.add_argument("name")
    lim = s.add_parser("set-limit", help="set an account's daily test-evaluation limit")
    lim.add_argument("name")
    lim.add_argument("limit", type=_limit, metavar="N|unlimited|default",
                     help="test evaluations per 24 h: a count (0: none at all), 'unlimited', or 'default' (the "
                          "server's --test-daily-limit)")
    s.add_parser("list-users", help="list accounts")
    s.add_parser("init-db", help="create the tables (serve does this too)")
    p.set_defaults(func=run)


def run(a: argparse.Namespace) -> int:
    from sqlalchemy import select

    from ..service import auth
    from ..service.db import ApiToken, User, init_db, make_engine, session_factory

    engine = make_engine(a.db)
    init_db(engine)
    sessions = session_factory(engine)

    def user(db, name):
        u = db.scalar(select(User).where(User.name == name))
        if u is None:
            raise SystemExit(f"error: no user {name!r}")
        return u

    with sessions.begin() as db:
        if a.action == "create-user":
            try:
                u, token = auth.create_user(db, a.name, admin=a.admin)
            except ValueError as e:
                print(f"error: {e}", file=sys.stderr)
                return 1
            u.test_daily_limit = a.test_daily_limit
            print(token)
            print(f"created user {a.name!r}; the token above is shown only once", file=sys.stderr)
        elif a.action == "new-token":
            print(auth.issue_token(db, user(db, a.name)))
        elif a.action == "revoke-tokens":
            print(f"revoked {auth.revoke_tokens(db, user(db, a.name))} token(s)", file=sys.stderr)
        elif a.action == "set-limit":
            user(db, a.name).test_daily_limit = a.limit
            print(f"{a.name}: daily test limit {_shown(a.limit)}", file=sys.stderr)
        elif a.action == "list-users":
            for u in db.scalars(select(User).order_by(User.id)):
                n = len(db.scalars(select(ApiToken.id).where(ApiToken.user_id == u.id,
                                                            ApiToken.revoked.is_(False))).all())
                print(f"{u.name}\tadmin={u.is_admin}\ttokens={n}\ttest_limit={_shown(u.test_daily_limit)}")
    engine.dispose()
    return 0


def main(argv: list[str] | None = None) -> int:
    """``python -m mapfree.cli.admin`` = ``mapfree admin`` without loading the other subcommands."""
    parser = argparse.ArgumentParser(prog="mapfree")
    register(parser.add_subparsers(dest="command"))
    args = parser.parse_args(["admin", *(sys.argv[1:] if argv is None else argv)])
    return int(args.func(args) or 0)


if __name__ == "__main__":
    raise SystemExit(main())
