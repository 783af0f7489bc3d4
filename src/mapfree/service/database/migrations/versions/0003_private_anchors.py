"""Anchors may be private: their photos are served to their owner (and admins) only; anyone signed in may still
localize against them.

Revision ID: 0003
"""

import sqlalchemy as sa
from alembic import op

from mapfree.service.database.migrations import add_missing

revision = "0003"
down_revision = "0002"
branch_labels = None
depends_on = None


def upgrade() -> None:
    add_missing("anchors", sa.Column("private", sa.Boolean, nullable=False, server_default=sa.false()))


def downgrade() -> None:
    with op.batch_alter_table("anchors") as t:
        t.drop_column("private")
