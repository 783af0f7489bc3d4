"""API tokens may expire (``expires_at``; NULL: never) and carry a label; browser sessions record when they were
opened, so that an account's tokens and sessions can be listed and revoked one by one.

Revision ID: 0002
"""

import sqlalchemy as sa
from alembic import op

from mapfree.service.database.migrations import add_missing

revision = "0002"
down_revision = "0001"
branch_labels = None
depends_on = None


def upgrade() -> None:
    add_missing(
        "api_tokens",
        sa.Column("expires_at", sa.Float, nullable=True),
        sa.Column("label", sa.String(64), nullable=False, server_default=""),
    )
    add_missing("web_sessions", sa.Column("created_at", sa.Float, nullable=True))


def downgrade() -> None:
    with op.batch_alter_table("web_sessions") as t:
        t.drop_column("created_at")
    with op.batch_alter_table("api_tokens") as t:
        t.drop_column("label")
        t.drop_column("expires_at")
