"""Anchors may carry their own calibrations (uploaded ``.calib.json`` files, else their method's shipped ones)
and an accept threshold on ``p_correct``.

Revision ID: 0005
"""

import sqlalchemy as sa
from alembic import op

from mapfree.service.database.migrations import add_missing

revision = "0005"
down_revision = "0004"
branch_labels = None
depends_on = None


def upgrade() -> None:
    add_missing("anchors", sa.Column("calibration", sa.JSON, nullable=True))
    add_missing("anchors", sa.Column("accept", sa.Float, nullable=True))


def downgrade() -> None:
    with op.batch_alter_table("anchors") as t:
        t.drop_column("accept")
        t.drop_column("calibration")
