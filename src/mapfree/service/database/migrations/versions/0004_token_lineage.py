"""Token lineage: a token records the token it was created with (``parent_id``), a browser session the token it
was signed in with (``token_id``), so that revoking a token ends what it made, and nothing made with a token
outlives it.

Revision ID: 0004
"""

import sqlalchemy as sa
from alembic import op

from mapfree.service.database.migrations import add_missing

revision = "0004"
down_revision = "0003"
branch_labels = None
depends_on = None


def upgrade() -> None:
    add_missing("api_tokens", sa.Column("parent_id", sa.Integer, nullable=True))
    add_missing("web_sessions", sa.Column("token_id", sa.Integer, nullable=True))


def downgrade() -> None:
    with op.batch_alter_table("web_sessions") as t:
        t.drop_column("token_id")
    with op.batch_alter_table("api_tokens") as t:
        t.drop_column("parent_id")
