"""The schema as it was before migrations existed (every table ``create_all`` made until then).

Each table is created only when missing: a database from before migrations has all or most of them (tables added
over time were created by ``create_all`` at each start), and gains the missing ones here before it is stamped.

Revision ID: 0001
"""

import sqlalchemy as sa
from alembic import op

revision = "0001"
down_revision = None
branch_labels = None
depends_on = None


def _owned_by(target: str) -> sa.ForeignKey:
    """A foreign key whose row goes when ``target``'s row does."""
    return sa.ForeignKey(target, ondelete="CASCADE")


def _tables() -> list[tuple[str, tuple, dict]]:
    return [
        (
            "users",
            (
                sa.Column("id", sa.Integer, primary_key=True, autoincrement=True),
                sa.Column("name", sa.String(64), nullable=False, unique=True),
                sa.Column("is_admin", sa.Boolean, nullable=False),
                sa.Column("test_daily_limit", sa.Integer, nullable=True),
                sa.Column("created_at", sa.Float, nullable=False),
            ),
            {},
        ),
        (
            "api_tokens",
            (
                sa.Column("id", sa.Integer, primary_key=True, autoincrement=True),
                sa.Column("user_id", sa.Integer, _owned_by("users.id"), nullable=False, index=True),
                sa.Column("token_hash", sa.String(64), nullable=False, unique=True),
                sa.Column("prefix", sa.String(16), nullable=False),
                sa.Column("revoked", sa.Boolean, nullable=False),
                sa.Column("created_at", sa.Float, nullable=False),
            ),
            {},
        ),
        (
            "web_sessions",
            (
                sa.Column("id", sa.Integer, primary_key=True, autoincrement=True),
                sa.Column("sid_hash", sa.String(64), nullable=False, unique=True),
                sa.Column("user_id", sa.Integer, _owned_by("users.id"), nullable=False, index=True),
                sa.Column("csrf", sa.String(64), nullable=False),
                sa.Column("expires_at", sa.Float, nullable=False),
            ),
            {},
        ),
        (
            "submissions",
            (
                sa.Column("id", sa.String(32), primary_key=True),
                sa.Column("user_id", sa.Integer, _owned_by("users.id"), nullable=False, index=True),
                sa.Column("split", sa.String(16), nullable=False, index=True),
                sa.Column("name", sa.String(128), nullable=False),
                sa.Column("public", sa.Boolean, nullable=False),
                sa.Column("status", sa.String(16), nullable=False, index=True),
                sa.Column("attempts", sa.Integer, nullable=False),
                sa.Column("worker_id", sa.String(64), nullable=True),
                sa.Column("lease_until", sa.Float, nullable=True),
                sa.Column("error", sa.Text, nullable=True),
                sa.Column("size_bytes", sa.Integer, nullable=False),
                sa.Column("sha256", sa.String(64), nullable=False),
                sa.Column("created_at", sa.Float, nullable=False, index=True),
                sa.Column("started_at", sa.Float, nullable=True),
                sa.Column("finished_at", sa.Float, nullable=True),
            ),
            {},
        ),
        (
            "submission_files",
            (
                sa.Column("submission_id", sa.String(32), _owned_by("submissions.id"), primary_key=True),
                sa.Column("data", sa.LargeBinary, nullable=False),
            ),
            {},
        ),
        (
            "zip_chunks",
            (
                sa.Column(
                    "submission_id",
                    sa.String(32),
                    _owned_by("submission_files.submission_id"),
                    primary_key=True,
                ),
                sa.Column("seq", sa.Integer, primary_key=True),
                sa.Column("data", sa.LargeBinary, nullable=False),
            ),
            {},
        ),
        (
            "results",
            (
                sa.Column("submission_id", sa.String(32), _owned_by("submissions.id"), primary_key=True),
                sa.Column("metrics", sa.JSON, nullable=False),
                sa.Column("per_scene", sa.JSON, nullable=True),
                sa.Column("problems", sa.JSON, nullable=False),
                sa.Column("plot_data", sa.LargeBinary, nullable=True),
                sa.Column("worker_id", sa.String(64), nullable=False),
                sa.Column("attempt", sa.Integer, nullable=False),
                sa.Column("eval_seconds", sa.Float, nullable=False),
                sa.Column("created_at", sa.Float, nullable=False),
            ),
            {},
        ),
        (
            "method_info",
            (
                sa.Column("submission_id", sa.String(32), _owned_by("submissions.id"), primary_key=True),
                sa.Column("description", sa.Text, nullable=False),
                sa.Column("paper_url", sa.String(500), nullable=False),
                sa.Column("code_url", sa.String(500), nullable=False),
                sa.Column("runtime_ms", sa.Float, nullable=True),
                sa.Column("extra_data", sa.Boolean, nullable=False),
            ),
            {},
        ),
        (
            "plots",
            (
                sa.Column("id", sa.Integer, primary_key=True, autoincrement=True),
                sa.Column(
                    "submission_id",
                    sa.String(32),
                    _owned_by("submissions.id"),
                    nullable=False,
                    index=True,
                ),
                sa.Column("name", sa.String(64), nullable=False),
                sa.Column("png", sa.LargeBinary, nullable=False),
                sa.UniqueConstraint("submission_id", "name"),
            ),
            {},
        ),
        (
            "anchors",
            (
                sa.Column("id", sa.String(32), primary_key=True),
                sa.Column("user_id", sa.Integer, _owned_by("users.id"), nullable=False, index=True),
                sa.Column("name", sa.String(128), nullable=False),
                sa.Column("method", sa.String(64), nullable=False),
                sa.Column("intrinsics", sa.JSON, nullable=False),
                sa.Column("image", sa.LargeBinary, nullable=False),
                sa.Column("depth", sa.LargeBinary, nullable=True),
                sa.Column("created_at", sa.Float, nullable=False),
            ),
            {},
        ),
        (
            "anchor_photos",
            (
                sa.Column("anchor_id", sa.String(32), _owned_by("anchors.id"), primary_key=True),
                sa.Column("seq", sa.Integer, primary_key=True),
                sa.Column("intrinsics", sa.JSON, nullable=False),
                sa.Column("pose", sa.JSON, nullable=False),
                sa.Column("image", sa.LargeBinary, nullable=False),
                sa.Column("depth", sa.LargeBinary, nullable=True),
                sa.Column("created_at", sa.Float, nullable=False),
            ),
            {},
        ),
        (
            "anchor_retired_indices",
            (
                sa.Column("anchor_id", sa.String(32), _owned_by("anchors.id"), primary_key=True),
                sa.Column("highest", sa.Integer, nullable=False),
            ),
            {},
        ),
        (
            "workers",
            (
                sa.Column("id", sa.String(64), primary_key=True),
                sa.Column("host", sa.String(128), nullable=False),
                sa.Column("pid", sa.Integer, nullable=False),
                sa.Column("started_at", sa.Float, nullable=False),
                sa.Column("last_seen", sa.Float, nullable=False),
                sa.Column("jobs_done", sa.Integer, nullable=False),
            ),
            {},
        ),
    ]


def upgrade() -> None:
    existing = set(sa.inspect(op.get_bind()).get_table_names())
    for name, columns, kw in _tables():
        if name in existing:
            continue
        op.create_table(name, *columns, **kw)  # with the indexes its columns ask for


def downgrade() -> None:
    raise NotImplementedError("the first schema has nothing to go back to")
