"""the decision window opens once the trial's scene is shown: scene deadline, report time, window opening

Revision ID: 0006
Revises: 0005
Create Date: 2026-12-02 00:00:00
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = '0006'
down_revision = '0005'
branch_labels = None
depends_on = None


def upgrade() -> None:
    with op.batch_alter_table('trial', schema=None) as batch_op:
        batch_op.add_column(sa.Column('scene_deadline_at', sa.DateTime(timezone=True), nullable=True))
        batch_op.add_column(sa.Column('scene_shown_at', sa.DateTime(timezone=True), nullable=True))
        batch_op.add_column(sa.Column('window_opened_at', sa.DateTime(timezone=True), nullable=True))
        batch_op.add_column(sa.Column('window_opened_by', sa.String(length=16), nullable=True))


def downgrade() -> None:
    with op.batch_alter_table('trial', schema=None) as batch_op:
        batch_op.drop_column('window_opened_by')
        batch_op.drop_column('window_opened_at')
        batch_op.drop_column('scene_shown_at')
        batch_op.drop_column('scene_deadline_at')
